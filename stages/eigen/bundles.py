"""The bundle types of the eigenfeature stages (:mod:`runner.bundle`, docs/eigen.md)."""

from __future__ import annotations

from runner.bundle import BundleType, Field

EIGEN_MODEL = BundleType("eigen_model", "The trained eigenfeature model of train.eigenfeatures.", ())
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
