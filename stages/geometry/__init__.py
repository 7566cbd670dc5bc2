"""Geometry stages, the front half of the pipeline (paper Sec. 11, 12, 12.1, 14.1).

- ``track.correlation`` (:mod:`.track`): the layout's tracked subset through the performer clip.
- ``smooth.gaussian`` (:mod:`.smooth`): Gaussian smoothing of the trajectories over time.
- ``compensate.similarity`` (:mod:`.compensate`): 2D similarity head motion (eq. 8-9) removed,
  displacements ``T^-1(x') - x``.
- ``pose.pnp`` (:mod:`.pose`): 3D head pose per frame by PnP (eq. 10).
- ``map.expression`` (:mod:`.mapping`): displacements carried onto the target's neutral (Sec. 11).
"""
