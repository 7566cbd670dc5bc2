"""write.data: the CSV parses back to exactly the npz's numbers, columns named as documented, and
is what ``csv.writer`` writes."""

import csv
import io
from pathlib import Path

import numpy as np
import pytest

from runner.stage import StageError
from stages.writers.data import WriteData, data_columns
from tests.memory_stream import MemoryStream, files_context

T, FPS = 5, 24.0


def _points(rng: np.random.Generator, names: list[str]) -> dict:
    valid = rng.random((T, len(names))) > 0.3
    return {"xy": rng.normal(size=(T, len(names), 2)) * 300, "valid": valid, "names": np.array(names)}


def _bundles(rng: np.random.Generator) -> dict:
    coeff = rng.dirichlet(np.ones(3), size=(T, 2))
    coeff[1, 1, 2] = np.nan  # an example that does not apply to a subregion
    return {
        "target": _points(rng, ["brow_l", "lip_top", "chin"]),
        "tracked": _points(rng, ["brow_l", "chin"]),
        "smoothed": _points(rng, ["brow_l", "chin"]),
        "pose": {
            "rvec": rng.normal(size=(T, 3)),
            "tvec": rng.normal(size=(T, 3)) * 400,
            "R": np.tile(np.eye(3), (T, 1, 1)),
            "reproj_err_px": rng.random(T),
            "valid": rng.random(T) > 0.5,
        },
        "similarity": {"params": rng.normal(size=(T, 4)), "residual_px": rng.random(T), "valid": np.ones(T, bool)},
        "coefficients": {
            "coeff": coeff,
            "subregions": np.array(["forehead", "mouth"]),
            "examples": np.array(["smile", "frown", "surprise"]),
        },
    }


def _read_csv(path: Path) -> tuple[list[str], dict[str, np.ndarray]]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header = rows[0]
    return header, {name: np.array([float(r[k]) for r in rows[1:]]) for k, name in enumerate(header)}


def test_csv_parses_back_to_npz(tmp_path: Path) -> None:
    bundles = _bundles(np.random.default_rng(0))
    inputs = {**bundles, "frames": MemoryStream(np.zeros((T, 2, 2, 3), np.uint8), fps=FPS)}
    assert WriteData().run(inputs, {}, files_context(tmp_path)) == {"data": None}
    npz = np.load(tmp_path / "data" / "data.npz", allow_pickle=False)
    header, table = _read_csv(tmp_path / "data" / "data.csv")

    np.testing.assert_array_equal(table["frame"], np.arange(T))
    np.testing.assert_array_equal(npz["frame"], np.arange(T))
    np.testing.assert_array_equal(table["time_s"], np.arange(T) / FPS)
    np.testing.assert_array_equal(npz["time_s"], table["time_s"])
    for port in ("target", "tracked", "smoothed"):
        xy, valid = npz[f"{port}_xy"], npz[f"{port}_valid"]
        np.testing.assert_array_equal(xy, bundles[port]["xy"])
        for n, name in enumerate(npz[f"{port}_names"]):
            np.testing.assert_array_equal(table[f"{port}_{name}_x"], xy[:, n, 0])
            np.testing.assert_array_equal(table[f"{port}_{name}_y"], xy[:, n, 1])
            np.testing.assert_array_equal(table[f"{port}_{name}_valid"], valid[:, n])
    for k, axis in enumerate("xyz"):
        np.testing.assert_array_equal(table[f"pose_r{axis}"], npz["pose_rvec"][:, k])
        np.testing.assert_array_equal(table[f"pose_t{axis}"], npz["pose_tvec"][:, k])
    np.testing.assert_array_equal(table["pose_reproj_err_px"], npz["pose_reproj_err_px"])
    np.testing.assert_array_equal(table["pose_valid"], npz["pose_valid"])
    for k, name in enumerate(("a", "b", "tx", "ty")):
        np.testing.assert_array_equal(table[f"sim_{name}"], npz["similarity_params"][:, k])
    np.testing.assert_array_equal(table["sim_residual_px"], npz["similarity_residual_px"])
    np.testing.assert_array_equal(table["sim_valid"], npz["similarity_valid"])
    for r, sub in enumerate(npz["coefficients_subregions"]):
        for m, ex in enumerate(npz["coefficients_examples"]):
            np.testing.assert_array_equal(table[f"coeff_{sub}_{ex}"], npz["coefficients_coeff"][:, r, m])
    assert np.isnan(table["coeff_mouth_surprise"][1])
    assert len(header) == 2 + 3 * (3 + 2 + 2) + 8 + 6 + 6
    assert not [p for p in (tmp_path / "data").iterdir() if p.name.endswith(".part")]


def test_column_order_with_some_inputs(tmp_path: Path) -> None:
    bundles = _bundles(np.random.default_rng(1))
    similarity = {**bundles["similarity"], "fps": np.float64(FPS)}  # frame rate carried by a bundle
    WriteData().run({"tracked": bundles["tracked"], "similarity": similarity}, {}, files_context(tmp_path))
    header, table = _read_csv(tmp_path / "data" / "data.csv")
    assert header == [
        "frame", "time_s",
        "tracked_brow_l_x", "tracked_brow_l_y", "tracked_brow_l_valid",
        "tracked_chin_x", "tracked_chin_y", "tracked_chin_valid",
        "sim_a", "sim_b", "sim_tx", "sim_ty", "sim_residual_px", "sim_valid",
    ]  # fmt: skip
    np.testing.assert_array_equal(table["time_s"], np.arange(T) / FPS)


def test_bad_inputs_are_stage_errors(tmp_path: Path) -> None:
    bundles = _bundles(np.random.default_rng(2))
    ctx = files_context(tmp_path)
    frames = MemoryStream(np.zeros((T, 2, 2, 3), np.uint8), fps=FPS)
    with pytest.raises(StageError, match="no input connected"):
        WriteData().run({"frames": frames}, {}, ctx)
    with pytest.raises(StageError, match="no frame rate"):
        WriteData().run({"pose": bundles["pose"]}, {}, ctx)
    short = {k: v[:-1] for k, v in bundles["pose"].items()}
    with pytest.raises(StageError, match=r"'pose' field 'rvec' has shape \(4, 3\), expected 5 frames"):
        WriteData().run({"pose": short, "similarity": bundles["similarity"], "frames": frames}, {}, ctx)
    with pytest.raises(StageError, match=r"'similarity' field 'params' has shape \(5, 4\), expected 4 .*'pose'"):
        WriteData().run({"pose": {**short, "fps": np.float64(FPS)}, "similarity": bundles["similarity"]}, {}, ctx)
    incomplete = {k: v for k, v in bundles["smoothed"].items() if k != "valid"}
    with pytest.raises(StageError, match="'smoothed' .* lacks field.* valid"):
        WriteData().run({"smoothed": incomplete, "frames": frames}, {}, ctx)
    coefficients = {**bundles["coefficients"], "examples": np.array(["smile", "frown"])}
    with pytest.raises(StageError, match="'coefficients'"):
        WriteData().run({"coefficients": coefficients, "frames": frames}, {}, ctx)
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(StageError, match="cannot write"):
        WriteData().run({"pose": bundles["pose"], "frames": frames}, {}, files_context(blocker))


def _csv_writer_text(columns: list[tuple[str, np.ndarray]]) -> str:
    """The CSV that ``csv.writer`` writes for ``columns`` (an independent formatter)."""
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow([name for name, _ in columns])
    writer.writerows(
        zip(*[v.astype(np.int64).tolist() if v.dtype.kind in "bi" else v.astype(np.float64).tolist() for _, v in columns])
    )
    return out.getvalue()


def test_csv_is_what_csv_writer_writes(tmp_path: Path) -> None:
    bundles = _bundles(np.random.default_rng(3))
    bundles["pose"]["tvec"][0] = [np.inf, -0.0, 1e300]
    bundles["similarity"]["params"][1] = [5e-324, -1e-7, 1e16, 123456789.125]
    WriteData().run({**bundles, "frames": MemoryStream(np.zeros((T, 2, 2, 3), np.uint8), fps=FPS)}, {}, files_context(tmp_path))
    expected = _csv_writer_text(data_columns(bundles, frames=T, fps=FPS))
    assert (tmp_path / "data" / "data.csv").read_bytes() == expected.encode()


def test_occlusion_columns_per_region(tmp_path: Path) -> None:
    occluded = np.zeros((T, 2), bool)
    occluded[1:3, 1] = True
    score = np.array([[1.0, 0.9], [0.8, 0.1], [np.nan, 0.2], [1.1, 0.95], [1.0, 1.0]], np.float32)
    occlusion = {
        "regions": np.array(["mouth", "eye_l"]),
        "occluded": occluded,
        "score": score,
        "valid": np.array([True, True, False, True, True]),
        "region_points": np.ones((2, 3), bool),
        "names": np.array(["a", "b", "c"]),
    }
    frames = MemoryStream(np.zeros((T, 2, 2, 3), np.uint8), fps=FPS)
    WriteData().run({"occlusion": occlusion, "frames": frames}, {}, files_context(tmp_path))
    header, table = _read_csv(tmp_path / "data" / "data.csv")
    assert header == [
        "frame",
        "time_s",
        "occluded_mouth",
        "occluded_eye_l",
        "occlusion_score_mouth",
        "occlusion_score_eye_l",
        "occlusion_valid",
    ]
    np.testing.assert_array_equal(table["occluded_eye_l"], [0, 1, 1, 0, 0])
    np.testing.assert_array_equal(table["occlusion_score_mouth"], score[:, 0].astype(np.float64))
    np.testing.assert_array_equal(table["occlusion_valid"], [1, 1, 0, 1, 1])
    npz = np.load(tmp_path / "data" / "data.npz", allow_pickle=False)
    np.testing.assert_array_equal(npz["occlusion_occluded"], occluded)
    assert list(npz["occlusion_regions"]) == ["mouth", "eye_l"] and npz["occlusion_region_points"].shape == (2, 3)
    with pytest.raises(StageError, match="'occlusion' must hold occluded and score"):
        WriteData().run({"occlusion": {**occlusion, "score": score[:, :1]}, "frames": frames}, {}, files_context(tmp_path))
