"""Loading and validating ``pipeline.yaml``: every error found, each with file, line and column.

Schema
------
.. code-block:: yaml

    extends: pipeline.yaml           # optional: laid over this base pipeline (see _overlay)
    chunk_frames: 16                 # optional: frames per chunk of frame stages (default 16)
    inputs:                          # pipeline inputs, bound on the command line
      clip: {type: video}            # `--in PATH` binds the (single) video input
      target: {type: dir, default: fixtures/packs/target}   # relative to this file's folder
    stages:                          # named stages; the DAG follows from the references
      decode:
        uses: video.decode           # registered stage name (`runner stages` lists them)
        inputs: {video: clip}        # a bare name references a pipeline input
      gray:
        uses: image.gray
        inputs: {frames: decode.frames}   # `stage.port` references another stage's output
      write:
        uses: write.video
        params: {codec: h264, crf: 18}
        inputs: {frames: gray.frames}

The file is read with :func:`runner.safe_yaml.compose` (the safe loader without aliases or
unknown tags) so that each node keeps its position; values are built with the safe constructor
only. A file that ``extends:`` another is first resolved to one node tree, each node keeping its
position in the file that wrote it (:func:`_overlay`; docs/runner.md, "extends:").
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import yaml

from runner import safe_yaml
from runner.bundle import PortType, accepts, describe
from runner.dag import CycleError, topological_order
from runner.files import kind_problem
from runner.registry import Registry, RegistryError
from runner.stage import FrameStage, Param, Stage, shown, value_has_type

DEFAULT_CHUNK_FRAMES = 16
INPUT_TYPES = ("video", "file", "dir")
NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_-]*$")
TOP_KEYS = ("extends", "chunk_frames", "inputs", "stages")
STAGE_KEYS = ("uses", "params", "inputs")
INPUT_KEYS = ("type", "default", "help")


@dataclass(frozen=True)
class Where:
    """A position in a file (1-based line and column); line 0 = the command line."""

    file: str
    line: int = 0
    column: int = 0

    def __str__(self) -> str:
        return f"{self.file}:{self.line}:{self.column}" if self.line else self.file


@dataclass(frozen=True)
class Issue:
    where: Where
    key: str
    message: str

    def __str__(self) -> str:
        return f"{self.where}: {self.key}: {self.message}"


class ConfigError(Exception):
    """The pipeline (or the command line that completes it) is invalid; exit code 2."""

    def __init__(self, issues: list[Issue]):
        self.issues = sorted(issues, key=lambda i: (i.where.file, i.where.line, i.where.column))
        super().__init__("\n".join(str(i) for i in self.issues))


@dataclass(frozen=True)
class Ref:
    """A reference to a stage output (``stage.port``) or, with ``stage=None``, a pipeline input."""

    stage: str | None
    port: str
    where: Where

    def __str__(self) -> str:
        return f"{self.stage}.{self.port}" if self.stage else self.port


@dataclass
class PipelineInput:
    name: str
    type: str
    default: Path | None
    help: str
    where: Where


@dataclass
class StageNode:
    """One named stage of the pipeline: the class it uses, its parameters (defaults filled in),
    and what each input port is connected to."""

    name: str
    uses: str
    cls: type[Stage]
    params: dict[str, Any]
    inputs: dict[str, Ref]
    where: Where
    param_where: dict[str, Where] = field(default_factory=dict)


@dataclass
class Pipeline:
    path: Path
    chunk_frames: int
    inputs: dict[str, PipelineInput]
    stages: dict[str, StageNode]  # in topological order
    edges: list[tuple[str, str]]  # (upstream stage, downstream stage)

    def upstream(self, name: str) -> list[str]:
        return [a for a, b in self.edges if b == name]

    def ancestors(self, name: str) -> set[str]:
        """``name`` and every stage it depends on."""
        seen, todo = {name}, [name]
        while todo:
            for up in self.upstream(todo.pop()):
                if up not in seen:
                    seen.add(up)
                    todo.append(up)
        return seen


def _where(node: yaml.Node) -> Where:
    """The position of ``node`` in the file that wrote it (its marks are named by the file)."""
    return Where(node.start_mark.name, node.start_mark.line + 1, node.start_mark.column + 1)


class _Reader:
    """Walks the composed node tree, collecting issues instead of stopping at the first."""

    def __init__(self) -> None:
        self.issues: list[Issue] = []
        self._constructor = yaml.SafeLoader("")

    def error(self, node: yaml.Node | Where, key: str, message: str) -> None:
        where = node if isinstance(node, Where) else _where(node)
        self.issues.append(Issue(where, key, message))

    def value(self, node: yaml.Node) -> Any:
        return self._constructor.construct_object(node, deep=True)

    def mapping(self, node: yaml.Node, key: str, allowed: tuple[str, ...] | None) -> list[tuple[str, yaml.Node, yaml.Node]]:
        """Entries ``(name, key node, value node)`` of a mapping node; reports non-mappings and,
        when ``allowed`` is given, unknown keys."""
        if isinstance(node, yaml.ScalarNode) and node.tag == "tag:yaml.org,2002:null":
            return []
        if not isinstance(node, yaml.MappingNode):
            self.error(node, key, "expected a mapping")
            return []
        entries = []
        for knode, vnode in node.value:  # no key twice: refused by runner.safe_yaml
            name = str(self.value(knode))
            sub = f"{key}.{name}" if key else name
            if allowed is not None and name not in allowed:
                self.error(knode, sub, f"unknown key (expected one of: {', '.join(allowed)})")
                continue
            entries.append((name, knode, vnode))
        return entries


def load_pipeline(path: Path, registry: Registry, *, overrides: Sequence[str] = ()) -> Pipeline:
    """Read, validate and resolve a pipeline file.

    Parameters
    ----------
    path
        The ``pipeline.yaml`` to read.
    registry
        Where stage names are looked up.
    overrides
        ``--set`` values, ``"stage.param=value"``, typed by the parameter's schema.

    Raises
    ------
    ConfigError
        With every problem found: unknown stage, unknown parameter, wrong type, missing input,
        port type mismatch, cycle, duplicate name.
    """
    path = Path(path)
    r = _Reader()
    root = _resolve_extends(r, read_yaml_file(path), path, [path.resolve()])
    top = {name: (knode, vnode) for name, knode, vnode in r.mapping(root, "", TOP_KEYS)}

    chunk_frames = DEFAULT_CHUNK_FRAMES
    if "chunk_frames" in top:
        node = top["chunk_frames"][1]
        value = r.value(node)
        if not (value_has_type(value, int) and value > 0):
            r.error(node, "chunk_frames", f"wrong type: expected a positive int, got {shown(value)}")
        else:
            chunk_frames = value

    inputs = _read_inputs(r, top["inputs"][1] if "inputs" in top else None)
    if "stages" not in top:
        r.error(root, "stages", "missing: a pipeline needs a `stages` mapping")
        raise ConfigError(r.issues)
    stages = _read_stages(r, top["stages"][1], registry, inputs)
    _apply_overrides(r, stages, overrides)
    _check_references(r, stages, inputs)
    if r.issues:
        raise ConfigError(r.issues)

    edges = [(ref.stage, node.name) for node in stages.values() for ref in node.inputs.values() if ref.stage]
    edges = list(dict.fromkeys(edges))
    try:
        order = topological_order(list(stages), edges)
    except CycleError as exc:
        first = stages[exc.cycle[0]]
        ref = next(ref for ref in first.inputs.values() if ref.stage == exc.cycle[-1])
        cycle = " -> ".join([*exc.cycle, exc.cycle[0]])
        raise ConfigError([Issue(ref.where, f"stages.{first.name}.inputs", f"cycle: {cycle}")]) from None
    return Pipeline(
        path=path, chunk_frames=chunk_frames, inputs=inputs, stages={name: stages[name] for name in order}, edges=edges
    )


def _read_inputs(r: _Reader, node: yaml.Node | None) -> dict[str, PipelineInput]:
    inputs: dict[str, PipelineInput] = {}
    if node is None:
        return inputs
    for name, knode, vnode in r.mapping(node, "inputs", None):
        key = f"inputs.{name}"
        if not NAME_RE.match(name):
            r.error(knode, key, "invalid name (letters, digits, '_' and '-'; no dots)")
            continue
        fields = {f: (k, v) for f, k, v in r.mapping(vnode, key, INPUT_KEYS)}
        if "type" not in fields:
            r.error(vnode, f"{key}.type", f"missing: one of {', '.join(INPUT_TYPES)}")
            continue
        kind = r.value(fields["type"][1])
        if kind not in INPUT_TYPES:
            r.error(fields["type"][1], f"{key}.type", f"wrong type: expected one of {', '.join(INPUT_TYPES)}, got {kind!r}")
            continue
        default = None
        if "default" in fields:
            value = r.value(fields["default"][1])
            if not isinstance(value, str):
                r.error(fields["default"][1], f"{key}.default", f"wrong type: expected a path string, got {shown(value)}")
                continue
            base = Path(fields["default"][1].start_mark.name).parent  # the folder of the file that wrote it
            default = (base / value) if not Path(value).is_absolute() else Path(value)
        text = str(r.value(fields["help"][1])) if "help" in fields else ""
        inputs[name] = PipelineInput(name, kind, default, text, _where(knode))
    return inputs


def read_yaml_file(
    path: Path, *, extended_at: yaml.Node | None = None, empty: tuple[str, str] = ("stages", "empty pipeline file")
) -> yaml.Node:
    """The node tree of the YAML file ``path`` (a pipeline or a batch manifest; its marks named
    ``str(path)``).

    Raises :class:`ConfigError` if it cannot be read, is not YAML or is empty (``empty``: the key
    and message of that error); positioned at ``extended_at`` (the ``extends:`` value naming it)
    when it is a base file that cannot be read."""
    shown = str(path)
    try:
        root = safe_yaml.compose(safe_yaml.read_text(path), name=shown)
    except OSError as exc:
        if extended_at is None:
            raise ConfigError([Issue(Where(shown), "file", f"cannot read: {exc.strerror}")]) from None
        raise ConfigError([Issue(_where(extended_at), "extends", f"cannot read {shown}: {exc.strerror}")]) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = Where(shown, mark.line + 1, mark.column + 1) if mark else Where(shown)
        raise ConfigError([Issue(where, "yaml", safe_yaml.error_message(exc))]) from None
    if root is None:
        raise ConfigError([Issue(Where(shown), *empty)])
    return root


def _resolve_extends(r: _Reader, root: yaml.Node, path: Path, chain: list[Path]) -> yaml.Node:
    """``root`` (the tree of ``path``) with its ``extends:`` resolved: the base pipeline's tree,
    itself resolved, overlaid with ``root``'s other entries (:func:`_overlay`). ``chain`` holds the
    resolved files extending down to ``path``, which must not name one of them again."""
    if not isinstance(root, yaml.MappingNode):
        return root  # reported by the reader
    named = [(k, v) for k, v in root.value if isinstance(k, yaml.ScalarNode) and k.value == "extends"]
    if not named:
        return root
    vnode = named[0][1]
    rest = yaml.MappingNode(root.tag, [e for e in root.value if e is not named[0]], start_mark=root.start_mark)
    value = r.value(vnode)
    if not isinstance(value, str) or not value:
        r.error(vnode, "extends", f"wrong type: expected the path of a pipeline file, got {shown(value)}")
        raise ConfigError(r.issues)
    base_path = Path(value) if Path(value).is_absolute() else path.parent / value
    if base_path.resolve() in chain:
        cycle = " -> ".join(str(p) for p in [*chain, base_path.resolve()])
        r.error(vnode, "extends", f"cycle of extends: {cycle}")
        raise ConfigError(r.issues)
    base = read_yaml_file(base_path, extended_at=vnode)
    if not isinstance(base, yaml.MappingNode):
        r.error(vnode, "extends", f"{base_path} is not a pipeline (expected a mapping)")
        raise ConfigError(r.issues)
    base = _resolve_extends(r, base, base_path, [*chain, base_path.resolve()])
    return _overlay(r, base, rest, levels=4, key="")


def _overlay(r: _Reader, base: yaml.Node, child: yaml.Node, *, levels: int, key: str) -> yaml.Node:
    """``child`` laid over ``base``, mapping by mapping for ``levels`` levels (the top keys, the
    names of stages and inputs, a stage's ``uses``/``params``/``inputs``, the names of parameters
    and ports): a key of ``child`` replaces (or, if both are mappings, is laid over) the base's
    value in its place, a new key is added after the base's, and a key whose value is null removes
    the base's. Below ``levels`` (a parameter's value) ``child`` replaces ``base`` whole. Every node
    keeps the marks of the file that wrote it."""
    if levels == 0 or not (isinstance(base, yaml.MappingNode) and isinstance(child, yaml.MappingNode)):
        return child
    entries = {str(r.value(k)): (k, v) for k, v in base.value}
    for knode, vnode in child.value:
        name = str(r.value(knode))
        sub = f"{key}.{name}" if key else name
        if isinstance(vnode, yaml.ScalarNode) and vnode.tag == "tag:yaml.org,2002:null":
            if entries.pop(name, None) is None:
                r.error(vnode, sub, f"nothing to remove: {base.start_mark.name} has no {sub}")
        elif name in entries:
            entries[name] = (knode, _overlay(r, entries[name][1], vnode, levels=levels - 1, key=sub))
        else:
            entries[name] = (knode, vnode)
    return yaml.MappingNode(child.tag, list(entries.values()), start_mark=child.start_mark)


def _read_stages(r: _Reader, node: yaml.Node, registry: Registry, inputs: dict[str, PipelineInput]) -> dict[str, StageNode]:
    stages: dict[str, StageNode] = {}
    entries = r.mapping(node, "stages", None)
    if not entries and not r.issues:
        r.error(node, "stages", "missing: no stages declared")
    for name, knode, vnode in entries:
        key = f"stages.{name}"
        if not NAME_RE.match(name):
            r.error(knode, key, "invalid name (letters, digits, '_' and '-'; no dots)")
            continue
        if name in inputs:
            r.error(knode, key, f"duplicate name: {name!r} is also a pipeline input")
            continue
        fields = {f: (k, v) for f, k, v in r.mapping(vnode, key, STAGE_KEYS)}
        if "uses" not in fields:
            r.error(vnode, f"{key}.uses", "missing: the registered stage this step uses")
            continue
        uses_node = fields["uses"][1]
        uses = r.value(uses_node)
        if not isinstance(uses, str) or uses not in registry:
            r.error(uses_node, f"{key}.uses", f"unknown stage {uses!r} (see `runner stages`)")
            continue
        try:
            cls = registry.get(uses)
        except RegistryError as exc:
            r.error(uses_node, f"{key}.uses", str(exc))
            continue
        stage = StageNode(
            name=name, uses=uses, cls=cls, params={p.name: p.default for p in cls.params}, inputs={}, where=_where(knode)
        )
        schema = {p.name: p for p in cls.params}
        if "params" in fields:
            for pname, pknode, pvnode in r.mapping(fields["params"][1], f"{key}.params", None):
                pkey = f"{key}.params.{pname}"
                if pname not in schema:
                    known = ", ".join(schema) or "none"
                    r.error(pknode, pkey, f"unknown parameter of {uses} (known: {known})")
                    continue
                value = r.value(pvnode)
                problem = _param_problem(schema[pname], value)
                if problem:
                    r.error(pvnode, pkey, problem)
                    continue
                stage.params[pname] = float(value) if schema[pname].type is float else value
                stage.param_where[pname] = _where(pvnode)
        if "inputs" in fields:
            for port, pknode, pvnode in r.mapping(fields["inputs"][1], f"{key}.inputs", None):
                pkey = f"{key}.inputs.{port}"
                if port not in cls.inputs:
                    r.error(pknode, pkey, f"unknown input port of {uses} (ports: {', '.join(cls.inputs) or 'none'})")
                    continue
                text = r.value(pvnode)
                if not isinstance(text, str) or text.count(".") > 1 or not all(map(NAME_RE.match, text.split("."))):
                    r.error(pvnode, pkey, f"wrong type: expected `stage.port` or an input name, got {text!r}")
                    continue
                upstream, _, out_port = text.rpartition(".")
                stage.inputs[port] = Ref(upstream or None, out_port, _where(pvnode))
        for port in cls.inputs:
            if port not in stage.inputs and port not in cls.optional_inputs:
                r.error(
                    vnode, f"{key}.inputs.{port}", f"missing input: {uses} needs port {port!r} ({describe(cls.inputs[port])})"
                )
        stages[name] = stage
    return stages


def _param_problem(param: Param, value: Any) -> str | None:
    """Why ``value`` is not allowed for ``param``: its type, its declared values, or, for a
    ``file=True`` parameter naming an existing path, that path not being a regular file."""
    if not value_has_type(value, param.type):
        return f"wrong type: expected {param.type.__name__}, got {type(value).__name__} {shown(value)}"
    if param.file and isinstance(value, str) and os.path.lexists(value):
        problem = kind_problem(value)
        if problem:
            return f"wrong value: {shown(value)}: {problem}"
    return param.problem(value)


def _parse_typed(text: str, kind: type) -> Any:
    """Convert a ``--set`` string to ``kind``; ValueError if it does not parse."""
    if kind is str:
        return text
    if kind is bool:
        words = {"true": True, "yes": True, "on": True, "1": True, "false": False, "no": False, "off": False, "0": False}
        if text.lower() not in words:
            raise ValueError(text)
        return words[text.lower()]
    if kind is list:
        value = safe_yaml.load(text)
        if not isinstance(value, list):
            raise ValueError(text)
        return value
    return kind(text)


def _apply_overrides(r: _Reader, stages: dict[str, StageNode], overrides: Sequence[str]) -> None:
    for text in overrides:
        where = Where("--set")
        target, eq, raw = text.partition("=")
        stage_name, dot, pname = target.partition(".")
        if not (eq and dot and stage_name and pname):
            r.error(where, text, "expected --set stage.param=value")
            continue
        if stage_name not in stages:
            r.error(where, target, f"unknown stage {stage_name!r} in this pipeline")
            continue
        stage = stages[stage_name]
        schema = {p.name: p for p in stage.cls.params}
        if pname not in schema:
            r.error(where, target, f"unknown parameter of {stage.uses} (known: {', '.join(schema) or 'none'})")
            continue
        try:
            value = _parse_typed(raw, schema[pname].type)
        except (ValueError, yaml.YAMLError):
            r.error(where, target, f"wrong type: expected {schema[pname].type.__name__}, got {shown(raw)}")
            continue
        problem = _param_problem(schema[pname], value)
        if problem:
            r.error(where, target, problem)
            continue
        stage.params[pname] = value
        stage.param_where[pname] = where


def _check_references(r: _Reader, stages: dict[str, StageNode], inputs: dict[str, PipelineInput]) -> None:
    for stage in stages.values():
        for port, ref in stage.inputs.items():
            key = f"stages.{stage.name}.inputs.{port}"
            expected = stage.cls.inputs[port]
            if ref.stage is None:
                if ref.port not in inputs:
                    r.error(ref.where, key, f"missing input: no pipeline input or stage output named {ref.port!r}")
                    continue
                got: PortType = inputs[ref.port].type
            else:
                if ref.stage not in stages:
                    r.error(ref.where, key, f"missing input: no stage named {ref.stage!r}")
                    continue
                outputs = stages[ref.stage].cls.outputs
                if ref.port not in outputs:
                    r.error(
                        ref.where,
                        key,
                        f"missing input: {ref.stage} ({stages[ref.stage].uses}) has no output "
                        f"{ref.port!r} (outputs: {', '.join(outputs) or 'none'})",
                    )
                    continue
                got = outputs[ref.port]
                if got == "files" and issubclass(stages[ref.stage].cls, FrameStage):
                    r.error(
                        ref.where,
                        key,
                        f"port type mismatch: {ref} is written chunk by chunk and is only "
                        "published to --out, not passed to other stages",
                    )
                    continue
            if not accepts(expected, got):
                r.error(ref.where, key, f"port type mismatch: {port!r} takes {describe(expected)}, {ref} gives {describe(got)}")


def clip_inputs(pipeline: Pipeline) -> list[str]:
    """The inputs ``--in`` may bind: the pipeline's ``video`` inputs, or, in a pipeline without
    one (a folder of photos as the footage, ``pack_build_photos.yaml``), its ``dir`` inputs.
    ``--in`` binds when this names exactly one."""
    for kind in ("video", "dir"):
        names = [i.name for i in pipeline.inputs.values() if i.type == kind]
        if names:
            return names
    return []


def _input_problem(kind: PortType, path: Path) -> tuple[str, str] | None:
    """Why ``path`` cannot be a pipeline input of type ``kind`` (``video`` and ``file``: a
    regular file; ``dir``: a folder), as ``(what, why)``: ``("missing input", "no such
    file")``, ``("wrong input", "a FIFO (named pipe), not a regular file")``; None if it can."""
    if kind == "dir":
        if path.is_dir():
            return None
        if not path.exists():
            return "missing input", "no such folder"
        return "wrong input", "a file, not a folder" if path.is_file() else (kind_problem(path) or "not a folder")
    problem = kind_problem(path)
    if problem is None:
        return None
    return ("missing input" if problem == "no such file" else "wrong input"), problem


def _readers_problems(pipeline: Pipeline, name: str, path: Path) -> list[str]:
    """Why the stages that read pipeline input ``name`` cannot read ``path``
    (:meth:`runner.stage.Stage.check_input`), one line per problem, each given once."""
    problems = (
        node.cls.check_input(port, path)
        for node in pipeline.stages.values()
        for port, ref in node.inputs.items()
        if ref.stage is None and ref.port == name
    )
    return list(dict.fromkeys(f"wrong input: {why}" for why in problems if why is not None))


def bind_inputs(pipeline: Pipeline, *, clip: Path | None, named: list[str]) -> dict[str, Path]:
    """Paths for every pipeline input: ``--in`` for the clip input (:func:`clip_inputs`),
    ``--input NAME=PATH`` for any, else the declared default. Raises :class:`ConfigError` naming
    what is missing, and what a stage reading an input finds wrong with it
    (:meth:`runner.stage.Stage.check_input`: a pack's manifest)."""
    issues: list[Issue] = []
    values: dict[str, Path | None] = {}
    clip_names = clip_inputs(pipeline)
    if clip is not None:
        if len(clip_names) != 1:
            issues.append(
                Issue(
                    Where("--in"),
                    "--in",
                    f"the pipeline has {len(clip_names)} clip inputs "
                    f"({', '.join(clip_names) or 'no video or folder input'}); "
                    "name one with --input NAME=PATH",
                )
            )
        else:
            values[clip_names[0]] = Path(clip)
    for text in named:
        name, eq, value = text.partition("=")
        if not eq or not value:
            issues.append(Issue(Where("--input"), text, "expected --input NAME=PATH"))
        elif name not in pipeline.inputs:
            issues.append(
                Issue(Where("--input"), name, f"unknown pipeline input (declared: {', '.join(pipeline.inputs) or 'none'})")
            )
        else:
            values[name] = Path(value)
    for decl in pipeline.inputs.values():
        values.setdefault(decl.name, decl.default)
        path = values[decl.name]
        flag = "--in" if clip_names == [decl.name] else f"--input {decl.name}=PATH"
        if path is None:
            issues.append(Issue(decl.where, f"inputs.{decl.name}", f"missing input: no value given (use {flag})"))
        else:
            problem = _input_problem(decl.type, path)
            if problem:
                issues.append(Issue(decl.where, f"inputs.{decl.name}", f"{problem[0]}: {path}: {problem[1]}"))
            else:
                issues.extend(
                    Issue(decl.where, f"inputs.{decl.name}", why) for why in _readers_problems(pipeline, decl.name, path)
                )
    if issues:
        raise ConfigError(issues)
    return cast("dict[str, Path]", values)  # a missing value is an issue above
