"""Output writers: EXR frames, per-frame data tables and the side-by-side preview.

Modules: :mod:`stages.writers.exr` (``write.exr``), :mod:`stages.writers.data` (``write.data``),
:mod:`stages.writers.preview` (``preview.side_by_side``), and :mod:`stages.writers.atomic`, the
temp-name-then-rename helper they share. The video encoder is ``stages.video`` (``write.video``).
"""
