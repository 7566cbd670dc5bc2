"""The bundle type of ``propagate.train`` (:mod:`runner.bundle`; the model and its keys:
:mod:`stages.propagation.hierarchical_pca`).

N is the layout's points, S the feature point sets, M the rows of all sets together (the sum of
their sizes), C the most components kept by a set.
"""

from __future__ import annotations

from runner.bundle import BundleType, Field

PCA_MODEL = BundleType(
    "pca_model",
    "The hierarchical PCA of the feature point sets over the captured expressions (Sec. 10).",
    (
        Field("neutral", "f", ("N", 2), "px", "neutral geometry"),
        Field("point_names", "U", ("N",), "", 'feature point names ("" when unknown)'),
        Field("set_names", "U", ("S",), "", "feature point set names"),
        Field("set_levels", "iu", ("S",), "", "hierarchy of each set (0 = whole face)"),
        Field("set_offsets", "iu", ("*",), "", "S + 1 offsets: set s owns rows set_offsets[s]:set_offsets[s+1]"),
        Field("set_points", "iu", ("M",), "", "point index of each row"),
        Field("mean", "f", ("M", 2), "px", "mean displacement of each row's point over the captured expressions"),
        Field("components", "f", ("M", 2, "C"), "", "principal directions per set (columns past n_components are zero)"),
        Field("n_components", "iu", ("S",), "", "number of kept components per set"),
        Field("explained_variance", "f", ("S", "C"), "", "fraction of the set's variance per kept component"),
    ),
)
