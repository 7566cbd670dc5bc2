"""The bundle types of the pack-building stages (:mod:`runner.bundle`, docs/packbuild.md)."""

from __future__ import annotations

from runner.bundle import BundleType

FRAME_FILTER = BundleType("frame_filter", "The frames pack.filter found usable, with its reasons.", ())
PACK_SELECTION = BundleType("pack_selection", "The frames pack.select chose for the pack's images.", ())
PHOTO_IDENTITY = BundleType("photo_identity", "Which photos of photos.identity show the same person.", ())
