"""Declared bundle types (runner/bundle.py): the problems a bundle has against its declaration,
and which output types an input accepts."""

from __future__ import annotations

import numpy as np

from runner.bundle import BundleType, Field, accepts, describe, type_names

TRACK = BundleType(
    "track",
    "points per frame",
    (
        Field("xy", "f", ("T", "N", 2), "px"),
        Field("valid", "b", ("T", "N")),
        Field("names", "U", ("N",)),
        Field("frame", "iu", ()),
        Field("confidence", "f", ("T", "N"), optional=True),
        Field("blob", "u", ("*",), optional=True),
    ),
)


def good(T: int = 3, N: int = 4) -> dict[str, np.ndarray]:
    return {
        "xy": np.zeros((T, N, 2)),
        "valid": np.ones((T, N), bool),
        "names": np.array([f"p{i}" for i in range(N)]),
        "frame": np.int64(0),
    }


def test_a_bundle_as_declared_has_no_problems_and_extra_fields_are_not_checked():
    assert TRACK.problems(good()) == []
    assert TRACK.problems({**good(), "confidence": np.ones((3, 4), np.float32), "extra": np.array(["x"])}) == []
    assert TRACK.problems({**good(), "blob": np.zeros(17, np.uint8)}) == []
    assert TRACK.problems({**good(), "frame": np.uint16(2)}) == []  # "iu": either integer kind


def test_a_missing_required_field_is_named_and_a_missing_optional_one_is_not():
    bundle = good()
    del bundle["valid"]
    assert TRACK.problems(bundle) == ["field 'valid' is missing"]


def test_another_dtype_kind_is_named_with_the_expected_one():
    assert TRACK.problems({**good(), "valid": np.ones((3, 4), np.uint8)}) == ["field 'valid' is uint8, expected bool"]
    assert TRACK.problems({**good(), "frame": np.float64(0)}) == ["field 'frame' is float64, expected int/uint"]


def test_another_rank_or_fixed_extent_is_named_with_the_expected_shape():
    assert TRACK.problems({**good(), "xy": np.zeros((3, 4))}) == ["field 'xy' has shape (3, 4), expected (T, N, 2)"]
    assert TRACK.problems({**good(), "xy": np.zeros((3, 4, 3))}) == ["field 'xy' has shape (3, 4, 3), expected (T, N, 2)"]
    assert TRACK.problems({**good(), "names": np.array("p0")}) == ["field 'names' has shape (), expected (N,)"]


def test_a_symbolic_dimension_must_have_one_extent_across_the_fields():
    assert TRACK.problems({**good(), "valid": np.ones((5, 4), bool)}) == [
        "field 'valid' has T = 5 (axis 0), field 'xy' has T = 3"
    ]
    assert TRACK.problems({**good(), "names": np.array(["a", "b"])}) == ["field 'names' has N = 2 (axis 0), field 'xy' has N = 4"]
    # an optional field, when present, is checked as well
    assert TRACK.problems({**good(), "confidence": np.ones((3, 5))}) == [
        "field 'confidence' has N = 5 (axis 1), field 'xy' has N = 4"
    ]


def test_every_problem_is_reported():
    bundle = {"xy": np.zeros((3, 4, 2), np.float32), "valid": np.ones((3, 4)), "names": np.arange(4)}
    assert TRACK.problems(bundle) == [
        "field 'valid' is float64, expected bool",
        "field 'names' is int64, expected str",
        "field 'frame' is missing",
    ]


def test_inputs_accept_outputs_by_type_name():
    other = BundleType("other", "", ())
    assert accepts(TRACK, TRACK) and not accepts(TRACK, other) and not accepts(TRACK, "frames")
    assert accepts((TRACK, other), other) and not accepts((TRACK, other), "points")
    assert accepts("track", TRACK) and accepts(TRACK, "track")  # an undeclared bundle connects by name
    assert describe((TRACK, other)) == "track | other" and str(TRACK) == "track"
    assert type_names("frames") == ("frames",) and type_names((TRACK, other)) == ("track", "other")
