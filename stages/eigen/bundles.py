"""The bundle types of the eigenfeature stages (:mod:`runner.bundle`, docs/eigen.md)."""

from __future__ import annotations

from runner.bundle import BundleType, Field

EIGEN_MODEL = BundleType(
    "eigen_model",
    "The trained eigenfeature model of train.eigenfeatures (P parameters, W feature windows); the "
    "fields that name what it estimates.",
    (
        Field("point_names", "U", ("N",), "", "layout point names"),
        Field("param_names", "U", ("P",), "", "parameter names"),
        Field("feature_names", "U", ("W",), "", "feature window names"),
        Field("feature_points", "b", ("W", "N"), "", "the points each feature window covers"),
    ),
)
EIGEN_PARAMETERS = BundleType(
    "eigen_parameters",
    "The expression parameters analyze.eigenfeatures estimated per frame (P parameters, W feature windows).",
    (
        Field("params", "f", ("T", "P"), "", "the estimated parameters (NaN where not read)"),
        Field("names", "U", ("P",), "", "parameter names"),
        Field("valid", "b", ("T",), "", "frames whose parameters were read"),
        Field("feature_valid", "b", ("T", "W"), "", "feature windows seen per frame"),
        Field("feature_names", "U", ("W",), "", "feature window names"),
    ),
)
