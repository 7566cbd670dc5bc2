"""``write.data``: the per-frame numbers of a run as one ``data.npz`` and one ``data.csv``.

Whatever bundles are connected (target points, tracked and smoothed performer points, pose,
similarity, QP coefficients per subregion) are written frame by frame. The ``.npz`` keeps every
array of every connected bundle as it came, named ``<port>_<key>`` (``target_xy (T, N, 2)``…),
plus ``frame (T,)`` and ``time_s (T,)``. The ``.csv`` is the same numbers flattened into one row
per frame with named columns; ``docs/writers.md`` lists them. Floats are written with Python's
shortest round-trip repr, so the CSV parses back to exactly the values in the ``.npz``.

Formatting those floats is most of the stage's time (~1 us a cell: 0.3 s for the 300-frame demo
run's 270 000 cells), and every bundle but the coefficients is known before the synthesis. So
``data.table`` formats the CSV cells of those bundles ahead (while the result is synthesized) into
a ``data_table`` bundle, and ``write.data``, given it as ``table``, formats only the columns after
them (the coefficients) and writes the same bytes.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.writers.atomic import atomic_write
from stages.writers.bundles import check_bundle, first_axis

# port -> port type, in CSV column order
BUNDLE_PORTS = {
    "target": "points",
    "tracked": "points",
    "smoothed": "points",
    "pose": "pose",
    "similarity": "similarity",
    "coefficients": "coefficients",
}
Column = tuple[str, np.ndarray]  # (name, values (T,))


def point_columns(prefix: str, bundle: Mapping[str, np.ndarray]) -> list[Column]:
    """``<prefix>_<name>_x``, ``_y`` (px) and ``_valid`` (0/1) for every point of a ``points`` bundle.

    Parameters
    ----------
    prefix : the port name (``target``, ``tracked``, ``smoothed``).
    bundle : ``xy (T, N, 2)`` float px, ``valid (T, N)`` bool, ``names (N,)`` str.
    """
    xy, valid, names = bundle["xy"], bundle["valid"], bundle["names"]
    if xy.ndim != 3 or xy.shape[2] != 2 or valid.shape != xy.shape[:2] or len(names) != xy.shape[1]:
        raise StageError(
            f"write.data: input '{prefix}' must hold xy (T, N, 2), valid (T, N), names (N,); "
            f"got xy {xy.shape}, valid {valid.shape}, names {len(names)}"
        )
    columns: list[Column] = []
    for n, name in enumerate(names):
        columns += [
            (f"{prefix}_{name}_x", xy[:, n, 0]),
            (f"{prefix}_{name}_y", xy[:, n, 1]),
            (f"{prefix}_{name}_valid", valid[:, n]),
        ]
    return columns


def pose_columns(port: str, bundle: Mapping[str, np.ndarray]) -> list[Column]:
    """``pose_rx, ry, rz`` (rvec, rad), ``pose_tx, ty, tz`` (tvec, model units), error, valid."""
    rvec, tvec = bundle["rvec"], bundle["tvec"]
    return [
        *((f"pose_r{axis}", rvec[:, k]) for k, axis in enumerate("xyz")),
        *((f"pose_t{axis}", tvec[:, k]) for k, axis in enumerate("xyz")),
        ("pose_reproj_err_px", bundle["reproj_err_px"]),
        ("pose_valid", bundle["valid"]),
    ]


def similarity_columns(port: str, bundle: Mapping[str, np.ndarray]) -> list[Column]:
    """``sim_a, sim_b, sim_tx, sim_ty`` (eq. 8, neutral -> frame), residual (px), valid."""
    params = bundle["params"]
    return [
        *((f"sim_{name}", params[:, k]) for k, name in enumerate(("a", "b", "tx", "ty"))),
        ("sim_residual_px", bundle["residual_px"]),
        ("sim_valid", bundle["valid"]),
    ]


def coefficient_columns(port: str, bundle: Mapping[str, np.ndarray]) -> list[Column]:
    """``coeff_<subregion>_<example>``: the convex-combination coefficients c_i of eq. 2-5.

    Parameters
    ----------
    bundle : ``coeff (T, R, M)`` float, ``subregions (R,)`` str, ``examples (M,)`` str.
    """
    coeff, subregions, examples = bundle["coeff"], bundle["subregions"], bundle["examples"]
    if coeff.ndim != 3 or coeff.shape[1:] != (len(subregions), len(examples)):
        raise StageError(
            f"write.data: input '{port}' field 'coeff' must be (T, {len(subregions)}, {len(examples)}) "
            f"(frames, subregions, examples), got {coeff.shape}"
        )
    return [
        (f"coeff_{sub}_{ex}", coeff[:, r, m]) for r, sub in enumerate(subregions) for m, ex in enumerate(examples)
    ]


COLUMNS = {  # port type -> its columns
    "points": point_columns,
    "pose": pose_columns,
    "similarity": similarity_columns,
    "coefficients": coefficient_columns,
}


def data_columns(bundles: Mapping[str, Mapping[str, np.ndarray]], *, frames: int, fps: float) -> list[Column]:
    """All CSV columns, in order: ``frame``, ``time_s``, then each connected port in ``BUNDLE_PORTS`` order.

    Parameters
    ----------
    bundles : port name -> bundle, for the connected ports only, each with ``frames`` rows
        (see :func:`stages.writers.bundles.check_bundle`).
    frames : frame count T.
    fps : source frame rate; ``time_s = frame / fps``.
    """
    index = np.arange(frames)
    columns: list[Column] = [("frame", index), ("time_s", index / fps)]
    for port, kind in BUNDLE_PORTS.items():
        if port in bundles:
            columns += COLUMNS[kind](port, bundles[port])
    names = [name for name, _ in columns]
    if len(set(names)) != len(names):
        duplicate = next(n for n in names if names.count(n) > 1)
        raise StageError(f"write.data: duplicate column '{duplicate}' (repeated point, subregion or example name)")
    return columns


def csv_lines(columns: list[Column]) -> list[str]:
    """One CSV line per frame, without its line end: the cells of ``columns`` joined by commas.

    Booleans and integers as integers; floats in Python's shortest round-trip repr (``nan`` for
    missing values), so parsing a cell with ``float()`` gives back the exact float64; these are
    the cells ``csv.writer`` writes for the same values (numbers never need quoting).
    """
    cells = [map(repr, (v.astype(np.int64) if v.dtype.kind in "bi" else v.astype(np.float64)).tolist())
             for _, v in columns]
    return [",".join(row) for row in zip(*cells)]


def write_csv(path: Path, names: list[str], lines: list[str]) -> None:
    """One header row of column ``names`` (quoted by ``csv.writer`` where needed), then ``lines``
    (:func:`csv_lines`), each ended by ``csv.writer``'s ``\\r\\n``."""
    with atomic_write(path) as tmp, open(tmp, "w", newline="") as f:
        csv.writer(f).writerow(names)
        f.writelines(line + "\r\n" for line in lines)


def table_bundle(columns: list[Column], *, frames: int, fps: float) -> dict[str, np.ndarray]:
    """The ``data_table`` bundle of ``columns`` (from :func:`data_columns`): ``names (K,) str``,
    ``text (N,) uint8`` (the UTF-8 of the T lines of :func:`csv_lines` joined by ``\\n``),
    ``frames ()`` and ``fps ()``."""
    return {"names": np.array([name for name, _ in columns], dtype=str),
            "text": np.frombuffer("\n".join(csv_lines(columns)).encode(), np.uint8),
            "frames": np.array(frames, np.int64), "fps": np.array(fps, np.float64)}


def lines_with_table(columns: list[Column], table: Mapping[str, np.ndarray], *, frames: int,
                     fps: float) -> list[str]:
    """:func:`csv_lines` of ``columns``, taking the cells of their first K columns from ``table``
    (:func:`table_bundle` of the same bundles) and formatting only the rest.

    Raises :class:`StageError` when ``table`` was made for another frame count, rate or set of
    columns, or when its first or last line is not what these ``columns`` give (another run's
    bundles).
    """
    names = [str(n) for n in np.asarray(table["names"])]
    made = (int(table["frames"]), float(table["fps"]))
    if made != (frames, fps) or [name for name, _ in columns[:len(names)]] != names:
        raise StageError(f"write.data: input 'table' holds {len(names)} columns of {made[0]} frames at "
                         f"{made[1]:g} frames/s, which are not the first columns of these inputs "
                         f"({len(columns)} columns of {frames} frames at {fps:g} frames/s)")
    ahead = np.asarray(table["text"], np.uint8).tobytes().decode().split("\n")
    if len(ahead) != frames or any(ahead[i] != csv_lines([(n, v[i:i + 1]) for n, v in columns[:len(names)]])[0]
                                   for i in (0, frames - 1)):
        raise StageError("write.data: input 'table' does not hold these inputs' numbers (connect it to a "
                         "data.table of the same bundles)")
    if len(columns) == len(names):
        return ahead
    return [f"{a},{b}" for a, b in zip(ahead, csv_lines(columns[len(names):]))]


def write_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """Uncompressed ``.npz`` of plain (no object) arrays, written atomically."""
    for key, value in arrays.items():
        if np.asarray(value).dtype == object:
            raise StageError(f"write.data: field '{key}' is an object array; bundles must hold plain arrays")
    with atomic_write(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def clip_bundles(stage: str, inputs: Mapping[str, Any], ports: Mapping[str, str]) -> tuple[dict, int, float]:
    """The connected bundles of ``ports`` (port -> type), checked, with the frame count and rate:
    from the ``frames`` input when connected, else from the first bundle (its rows; its ``fps``
    or any bundle's)."""
    bundles = {port: inputs[port] for port in ports if inputs.get(port) is not None}
    if not bundles:
        raise StageError(f"{stage}: no input connected; connect at least one of " + ", ".join(ports))
    if inputs.get("frames") is not None:
        info = inputs["frames"].info
        frames, fps, source = info.frames, float(info.fps), "frames"
    else:
        source = next(iter(bundles))
        with_fps = [p for p in bundles if "fps" in bundles[p]]
        if not with_fps:
            frames_port = "'frames' or " if "frames" in inputs else ""
            raise StageError(f"{stage}: no frame rate: connect {frames_port}an input bundle carrying 'fps'")
        frames, fps = first_axis(bundles[source], ports[source]), float(bundles[with_fps[0]]["fps"])
    for port, bundle in bundles.items():
        try:
            check_bundle(bundle, stage=stage, port=port, kind=ports[port], frames=frames)
        except StageError as err:
            raise StageError(f"{err} (from '{source}')") from None
    return bundles, frames, fps


AHEAD_PORTS = {port: kind for port, kind in BUNDLE_PORTS.items() if kind != "coefficients"}  # known before synthesis


class DataTable(SequenceStage):
    """``data.table``: the CSV cells of ``write.data``'s bundles known before the synthesis (see
    the module doc); its frame rate comes from a bundle's ``fps``."""

    name = "data.table"
    version = "1"
    doc = "write.data's CSV cells of the points, pose and similarity, formatted ahead of the synthesis"
    inputs = dict(AHEAD_PORTS)
    optional_inputs = frozenset(inputs)
    outputs = {"table": "data_table"}
    params: tuple[Param, ...] = ()

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        bundles, frames, fps = clip_bundles(self.name, inputs, AHEAD_PORTS)
        return {"table": table_bundle(data_columns(bundles, frames=frames, fps=fps), frames=frames, fps=fps)}


class WriteData(SequenceStage):
    """Writes ``data.npz`` and ``data.csv``: every connected per-frame bundle, one row per frame."""

    name = "write.data"
    version = "1"
    doc = "per-frame points, pose, similarity and QP coefficients as data.npz and data.csv"
    inputs = {**BUNDLE_PORTS, "frames": "frames", "table": "data_table"}
    optional_inputs = frozenset(inputs)
    outputs = {"data": "files"}
    params: tuple[Param, ...] = ()

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        bundles, frames, fps = clip_bundles(self.name, inputs, BUNDLE_PORTS)
        columns = data_columns(bundles, frames=frames, fps=fps)
        table = inputs.get("table")
        lines = csv_lines(columns) if table is None else lines_with_table(columns, table, frames=frames, fps=fps)
        arrays = {"frame": columns[0][1], "time_s": columns[1][1], "fps": np.float64(fps)}
        for port, bundle in bundles.items():
            arrays.update({f"{port}_{key}": np.asarray(value) for key, value in bundle.items()})
        folder = ctx.files_dir("data")
        try:
            folder.mkdir(parents=True, exist_ok=True)
            write_npz(folder / "data.npz", arrays)
            write_csv(folder / "data.csv", [name for name, _ in columns], lines)
        except OSError as err:
            raise StageError(f"write.data: cannot write to {folder}: {err.strerror or err}") from err
        return {"data": None}
