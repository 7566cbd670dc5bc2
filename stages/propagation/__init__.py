"""Motion propagation (Sec. 10): hierarchical PCA of feature point sets, and the iterative
inference of all feature point motions from a subset (tracker points, or points a user drags)."""

from stages.propagation.hierarchical_pca import HierarchicalPCA, fit_hierarchical_pca
from stages.propagation.propagate import (
    PropagationResult,
    motion_propagation,
    propagate_edit,
    start_sets,
    traversal_order,
)

__all__ = [
    "HierarchicalPCA",
    "PropagationResult",
    "fit_hierarchical_pca",
    "motion_propagation",
    "propagate_edit",
    "start_sets",
    "traversal_order",
]
