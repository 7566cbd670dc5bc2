"""Points files: written, read back as a ``points`` bundle by ``points.load``; bad files are a
StageError naming the file and the field."""

from __future__ import annotations

import numpy as np
import pytest

from stages.geometry.points_file import LoadPoints, points_file_bytes, read_points_file
from runner.stage import Context, StageError


def test_round_trip_through_the_stage(tmp_path):
    xy = np.random.default_rng(1).normal(100.0, 10.0, (3, 5, 2))
    path = tmp_path / "k.npz"
    path.write_bytes(points_file_bytes(xy, ("a", "b", "c", "d", "e"), fps=12.5))
    bundle = LoadPoints().run({"file": path}, {}, Context(device="cpu", files_dir=lambda port: tmp_path))["points"]
    np.testing.assert_array_equal(bundle["xy"], xy)
    assert bundle["valid"].all() and bundle["valid"].shape == (3, 5)
    assert list(bundle["names"]) == ["a", "b", "c", "d", "e"] and float(bundle["fps"]) == 12.5


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"names": np.array(["a"]), "fps": np.float64(5)}, "'xy' is missing"),
        ({"xy": np.zeros((2, 1, 3)), "names": np.array(["a"]), "fps": np.float64(5)}, "'xy'"),
        ({"xy": np.full((2, 1, 2), np.nan), "names": np.array(["a"]), "fps": np.float64(5)}, "non-finite"),
        ({"xy": np.zeros((2, 1, 2)), "names": np.array(["a", "b"]), "fps": np.float64(5)}, "'names'"),
        ({"xy": np.zeros((2, 1, 2)), "names": np.array(["a"]), "fps": np.float64(-1)}, "'fps'"),
    ],
)
def test_bad_points_files(tmp_path, fields, message):
    path = tmp_path / "bad.npz"
    np.savez(path, **fields)
    with pytest.raises(StageError, match=message) as error:
        read_points_file(path)
    assert str(path) in str(error.value)


def test_not_an_npz(tmp_path):
    path = tmp_path / "x.npz"
    path.write_text("hello")
    with pytest.raises(StageError, match="not a points file"):
        read_points_file(path)


def test_writer_rejects_mismatched_names():
    with pytest.raises(ValueError):
        points_file_bytes(np.zeros((1, 2, 2)), ("a",), fps=10.0)
