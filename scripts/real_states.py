"""Expression states on real clips: the state, coverage, pops and cut-start rows of ``bench.py real``.

No truth exists for a real clip; the performer's geometry as the face landmarker measured it
(``tracked_xy`` of the run's data file) is the reference, the target's output geometry
(``target_xy``) what is judged, each read through :mod:`stages.geometry.states` in its own
eye-line frame:

- **eyes**: an eye is shut where its lid gap is below 35 % of its open level, the 90th percentile
  of its gap; the target's open level is the 90th percentile of the target's gap over the frames
  where the performer's eye is open. ``real_eyes_shut_recall`` / ``_precision`` pool both eyes;
  ``real_lid_follow_r`` is the mean of the two eyes' Pearson r of the gaps; ``real_wink_recall_l`` /
  ``_r``: frames where only that eye of the performer is shut and the target's is shut while its
  other eye is open.
- **lip seal**: inner-lip gap below 0.02 eye distances on both faces (``real_mouth_closed_recall``
  / ``_precision``).
- **brow furrow**: Pearson r of the distance between the inner brow ends
  (``real_brow_furrow_follow_r``), on clips where it spreads over at least :data:`FURROW_SPREAD`.
- **coverage**: ``real_range_limited_frac`` (frames the mapping limited or scaled to the pack's
  range) and ``real_beyond_pack_frames`` (frames with some state beyond what the pack's examples
  show), with one ``real_beyond_pack_frames_<state>`` row per state that occurs.
- **pops** (:func:`texture_changes`): with ``synthesize.head_motion=none``, each result frame
  (what a viewer sees: ``video/result.mp4``) warped back onto the clip's median target geometry by
  a piecewise-affine map of this module's own (Delaunay over the median points, barycentric), and
  the mean absolute change of the face's grey level between frame steps:
  ``real_texture_change_ratio`` (mean over steps, full / warp-only), ``real_pops_ratio`` (steps
  above 3x the run's median step, full / warp-only, warp-only counted at least 1), the same over
  the calm steps only (geometry moving less than its median speed: ``_calm``), where a change is
  not the expression's own, and the same from the EXR master frames (``_master``: no codec noise,
  so warp-only's floor is the resampling alone and every expression's own texture change counts).
- **cut start**: the clip cut to start at its most expressive frame (the one farthest from the
  clip's median geometry after a similarity, in eye distances), run again: the state rows over the
  frames both runs share, the largest absolute difference (``real_cutstart_expr_diff``).

Each row is per clip and target (``..._<stem>_onto_<target>``); the clip's row
(``..._<stem>``) is the worst over its targets, except for ``mouth_follow_r`` and
``mouth_amp_ratio``, whose clip rows are those of the bundled run (``scripts/bench_real.py``). A clip where the performer never does a state
(fewer than :data:`MIN_FRAMES` frames) gives no row for it and is left out of that aggregate.
"""

from __future__ import annotations

import itertools
import sys
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import numpy as np

MIN_FRAMES = 5
SHUT_FRACTION = 0.35
OPEN_PERCENTILE = 90
SEALED_GAP = 0.02
POP_FACTOR = 3.0
FURROW_SPREAD = 0.02  # eye distances between the 5th and 95th percentile: the inner brows move


def row(metric: str, value: float, unit: str) -> dict[str, Any]:
    return {"bench": "real", "metric": metric, "value": float(value), "unit": unit}


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    keep = np.isfinite(a) & np.isfinite(b)
    if keep.sum() < 3 or np.std(a[keep]) == 0 or np.std(b[keep]) == 0:
        return float("nan")
    return float(np.corrcoef(a[keep], b[keep])[0, 1])


def eye_states(performer: np.ndarray, target: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(T,)`` bool shut flags of one eye on the performer and on the target (module docstring)."""
    level = np.nanpercentile(performer[valid], OPEN_PERCENTILE)
    shut_p = valid & (performer < SHUT_FRACTION * level)
    open_frames = valid & ~shut_p
    level_t = np.nanpercentile(target[open_frames], OPEN_PERCENTILE) if open_frames.any() else np.nan
    return shut_p, valid & (target < SHUT_FRACTION * level_t)


def recall_precision(truth: np.ndarray, found: np.ndarray) -> tuple[float, float]:
    hits = float((truth & found).sum())
    return (
        hits / truth.sum() if truth.any() else float("nan"),
        hits / found.sum() if found.any() else (1.0 if not truth.any() else 0.0),
    )


def state_measures(data: Mapping[str, np.ndarray], frames: np.ndarray | None = None) -> dict[str, float]:
    """The state measures of one run's data file (module docstring), over ``frames`` (all by
    default); NaN where the performer never does the state."""
    from stages.geometry.states import state_signals

    names = [str(n) for n in data["target_names"]]
    keep = np.ones(len(data["target_xy"]), bool) if frames is None else np.isin(np.arange(len(data["target_xy"])), frames)
    valid = np.asarray(data["tracked_valid"], bool).all(axis=1) & keep
    performer, target = state_signals(data["tracked_xy"], names), state_signals(data["target_xy"], names)
    shut = {side: eye_states(performer[f"eye_open_{side}"], target[f"eye_open_{side}"], valid) for side in "lr"}
    pooled_p = np.concatenate([shut[s][0] for s in "lr"])
    pooled_t = np.concatenate([shut[s][1] for s in "lr"])
    out: dict[str, float] = {}
    recall, precision = recall_precision(pooled_p, pooled_t)
    enough = pooled_p.sum() >= MIN_FRAMES
    out["eyes_shut_recall"] = recall if enough else np.nan
    out["eyes_shut_precision"] = precision if enough else np.nan
    out["eyes_shut_frames"] = float(pooled_p.sum())
    out["lid_follow_r"] = float(
        np.nanmean([pearson(np.where(valid, performer[f"eye_open_{s}"], np.nan), target[f"eye_open_{s}"]) for s in "lr"])
    )
    for side, other in (("l", "r"), ("r", "l")):
        wink = shut[side][0] & ~shut[other][0]
        hit = wink & shut[side][1] & ~shut[other][1]
        out[f"wink_recall_{side}"] = hit.sum() / wink.sum() if wink.sum() >= MIN_FRAMES else np.nan
    closed_p = valid & (performer["mouth_open"] < SEALED_GAP)
    closed_t = valid & (target["mouth_open"] < SEALED_GAP)
    recall, precision = recall_precision(closed_p, closed_t)
    enough = closed_p.sum() >= MIN_FRAMES
    out["mouth_closed_recall"] = recall if enough else np.nan
    out["mouth_closed_precision"] = precision if enough else np.nan
    furrow_p = np.where(valid, performer["brow_furrow"], np.nan)
    spread = np.subtract(*np.nanpercentile(furrow_p, [95, 5])) if valid.any() else 0.0
    out["brow_furrow_follow_r"] = pearson(furrow_p, target["brow_furrow"]) if spread >= FURROW_SPREAD else np.nan
    out["mouth_follow_r"] = pearson(np.where(valid, performer["mouth_open"], np.nan), target["mouth_open"])
    p, t = performer["mouth_open"][valid], target["mouth_open"][valid]
    out["mouth_amp_ratio"] = float(np.std(t) / np.std(p)) if np.std(p) > 0 else np.nan
    return out


def coverage_measures(data: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Frames the mapping limited to the pack's range, and those beyond the pack's states."""
    out: dict[str, float] = {}
    if "target_range_limited" in data:
        out["range_limited_frac"] = float(np.mean(data["target_range_limited"]))
    if "target_beyond_pack" in data:
        beyond = np.asarray(data["target_beyond_pack"], bool)
        out["beyond_pack_frames"] = float(beyond.any(axis=1).sum())
        for k, name in enumerate(data["target_state_names"]):
            if beyond[:, k].any():
                out[f"beyond_pack_frames_{name}"] = float(beyond[:, k].sum())
    return out


UNITS = (
    ("recall", "fraction"),
    ("precision", "fraction"),
    ("_frac", "fraction"),
    ("_frames", "frames"),
    ("_frame", "frame"),
    ("_grey", "grey levels"),
    ("_diff", "fraction"),
    ("ratio", "ratio"),
    ("_r", "r"),
)


def unit_of(name: str) -> str:
    """The unit of a measure, from its name (``_master``/``_calm`` suffixes aside)."""
    base = name.removesuffix("_master").removesuffix("_calm")
    return next((unit for key, unit in UNITS if key in base), "")


# -- texture pops ------------------------------------------------------------------------------


def master_greys(out: Path) -> Iterator[np.ndarray]:
    """The EXR result frames' grey levels, 0-255 (scene-linear colour unpremultiplied, the sRGB curve)."""
    import OpenImageIO as oiio

    from stages.color import linear_to_srgb

    for path in sorted((out / "exr").glob("frame.*.exr")):
        image = oiio.ImageInput.open(str(path))
        try:
            pixels = image.read_image("float")
        finally:
            image.close()
        rgb = pixels[..., :3] / np.maximum(pixels[..., 3:4], 1e-6) if pixels.shape[2] > 3 else pixels[..., :3]
        srgb = linear_to_srgb(np.clip(rgb, 0.0, 1.0))
        yield 255.0 * (0.299 * srgb[..., 0] + 0.587 * srgb[..., 1] + 0.114 * srgb[..., 2])


def video_greys(out: Path) -> Iterator[np.ndarray]:
    """The result video's frames as grey levels, 0-255 (BT.601 luma of the decoded RGB)."""
    import av

    with av.open(str(out / "video" / "result.mp4")) as container:
        for frame in container.decode(video=0):
            rgb = frame.to_ndarray(format="rgb24").astype(np.float64)
            yield 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]


def texture_changes(out: Path, *, master: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per frame step: the mean absolute change of the face's grey level with the geometry taken
    out (each frame warped back onto the median target geometry), and the geometry's speed (RMS
    point motion, px); ``(T - 1,)`` each. Frames of the result video, or of the EXR master."""
    import cv2
    from scipy.spatial import Delaunay

    data = np.load(out / "data" / "data.npz")
    xy = np.asarray(data["target_xy"], np.float64)
    median = np.median(xy, axis=0)
    greys = master_greys(out) if master else video_greys(out)
    first = next(greys)
    H, W = first.shape
    mesh = Delaunay(median)
    ys, xs = np.mgrid[0:H, 0:W]
    pixels = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    simplex = mesh.find_simplex(pixels)
    inside = np.flatnonzero(simplex >= 0)
    affine = mesh.transform[simplex[inside]]
    bary = np.einsum("nij,nj->ni", affine[:, :2], pixels[inside] - affine[:, 2])
    bary = np.concatenate([bary, 1.0 - bary.sum(axis=1, keepdims=True)], axis=1)
    corners = mesh.simplices[simplex[inside]]
    previous, changes = None, []
    for t, grey in enumerate(itertools.chain([first], greys)):
        source = np.einsum("ni,nij->nj", bary, xy[t][corners])
        map_x = np.full(H * W, -1.0, np.float32)
        map_y = np.full(H * W, -1.0, np.float32)
        map_x[inside], map_y[inside] = source[:, 0], source[:, 1]
        back = cv2.remap(grey.astype(np.float32), map_x.reshape(H, W), map_y.reshape(H, W), cv2.INTER_LINEAR)
        values = back.ravel()[inside]
        if previous is not None:
            changes.append(float(np.abs(values - previous).mean()))
        previous = values
    speed = np.sqrt(np.mean(np.sum(np.diff(xy, axis=0) ** 2, axis=-1), axis=1))
    return np.array(changes), speed


def pops_measures(full: Path, warp_only: Path) -> dict[str, float]:
    """The pops rows of one clip from a ``full`` and a ``warp-only`` run (module docstring)."""

    def pops(change: np.ndarray) -> int:
        return int((change > POP_FACTOR * np.median(change)).sum())

    out: dict[str, float] = {}
    for master, suffix in ((False, ""), (True, "_master")):
        change_f, speed = texture_changes(full, master=master)
        change_w, _ = texture_changes(warp_only, master=master)
        calm = speed < np.median(speed)
        out |= {
            f"texture_change_ratio{suffix}": float(change_f.mean() / change_w.mean()),
            f"pops_ratio{suffix}": pops(change_f) / max(pops(change_w), 1),
            f"texture_change_ratio_calm{suffix}": float(change_f[calm].mean() / change_w[calm].mean()),
            f"pops_ratio_calm{suffix}": pops(change_f[calm]) / max(pops(change_w[calm]), 1),
            f"texture_change_full_grey{suffix}": float(change_f.mean()),
            f"texture_change_warponly_grey{suffix}": float(change_w.mean()),
        }
    return out


# -- cut start ---------------------------------------------------------------------------------


def most_expressive_frame(data: Mapping[str, np.ndarray]) -> int:
    """The frame whose performer geometry is farthest from the clip's median geometry once a
    similarity on the eye corners and nose is taken out (RMS, eye distances)."""
    from stages.geometry.mapping import NORMALIZATION_POINTS, eye_distance
    from stages.geometry.similarity import apply_similarity, fit_similarity

    names = [str(n) for n in data["tracked_names"]]
    xy = np.asarray(data["tracked_xy"], np.float64)
    valid = np.asarray(data["tracked_valid"], bool).all(axis=1)
    valid[int(len(valid) * 2 / 3) :] = False  # a third of the clip at least is left to compare
    stable = [names.index(n) for n in NORMALIZATION_POINTS]
    median = np.median(xy[valid], axis=0)
    scale = eye_distance(median, names)
    distance = np.full(len(xy), -np.inf)
    for t in np.flatnonzero(valid):
        aligned = apply_similarity(fit_similarity(xy[t, stable], median[stable]), xy[t])
        distance[t] = np.sqrt(np.mean(np.sum((aligned - median) ** 2, axis=-1))) / scale
    return int(np.argmax(distance))


def cut_clip(clip: Path, start: int, path: Path) -> Path:
    """The clip from frame ``start`` on, losslessly (FFV1 in Matroska, the source's rate)."""
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(clip)) as source, av.open(str(path), "w") as sink:
        stream_in = source.streams.video[0]
        stream = sink.add_stream("ffv1", rate=stream_in.average_rate)
        stream.width, stream.height, stream.pix_fmt = stream_in.codec_context.width, stream_in.codec_context.height, "bgr0"
        for k, frame in enumerate(source.decode(video=0)):
            if k >= start:
                out = av.VideoFrame.from_ndarray(frame.to_ndarray(format="bgr24"), format="bgr24")
                for packet in stream.encode(out.reformat(format="bgr0")):
                    sink.mux(packet)
        for packet in stream.encode():
            sink.mux(packet)
    return path


def cutstart_measures(clip: Path, whole: Path, work: Path, run: Callable[..., Any]) -> dict[str, float]:
    """The clip cut at its most expressive frame, run with the same target: the largest absolute
    difference of the state measures over the frames the two runs share."""
    data = np.load(whole / "data" / "data.npz")
    start = most_expressive_frame(data)
    cut = cut_clip(clip, start, work / f"{clip.stem}_cut.mkv")
    folder = work / "cut"
    run(cut, folder)
    cut_data = np.load(folder / "out" / "data" / "data.npz")
    shared = np.arange(start, len(data["target_xy"]))
    a = state_measures(data, shared)
    b = state_measures(cut_data)
    diffs = [
        abs(a[k] - b[k])
        for k in a
        if k != "eyes_shut_frames" and np.isfinite(a[k]) and np.isfinite(b[k]) and not k.endswith("amp_ratio")
    ]
    return {"cutstart_expr_diff": max(diffs) if diffs else np.nan, "cutstart_frame": float(start)}


def aggregate(per_clip: dict[str, dict[str, float]]) -> list[dict[str, Any]]:
    """The minima / maxima over the clips the issue's targets are judged on; a clip without the
    state is left out and named on stderr."""
    rows = []
    wanted = (
        ("eyes_shut_recall", "min"),
        ("eyes_shut_precision", "min"),
        ("mouth_closed_recall", "min"),
        ("mouth_closed_precision", "min"),
        ("brow_furrow_follow_r", "min"),
        ("lid_follow_r", "min"),
        ("pops_ratio", "max"),
        ("texture_change_ratio", "max"),
        ("pops_ratio_calm", "max"),
        ("texture_change_ratio_calm", "max"),
        ("cutstart_expr_diff", "max"),
    )
    for name, kind in wanted:
        values = {stem: m[name] for stem, m in per_clip.items() if name in m and np.isfinite(m[name])}
        left = sorted(set(per_clip) - set(values))
        if left:
            print(
                f"real_{name}_{kind}: left out (the performer never does it, or not measured): {', '.join(left)}", file=sys.stderr
            )
        if values:
            rows.append(row(f"real_{name}_{kind}", (min if kind == "min" else max)(values.values()), unit_of(name)))
    return rows


def states_sheet(work: Path, path: Path, run: Callable[..., Any], *, size: int = 512, height: int = 150) -> None:
    """A contact sheet of the states: the real-texture ``states`` clip (lab/realface: the
    astronaut photo's face holding each state in turn) mapped by the default pipeline onto its
    bundled target; one column per state at the middle of its hold, performer over result,
    labelled. Public-domain and generated material only, so the sheet may be committed."""
    import av
    import cv2

    from lab.realface.clip import make_clip

    clip, truth_path = make_clip(work / "states_clip", frames=0, seed=3, size=size, script="states")
    run(clip, work / "states_run")
    truth = np.load(truth_path)
    middle = {str(n): (int(a) + int(b)) // 2 for n, (a, b) in zip(truth["state_names"], truth["state_spans"])}

    def frames_of(video: Path) -> dict[int, np.ndarray]:
        wanted, out = set(middle.values()), {}
        with av.open(str(video)) as container:
            for k, frame in enumerate(container.decode(video=0)):
                if k in wanted:
                    out[k] = frame.to_ndarray(format="rgb24")
        return out

    performer, result = frames_of(clip), frames_of(work / "states_run" / "out" / "video" / "result.mp4")
    points = truth["points"][list(middle.values())]  # the performer's face, cropped
    (x0, y0), (x1, y1) = np.nanmin(points, axis=(0, 1)), np.nanmax(points, axis=(0, 1))
    pad = 0.15 * max(x1 - x0, y1 - y0)
    box = [int(max(v, 0)) for v in (y0 - pad, y1 + pad, x0 - pad, x1 + pad)]
    performer = {f: image[box[0] : box[1], box[2] : box[3]] for f, image in performer.items()}
    columns = []
    for name, f in middle.items():
        cells = [
            cv2.resize(image, (int(round(image.shape[1] * height / image.shape[0])), height), interpolation=cv2.INTER_AREA)
            for image in (performer[f], result[f])
        ]
        width = max(c.shape[1] for c in cells)
        cells = [np.pad(c, ((0, 0), (0, width - c.shape[1]), (0, 0)), constant_values=255) for c in cells]
        label = np.full((22, width, 3), 255, np.uint8)
        cv2.putText(label, name.replace("_", " "), (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        columns.append(np.concatenate([label, *cells], axis=0))
    sheet = np.concatenate([np.pad(c, ((0, 0), (0, 3), (0, 0)), constant_values=255) for c in columns], axis=1)
    jpeg = path.suffix.lower() in (".jpg", ".jpeg")
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 88] if jpeg else [])
