"""The bundle type of ``propagate.train`` (:mod:`runner.bundle`, docs/propagation.md)."""

from __future__ import annotations

from runner.bundle import BundleType

PCA_MODEL = BundleType("pca_model", "The hierarchical PCA of the feature point sets (Sec. 10).", ())
