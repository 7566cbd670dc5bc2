"""Stage registry: stage classes found through the ``expression_mapping.stages`` entry points.

Built-in stages are registered exactly like third-party ones: an entry point whose name is the
stage's registered name and whose value is ``module:Class``, e.g.

.. code-block:: toml

    [project.entry-points."expression_mapping.stages"]
    "video.decode" = "stages.video:VideoDecode"

Classes are imported only when asked for, so running a pipeline imports the modules of the
stages it uses and nothing else (a torch stage elsewhere costs nothing to a video-only run).
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Iterable, Mapping

from runner.bundle import BundleType
from runner.stage import RUNNER_TYPES, THREADING, FrameStage, Param, SequenceStage, Stage, value_has_type

ENTRY_POINT_GROUP = "expression_mapping.stages"
PARAM_TYPES = (int, float, str, bool, list)


class RegistryError(Exception):
    """A registered stage cannot be loaded or declares an invalid contract."""


class Registry:
    """Registered stages by name.

    Parameters
    ----------
    entry_points
        ``{name: "module:Class"}`` targets, imported lazily by :meth:`get`.
    classes
        Stage classes registered directly (tests, embedding applications).
    """

    def __init__(self, *, entry_points: Mapping[str, str] | None = None, classes: Iterable[type[Stage]] = ()):
        self._targets: dict[str, str] = dict(entry_points or {})
        self._loaded: dict[str, type[Stage]] = {}
        for cls in classes:
            self.register(cls)

    @classmethod
    def from_entry_points(cls) -> Registry:
        """The stages every installed distribution declares in :data:`ENTRY_POINT_GROUP`."""
        targets: dict[str, str] = {}
        for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
            if ep.name in targets and targets[ep.name] != ep.value:
                raise RegistryError(f"stage {ep.name!r} is registered twice: {targets[ep.name]} and {ep.value}")
            targets[ep.name] = ep.value
        return cls(entry_points=targets)

    def register(self, stage_cls: type[Stage]) -> None:
        """Register a class directly under its declared name."""
        check_stage_class(stage_cls)
        self._loaded[stage_cls.name] = stage_cls

    def names(self) -> list[str]:
        return sorted(set(self._targets) | set(self._loaded))

    def __contains__(self, name: str) -> bool:
        return name in self._targets or name in self._loaded

    def get(self, name: str) -> type[Stage]:
        """The class registered as ``name`` (imported on first use); KeyError if unknown."""
        if name in self._loaded:
            return self._loaded[name]
        target = self._targets[name]
        module_name, _, attr = target.partition(":")
        try:
            obj = importlib.import_module(module_name)
            for part in attr.split("."):
                obj = getattr(obj, part)
        except (ImportError, AttributeError) as exc:
            raise RegistryError(f"stage {name!r}: cannot load {target}: {exc}") from exc
        if not (isinstance(obj, type) and issubclass(obj, Stage)):
            raise RegistryError(f"stage {name!r}: {target} is not a Stage subclass")
        check_stage_class(obj)
        if obj.name != name:
            raise RegistryError(f"entry point {name!r} points at {target}, whose name is {obj.name!r}")
        self._loaded[name] = obj
        return obj


def _port_type(kind: object) -> bool:
    """Whether ``kind`` is one port type: a non-empty string, or a bundle type not named as a runner type."""
    if isinstance(kind, BundleType):
        return bool(kind.name) and kind.name not in RUNNER_TYPES
    return isinstance(kind, str) and bool(kind)


def check_stage_class(stage_cls: type[Stage]) -> None:
    """Raise :class:`RegistryError` unless the class declares a complete, well-typed contract."""
    where = f"{stage_cls.__module__}.{stage_cls.__qualname__}"
    if not issubclass(stage_cls, (SequenceStage, FrameStage)):
        raise RegistryError(f"{where}: derive from SequenceStage or FrameStage")
    for attr in ("name", "version"):
        if not isinstance(getattr(stage_cls, attr, None), str) or not getattr(stage_cls, attr):
            raise RegistryError(f"{where}: class attribute {attr!r} must be a non-empty string")
    for port, kind in stage_cls.inputs.items():
        accepted = kind if isinstance(kind, tuple) and kind and all(isinstance(t, BundleType) for t in kind) else (kind,)
        if not (isinstance(port, str) and all(_port_type(t) for t in accepted)):
            raise RegistryError(f"{where}: input {port!r} must map a name to a type string, a BundleType or a tuple of them")
    for port, kind in stage_cls.outputs.items():
        if not (isinstance(port, str) and _port_type(kind)):
            raise RegistryError(f"{where}: output {port!r} must map a name to a type string or a BundleType")
    for kind in stage_cls.outputs.values():
        if kind in ("video", "file", "dir"):
            raise RegistryError(f"{where}: {kind!r} is a pipeline-input type, not an output type")
        if kind == "frames" and not issubclass(stage_cls, FrameStage):
            raise RegistryError(f"{where}: only frame stages produce 'frames' outputs")
        if issubclass(stage_cls, FrameStage) and not stage_cls.cached and kind != "frames":
            raise RegistryError(f"{where}: a stage with cached = False may only have 'frames' outputs")
    if (
        issubclass(stage_cls, FrameStage)
        and "frames" not in stage_cls.inputs.values()
        and stage_cls.stream_info is FrameStage.stream_info
    ):
        raise RegistryError(f"{where}: a frame stage without a frames input must define stream_info")
    if stage_cls.threading not in THREADING:
        raise RegistryError(f"{where}: class attribute 'threading' must be one of {', '.join(map(repr, THREADING))}")
    seen: set[str] = set()
    for param in stage_cls.params:
        if not isinstance(param, Param) or param.type not in PARAM_TYPES:
            raise RegistryError(f"{where}: params must be Param with a type among int, float, str, bool, list")
        if param.name in seen:
            raise RegistryError(f"{where}: parameter {param.name!r} declared twice")
        seen.add(param.name)
        if not value_has_type(param.default, param.type):
            raise RegistryError(f"{where}: default of {param.name!r} is not a {param.type.__name__}")
        if (param.min is not None or param.max is not None) and param.type not in (int, float):
            raise RegistryError(f"{where}: parameter {param.name!r} has min/max but is not an int or float")
        problem = param.problem(param.default)
        if problem:
            raise RegistryError(f"{where}: default of {param.name!r}: {problem}")
