"""Geometry stages, the front half of the pipeline (paper Sec. 11, 12, 12.1, 14.1).

- ``track.correlation`` (:mod:`.track`): the layout's tracked subset through the performer clip
  (the trackers: :mod:`.tracking`, :mod:`.ncc_tracker`, :mod:`.baseline_trackers`,
  :mod:`.correlation`; their defaults: :mod:`.tracker_options`; the first-frame points file:
  :mod:`.first_frame_points`).
- ``smooth.gaussian`` (:mod:`.smooth`): Gaussian smoothing of the trajectories over time.
- ``compensate.similarity`` (:mod:`.compensate`): 2D similarity head motion (eq. 8-9, the
  similarity itself in :mod:`.similarity`) removed, displacements ``T^-1(x') - x``.
- ``pose.pnp`` (:mod:`.pose`): 3D head pose per frame by PnP (eq. 10; the camera model and the
  rotation conventions in :mod:`.camera`); ``compensate.pose3d`` (:mod:`.frontalize`).
- ``map.expression`` (:mod:`.mapping`): displacements carried onto the target's neutral (Sec. 11).

The stages that read an actor pack take ``pack.load``'s bundles (:mod:`stages.pack`).
"""
