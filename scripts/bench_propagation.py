"""Motion propagation: the paper's Fig. 12 experiment, two baselines, and batched speed.

Sec. 14: 17 of the 134 feature points are the input, 25 held-out expressions are inferred from
them. Three methods, all keeping the input points at their input values:

* ``hierarchical``: MotionPropagation (Sec. 10.1) on the hierarchical PCA of the captured set;
* ``flatpca``: one PCA over all points (same number of components as each set), coefficients by
  least squares on the 34 known coordinates;
* ``zero``: displacement 0 (the neutral) for every unknown point.

The 17 input points (``INPUT17``) are spread like a sparse tracker's: inner and outer end of each
brow, the middle of each upper and lower lid, nose tip and both nose wings, the four extreme
points of the outer lip line and the middle of the upper and lower inner lip line.

Writes ``<work>/propagation/fig12.csv`` and ``fig12.png`` (mean error on the 17 input points
against iteration, and the all-points error of a run stopped at that iteration, with the two
baselines). The README's ``docs/img/fig12.png`` is a copy of that PNG from the fixture pack.

Speed: a clip of ``--frames`` distinct expressions (blends of the held-out ones) with the 17-point
mask propagates in one call (``prop_fps``); the baseline is one call per frame on part of the same
clip (``prop_fps_per_frame``), measured in the same run. ``prop_fps_varying_mask`` is a clip whose
tracker mask changes every frame (the tracked subset with random dropouts), which cannot share
work between frames.

    python scripts/bench.py propagation --json [--frames 5000] [--components 8]
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from stages.actor_pack import load_pack
from stages.layout import Layout, load_layout
from stages.propagation import fit_hierarchical_pca, motion_propagation

REPO = Path(__file__).resolve().parent.parent
INPUT17 = (
    "brow_l_0", "brow_l_3", "brow_r_0", "brow_r_3",
    "eye_l_3", "eye_l_9", "eye_r_3", "eye_r_9",
    "nose_tip", "nose_ala_l", "nose_ala_r",
    "mouth_outer_0", "mouth_outer_4", "mouth_outer_8", "mouth_outer_12", "mouth_inner_2", "mouth_inner_7",
)  # fmt: skip
FIG12_ITERATIONS = 100


@dataclass(frozen=True)
class Geometries:
    """Captured geometries of one face, px, and which of them are the test expressions."""

    source: str
    layout: Layout
    neutral: np.ndarray  # (N, 2)
    captured: np.ndarray  # (K, N, 2), all captured geometries (ground truth of the tests)
    test: np.ndarray  # (E,) indices into captured of the test expressions


def pack_geometries(pack_dir: Path, n_test: int) -> Geometries:
    """A fixture actor pack: its captured set, and the first ``n_test`` held-out expressions
    (``truth.npz`` ``heldout_index``: captured geometries that are not example images)."""
    pack = load_pack(pack_dir)
    with np.load(pack_dir / "truth.npz", allow_pickle=False) as truth:
        held_out = np.asarray(truth["heldout_index"], dtype=np.int64)
    return Geometries(
        source=f"fixture pack {pack.name} ({pack.image_size[0]}x{pack.image_size[1]} px)",
        layout=pack.layout,
        neutral=pack.neutral.points,
        captured=pack.captured_points,
        test=held_out[:n_test],
    )


def synthetic_geometries(n_test: int, *, n_captured: int = 40, n_examples: int = 12, seed: int = 5) -> Geometries:
    """The fixture generator's face model and expression recipes (``stages/eigen/facegen``), no images.

    The captured expressions move the 3D points, seen frontally (orthographic) at 3 px/mm, about
    the scale of a 600x800 image, with 0.3 px of annotation noise; as in the fixture packs, the
    test expressions are captured geometries not chosen as examples.
    """
    from stages.eigen.facegen.face import expression_points3d, make_identity, neutral_points3d
    from lab.facegen.sequences import captured_controls, farthest_point_selection

    layout = load_layout("zhang134")
    identity = make_identity(seed, layout)
    neutral3d = neutral_points3d(identity, layout)
    rng = np.random.default_rng(seed)
    scale, centre = 3.0, np.array([300.0, 400.0])
    controls = captured_controls(rng, n_captured)
    faces = np.stack([expression_points3d(neutral3d, c, layout)[:, :2] for c in controls]) * scale + centre
    faces += rng.normal(scale=0.3, size=faces.shape)
    neutral = neutral3d[:, :2] * scale + centre
    examples = farthest_point_selection((faces - neutral).reshape(n_captured, -1), n_examples)
    return Geometries(
        source=f"synthetic (stages/eigen/facegen face model and recipes, seed {seed}, no fixture pack)",
        layout=layout,
        neutral=neutral,
        captured=faces,
        test=np.setdiff1d(np.arange(n_captured), examples)[:n_test],
    )


def flat_pca_fill(captured_d: np.ndarray, known_d: np.ndarray, known: np.ndarray, n_components: int) -> np.ndarray:
    """Baseline: one PCA over all points, least squares on the known coordinates.

    ``captured_d`` (K, N, 2) training displacements; ``known_d`` (E, N, 2) inputs; ``known`` (N,)
    the shared input mask. Returns (E, N, 2) with the inputs kept at the known points.
    """
    x = captured_d.reshape(len(captured_d), -1)
    mean = x.mean(axis=0)
    basis = np.linalg.svd(x - mean, full_matrices=False)[2][:n_components].T  # (2N, C)
    rows = np.repeat(known, 2)
    target = known_d.reshape(len(known_d), -1)[:, rows] - mean[rows]
    coef = np.linalg.lstsq(basis[rows], target.T, rcond=None)[0]  # (C, E)
    fill = (mean[:, None] + basis @ coef).T.reshape(known_d.shape)
    return np.where(known[None, :, None], known_d, fill)


def mean_error(a: np.ndarray, b: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
    """(E,) mean point distance, px, per expression over ``points`` (all if None)."""
    dist = np.linalg.norm(a - b, axis=-1)
    return dist.mean(axis=1) if points is None else dist[:, points].mean(axis=1)


def evaluate(data: Geometries, known: np.ndarray, n_components: int, *, folds: int) -> dict[str, np.ndarray]:
    """Infer every test expression from its ``known`` points with the three methods.

    ``folds`` > 1: cross-validation, each test expression is inferred by models trained on the
    captured set without its fold (the test expressions are split in ``folds`` folds); ``folds``
    = 1: the paper's protocol (Sec. 14), models trained on all captured geometries, tests
    included. Returns per test expression (E,) arrays: all-points errors ``hierarchical``,
    ``flatpca``, ``zero``, and ``*_unknown`` (the points not input), ``iterations``,
    ``input_error`` (px, at the default stop); with folds > 1 also ``input_curve`` and
    ``all_curve`` (E, FIG12_ITERATIONS): the input-point error after each iteration and the
    all-points error of a run stopped there.
    """
    n_test = len(data.test)
    fold_of = np.arange(n_test) % folds
    unknown = np.flatnonzero(~known)
    out: dict[str, np.ndarray] = {}
    for fold in range(folds):
        tests = data.test[fold_of == fold]
        train = np.setdiff1d(np.arange(len(data.captured)), tests) if folds > 1 else np.arange(len(data.captured))
        model = fit_hierarchical_pca(
            data.neutral, data.captured[train], data.layout.feature_point_sets, n_components=n_components
        )
        truth = data.captured[tests] - data.neutral
        masks = np.repeat(known[None], len(tests), axis=0)
        hier = motion_propagation(model, truth, masks)
        methods = {
            "hierarchical": hier.displacements,
            "flatpca": flat_pca_fill(data.captured[train] - data.neutral, truth, known, n_components),
            "zero": np.where(known[None, :, None], truth, 0.0),
        }
        rows = {"iterations": hier.iterations, "input_error": hier.input_error_px}
        for name, guess in methods.items():
            rows[name] = mean_error(guess, truth)
            rows[f"{name}_unknown"] = mean_error(guess, truth, unknown)
        if folds > 1:
            full = motion_propagation(
                model, truth, masks, stop_progress_px=0.0, max_iterations=FIG12_ITERATIONS, record_history=True
            )
            rows["input_curve"] = full.error_history_px
            stopped = [
                motion_propagation(model, truth, masks, stop_progress_px=0.0, max_iterations=it).displacements
                for it in range(1, FIG12_ITERATIONS + 1)
            ]
            rows["all_curve"] = np.stack([mean_error(guess, truth) for guess in stopped], axis=1)
        for key, value in rows.items():
            out.setdefault(key, np.zeros((n_test,) + value.shape[1:], dtype=value.dtype))[fold_of == fold] = value
    return out


def write_fig12(result: dict[str, np.ndarray], out: Path, *, caption: str) -> list[dict]:
    """Convergence table and plot: mean error on the inputs vs iteration, all-points error."""
    baselines = {"flat PCA": float(result["flatpca"].mean()), "zero fill": float(result["zero"].mean())}
    input_curve, all_curve = result["input_curve"].mean(axis=0), result["all_curve"].mean(axis=0)
    rows = [
        {
            "iteration": it,
            "input17_error_px": float(input_curve[it - 1]),
            "all_points_error_px": float(all_curve[it - 1]),
            "flatpca_all_points_error_px": baselines["flat PCA"],
            "zero_all_points_error_px": baselines["zero fill"],
        }
        for it in range(1, FIG12_ITERATIONS + 1)
    ]
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "fig12.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    _plot(rows, baselines, out / "fig12.png", caption=caption)
    return rows


def _plot(rows: list[dict], baselines: dict[str, float], path: Path, *, caption: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    it = [r["iteration"] for r in rows]
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
    left.plot(it, [r["input17_error_px"] for r in rows], color="C0")
    left.set(xlabel="iteration", ylabel="mean error on the 17 input points (px)", title="Convergence (Fig. 12)")
    left.set_ylim(bottom=0)
    right.plot(it, [r["all_points_error_px"] for r in rows], color="C0", label="hierarchical PCA")
    for k, (name, value) in enumerate(baselines.items()):
        right.axhline(value, color=f"C{k + 1}", linestyle="--", label=name)
    right.set(xlabel="iteration", ylabel="mean error on all 134 points (px)", title="All points vs ground truth")
    right.set_ylim(bottom=0)
    right.legend()
    fig.suptitle(caption, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def speed(data: Geometries, known: np.ndarray, n_components: int, n_frames: int) -> dict[str, float]:
    """Frames per second: batched clip, one call per frame, and a clip with per-frame masks.

    The model is trained on all captured geometries; the clip's frames are distinct blends of
    two test expressions plus 0.2 px noise.
    """
    model = fit_hierarchical_pca(data.neutral, data.captured, data.layout.feature_point_sets, n_components=n_components)
    rng = np.random.default_rng(1)
    test_d = data.captured[data.test] - data.neutral
    a, b = rng.integers(0, len(test_d), (2, n_frames))
    t = rng.random((n_frames, 1, 1))
    clip = (1 - t) * test_d[a] + t * test_d[b] + rng.normal(scale=0.2, size=(n_frames,) + test_d.shape[1:])
    masks = np.repeat(known[None], n_frames, axis=0)

    def fps(frames: np.ndarray, mask: np.ndarray, *, per_frame: bool = False, repeats: int = 5) -> float:
        best = np.inf  # best of several runs: the machine is shared
        for _ in range(repeats):
            start = time.perf_counter()
            if per_frame:
                for k in range(len(frames)):
                    motion_propagation(model, frames[k : k + 1], mask[k : k + 1])
            else:
                motion_propagation(model, frames, mask)
            best = min(best, time.perf_counter() - start)
        return len(frames) / best

    tracked = np.zeros((n_frames, model.n_points), dtype=bool)
    tracked[:, list(data.layout.tracked)] = True
    tracked &= rng.random(tracked.shape) > 0.1
    n_small = min(n_frames, 100)
    return {
        "batched": fps(clip, masks),
        "per_frame": fps(clip[:n_small], masks[:n_small], per_frame=True, repeats=2),
        "varying_mask": fps(clip[:n_small], tracked[:n_small]),
    }


def run(args: argparse.Namespace) -> list[dict]:
    parser = argparse.ArgumentParser(prog="bench.py propagation")
    parser.add_argument("--pack", type=Path, default=REPO / "fixtures" / "packs" / "target", help="fixture actor pack")
    parser.add_argument("--tests", type=int, default=25, help="held-out expressions to infer (paper: 25)")
    parser.add_argument("--folds", type=int, default=5, help="cross-validation folds over the test expressions")
    parser.add_argument("--frames", type=int, default=5000, help="clip length for the speed figures")
    parser.add_argument("--components", type=int, default=8, help="principal components per feature point set")
    opts = parser.parse_args(getattr(args, "extra", []))
    has_pack = (opts.pack / "truth.npz").is_file()
    data = pack_geometries(opts.pack, opts.tests) if has_pack else synthetic_geometries(opts.tests)
    print(f"propagation bench data: {data.source}; {len(data.test)} test expressions", file=sys.stderr)
    known = np.zeros(data.layout.n_points, dtype=bool)
    known[list(data.layout.indices(INPUT17))] = True

    held_out = evaluate(data, known, opts.components, folds=opts.folds)
    in_sample = evaluate(data, known, opts.components, folds=1)
    caption = f"{data.source}: 17 input points, {len(data.test)} held-out expressions, {opts.folds}-fold cross-val."
    curve = write_fig12(held_out, Path(args.work) / "propagation", caption=caption)
    fps = speed(data, known, opts.components, opts.frames)

    def row(metric: str, value: float, unit: str) -> dict:
        return {"bench": "propagation", "metric": metric, "value": float(value), "unit": unit}

    rows = []
    for suffix, result in (("", held_out), ("_insample", in_sample)):
        rows += [
            row(f"prop_err17{suffix}_px", result["hierarchical"].mean(), "px"),
            row(f"prop_err17_flatpca{suffix}_px", result["flatpca"].mean(), "px"),
            row(f"prop_err17_zero{suffix}_px", result["zero"].mean(), "px"),
            row(f"prop_err17_unknown{suffix}_px", result["hierarchical_unknown"].mean(), "px"),
            row(f"prop_err17_flatpca_unknown{suffix}_px", result["flatpca_unknown"].mean(), "px"),
        ]
    return rows + [
        row("prop_err17_zero_unknown_px", held_out["zero_unknown"].mean(), "px"),
        row("prop_input17_err_px", held_out["input_error"].mean(), "px"),
        row("prop_input17_err_it1_px", curve[0]["input17_error_px"], "px"),
        row("prop_input17_err_it50_px", curve[49]["input17_error_px"], "px"),
        row("prop_input17_err_it100_px", curve[-1]["input17_error_px"], "px"),
        row("prop_iters_median", float(np.median(held_out["iterations"])), "iterations"),
        row("prop_fps", fps["batched"], "frames/s"),
        row("prop_fps_per_frame", fps["per_frame"], "frames/s"),
        row("prop_batched_speedup", fps["batched"] / fps["per_frame"], "x"),
        row("prop_fps_varying_mask", fps["varying_mask"], "frames/s"),
    ]


if __name__ == "__main__":
    namespace = argparse.Namespace(work=Path(".cache/bench"), extra=sys.argv[1:])
    for r in run(namespace):
        print(r)
