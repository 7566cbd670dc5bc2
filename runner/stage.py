"""The stage contract: what a stage declares before any data flows, and what it is handed.

A stage is a class with class-level declarations (name, version, ports, parameters) and one
method that does the work. The runner checks a pipeline against these declarations when the
graph is loaded, and owns everything about files, caching and scheduling; a stage only sees
values on its ports.

Port types
----------
A port type is a string or a declared bundle type (:mod:`runner.bundle`). Five strings have a
fixed meaning to the runner:

``video``   a ``pathlib.Path`` to a media file (a pipeline input); digest = file bytes.
``file``    a ``pathlib.Path`` to any other file (a pipeline input, e.g. first-frame points);
            digest = file bytes.
``dir``     a ``pathlib.Path`` to a folder (a pipeline input, e.g. an actor pack); digest = the
            relative paths and bytes of every file under it.
``frames``  a :class:`FrameStream`: images ``(H, W, C)`` produced chunk by chunk by a frame stage.
``files``   a folder of files a stage writes (images, video, tables); the stage writes them under
            ``ctx.files_dir(port)``; the runner keeps them in the cache entry and publishes them to
            ``--out/<stage>/``.

Every other port type is a *bundle*: a ``dict[str, numpy.ndarray]`` stored as ``.npz`` without
pickle (so no object arrays; strings as fixed-width unicode arrays). A bundle's type is a
:class:`runner.bundle.BundleType` declared by the package that produces it (``points``,
``pose_pnp``, ``similarity``…: its fields, dtypes, shapes and units; docs/bundles.md lists them),
or a plain string naming an undeclared bundle. Two ports connect only when the output's type
name is one the input accepts (an input may accept a tuple of bundle types); the runner checks
a declared bundle's fields when the stage's output is stored.

Lifecycle and threads
---------------------
The runner makes one instance of a stage class per pipeline stage and run (and one in each
child process of :mod:`runner.offload` that computes the stage). An instance that computes
anything is opened (:meth:`Stage.open`) before its first ``run`` / ``process`` and closed
(:meth:`Stage.close`) once the run no longer calls it, in a ``finally`` (also after a failure
or an interrupt); one served wholly from the cache is neither opened nor closed.

A sequence stage's ``run`` is called once, on the thread visiting it (the main thread, or the
stage's own thread while it reads a stream being computed). A frame stage's ``process`` is
called from whichever thread needs its chunk: the main thread, ``--jobs`` worker threads
resolving its chunks, its producer threads (``os.cpu_count()`` of them, ``--jobs`` or not)
while other stages read it, the threads of the stages reading it, and a stream's read-ahead
thread. With ``threading = "reentrant"`` (the default) these calls may overlap; with
``"single"`` the runner holds a lock of the instance around each, so one runs at a time (not
always on the same thread). So a reentrant stage keeps no per-call state on ``self``.
Calls outside a run (tests, scripts) go through :func:`runner.lifecycle.opened`.

What a result depends on
------------------------
A stage's cache key covers its inputs, parameters and version (docs/runner.md, "Cache"). A
stage (or a loader it calls) that reads any other file, such as a bundled layout named by a
parameter or a pack manifest, calls :func:`runner.depends.depends_on` with its path; the runner
records the file's digest with the entry and recomputes the entry when the file changes.
"""

from __future__ import annotations

import builtins
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ClassVar, Iterator, Mapping, Protocol

from runner.bundle import BundleType, PortType

if TYPE_CHECKING:  # annotations only: `runner --help` and `runner cache` start without numpy
    import numpy as np

RUNNER_TYPES = ("video", "file", "dir", "frames", "files")
THREADING = ("reentrant", "single")  # the values of Stage.threading


def value_has_type(value: object, expected: type) -> bool:
    """True if ``value`` is acceptable for a parameter of type ``expected`` (ints pass as floats;
    bools never pass as numbers)."""
    if isinstance(value, bool):
        return expected is bool
    if expected is float:
        return isinstance(value, (int, float))
    return isinstance(value, expected)


#: A file name a stage writes under its own folder: no folder part, not hidden, at most 100 characters.
FILE_NAME = r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,99}"
SHOWN = 80  # characters of a value quoted in a message (a longer one is cut, saying its length)


def shown(value: Any) -> str:
    """``repr(value)`` for a message, cut at :data:`SHOWN` characters."""
    text = repr(value)
    return text if len(text) <= SHOWN else f"{text[:SHOWN]}... ({len(text)} characters)"


@dataclass(frozen=True)
class Param:
    """One declared parameter: name, Python type (int, float, str, bool, list), default, help.

    Allowed values: ``choices`` (the value must be one of them), for ``int`` and ``float`` the
    closed range ``[min, max]`` (either bound may be None), for a ``str`` a ``pattern`` (a
    regular expression the whole value must match, e.g. :data:`FILE_NAME`), and for a ``list``
    of names ``items``: the type every item must have, each item given once. The pipeline loader checks them
    (and ``--set`` values) when the graph is loaded, so ``run``/``process`` never see a value
    outside them.

    Cache key (docs/runner.md, "Cache"): the value enters the stage's key unless ``in_key`` is
    False (a setting that cannot change the outputs, such as a thread count). With ``file`` True,
    a value that names an existing file (relative to the working directory, as the stage reads
    it) also adds that file's content digest, so editing the file invalidates the entry.
    """

    name: str
    type: type
    default: Any
    help: str
    choices: tuple[Any, ...] | None = None
    file: bool = False
    in_key: bool = True
    min: float | None = None
    max: float | None = None
    items: builtins.type | None = None
    pattern: str | None = None

    @property
    def type_name(self) -> str:
        """The declared type as ``runner stages`` shows it: ``float``, ``list of str``."""
        return self.type.__name__ + ("" if self.items is None else f" of {self.items.__name__}")

    def problem(self, value: Any) -> str | None:
        """Why ``value`` (already of the declared type) is not allowed, or None."""
        if isinstance(value, list) and self.items is not None:
            return self._items_problem(value, self.items)
        if isinstance(value, str) and self.pattern is not None and not re.fullmatch(self.pattern, value):
            return f"wrong value: expected {self.name} matching {self.pattern}, got {shown(value)}"
        if self.choices is not None and value not in self.choices:
            return f"wrong value: expected one of {', '.join(map(repr, self.choices))}, got {shown(value)}"
        if isinstance(value, float) and not math.isfinite(value):
            return f"wrong value: expected a finite number, got {value!r}"
        below = self.min is not None and value < self.min
        if below or (self.max is not None and value > self.max):
            low = "" if self.min is None else f"{self.min!r} <= "
            high = "" if self.max is None else f" <= {self.max!r}"
            return f"out of range: expected {low}{self.name}{high}, got {value!r}"
        return None

    def _items_problem(self, value: list[Any], kind: builtins.type) -> str | None:
        """Why list ``value`` has an item that is not of type ``kind``, or one given twice."""
        for index, item in enumerate(value):
            if not value_has_type(item, kind):
                return f"wrong type: expected a list of {kind.__name__}, got item {index} {shown(item)}"
            if item in value[:index]:
                return f"wrong value: {shown(item)} is given twice"
        return None


@dataclass(frozen=True)
class StreamInfo:
    """Shape of a frame stream: frame count, frames per second, image width and height in px."""

    frames: int
    fps: float
    width: int
    height: int


class FrameStream(Protocol):
    """Frames of an upstream frame stage, read lazily chunk by chunk.

    ``read(start, stop)`` returns an array ``(stop - start, H, W, C)``; indices are clamped to
    ``[0, info.frames)`` by edge replication, so a stage with a temporal window may ask past the
    ends of the clip.
    """

    info: StreamInfo

    def read(self, start: int, stop: int) -> np.ndarray: ...

    def chunks(self) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(first_frame_index, frames (B, H, W, C))`` over the whole stream in order."""
        ...


#: The log level of a stage's lines that the console shows beside its warnings: what a stage
#: decided that its user should know (``ctx.log.log(SUMMARY, ...)``: the reference it took, what a
#: pack covers); kept with the entry and given again by a cached run as warnings are
#: (:mod:`runner.notes`). ``ctx.log.info`` is not shown.
SUMMARY = 25
logging.addLevelName(SUMMARY, "SUMMARY")


@dataclass
class Context:
    """What the runner hands a stage besides its inputs and parameters.

    ``device`` is ``"cpu"`` or ``"cuda"`` (already resolved from ``--device auto``).
    ``files_dir(port)`` is the empty folder to write a ``files`` output into.
    ``progress(n)`` reports ``n`` more units (frames) done.
    """

    device: str
    files_dir: Callable[[str], Path]
    progress: Callable[[int], None] = lambda n: None
    log: logging.Logger = field(default_factory=lambda: logging.getLogger("runner.stage"))


class StageError(Exception):
    """A failure a user can act on (bad input data, impossible parameters).

    The runner prints its message on one line, naming the stage, and exits with code 1; no
    traceback is shown. Raise it instead of letting a numpy or OpenCV error escape.
    """


class Stage:
    """Base of both stage shapes; subclasses set the class attributes below."""

    name: ClassVar[str]  # registered name, e.g. "track.correlation"
    version: ClassVar[str]  # bump to invalidate cache entries made by older code; CHANGELOG.md lists each version
    doc: ClassVar[str] = ""  # one line shown by `runner stages`
    inputs: ClassVar[Mapping[str, PortType]] = {}  # port name -> port type
    optional_inputs: ClassVar[frozenset[str]] = frozenset()
    outputs: ClassVar[Mapping[str, str | BundleType]] = {}
    params: ClassVar[tuple[Param, ...]] = ()
    # Modules the stage's run imports (its heavy libraries): the runner imports them ahead while
    # its scheduling thread waits for other stages (a stream), so that the stage does not start
    # by importing. Loading a pipeline still imports none of them.
    imports: ClassVar[tuple[str, ...]] = ()
    # Whether the runner may call ``process`` of one instance from several threads at once
    # ("reentrant") or must call it one at a time ("single"); see "Lifecycle and threads" above.
    threading: ClassVar[str] = "reentrant"

    @classmethod
    def check_input(cls, port: str, path: Path) -> str | None:
        """Why ``path``, the pipeline input bound to this stage's input ``port``, is not one the
        stage can read (one line naming the file and the field), or None if it is.

        The runner calls it when the inputs are bound, before anything runs (as the pipeline
        file is checked): a non-None answer is a configuration error (exit 2). It runs on every
        run, cached or not, so it checks what is cheap to check (a manifest, the files it names,
        image headers), never decoding the data. By default None."""
        return None

    def open(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> None:
        """Set up what every call of ``run`` / ``process`` of this run shares (a model prepared
        on ``ctx.device``, a GL context), from the same ``inputs`` and ``params`` they are
        handed. Called once per instance, before its first ``run`` / ``process``, on the thread
        about to make that call; never for an instance that computes nothing (served from the
        cache). ``ctx.files_dir`` is not for writing here. By default nothing."""

    def close(self, ctx: Context) -> None:
        """Free what :meth:`open` set up (and what ``process`` kept, such as decoders). Called
        once per opened instance, after its last ``run`` / ``process`` has returned, also when
        the run failed or was interrupted; on the run's scheduling thread. By default nothing."""


class SequenceStage(Stage):
    """Sees a whole clip's arrays at once (tracking, smoothing, pose, propagation).

    ``frames`` inputs arrive as :class:`FrameStream` (stream them; never hold a long clip).
    """

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        """Return one value per declared output port (bundles as dicts of arrays; ``files``
        ports as ``None`` after writing under ``ctx.files_dir(port)``)."""
        raise NotImplementedError


class FrameStage(Stage):
    """Maps over chunks of frames (decode, synthesize, write); cached chunk by chunk.

    ``window`` is the number of neighbouring frames each side that ``process`` may read from
    its ``frames`` inputs (their ``read`` clamps at the clip ends): output frame t is computed
    from input frames t ± window. :meth:`stream_info` may give the output frames another size,
    channel count or rate, not another count (the runner checks it): a chunk's key reads the
    upstream chunks of its window only, so its frames are streamed through in bounded memory.

    Each output frame must depend only on the inputs, not on which range ``[start, stop)`` it
    is computed in: the cache keeps the digests of ``frames`` outputs, not the frames, and the
    runner computes frames again for a reader that asks after the others (a whole chunk, or
    just the frames it picks), handing them on as the same bytes (docs/runner.md,
    "Scheduling").
    """

    window: ClassVar[int] = 0
    # False for stages cheaper to recompute than to read back from disk (decoding a clip): the
    # runner then computes their chunks on demand while a downstream stage reads them, and keys
    # their output by the chunk's cache key instead of by its bytes.
    cached: ClassVar[bool] = True

    def stream_info(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> StreamInfo:
        """Frame count, rate and size of this stage's output stream; by default those of the
        first ``frames`` input. Stages without one (decode, synthesize) override it."""
        for port, kind in self.inputs.items():
            if kind == "frames" and inputs.get(port) is not None:
                return inputs[port].info  # type: ignore[no-any-return]  # a frames input is a FrameStream
        raise NotImplementedError(f"{self.name} has no frames input; it must define stream_info")

    def process(
        self, start: int, stop: int, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context
    ) -> dict[str, Any]:
        """Compute frames ``[start, stop)``. Return, per output port: for ``frames`` an array
        ``(stop - start, H, W, C)``; for a bundle a dict of arrays whose first axis is
        ``stop - start`` (the runner concatenates chunks); for ``files`` ``None`` after writing
        under ``ctx.files_dir(port)``. Bundle inputs arrive whole: slice ``[start:stop]``."""
        raise NotImplementedError


def defines_stream_info(cls: type[FrameStage]) -> bool:
    """True if the stage computes its own output shape instead of taking its frames input's."""
    return cls.stream_info is not FrameStage.stream_info
