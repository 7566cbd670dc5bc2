"""The bundle types of the eigenfeature stages (:mod:`runner.bundle`, docs/eigen.md)."""

from __future__ import annotations

from runner.bundle import BundleType

EIGEN_MODEL = BundleType("eigen_model", "The trained eigenfeature model of train.eigenfeatures.", ())
EIGEN_PARAMETERS = BundleType("eigen_parameters", "The expression parameters analyze.eigenfeatures estimated per frame.", ())
