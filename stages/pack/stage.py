"""``pack.load``: an actor pack folder read once and split into typed bundles (docs/architecture.md, "Packs in the graph").

The stage's key is the pack folder's digest (every file under it) plus, through
:func:`runner.depends.depends_on`, the bundled layout file a manifest names. Its outputs are
keyed by content: a stage that takes only ``geometry`` and ``layout`` (``map.expression``,
``propagate.train``) keeps its cache entry when an example image changes, and every stage that
reads the layout sees the layout file's content in its key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from runner.stage import Context, SequenceStage, StageError
from stages.pack.bundle_types import CAMERA, LAYOUT, PACK_GEOMETRY, PACK_IMAGES, PACK_MODEL3D
from stages.actor_pack import check_pack, load_pack
from stages.pack.bundles import pack_to_bundles


class LoadPack(SequenceStage):
    """``pack.load``: load and validate an actor pack (:func:`stages.actor_pack.load_pack`)."""

    name = "pack.load"
    version = "3"
    doc = "read an actor pack folder: layout, neutral/captured geometry, images, generic 3D model, camera"
    inputs = {"pack": "dir"}
    outputs = {
        "layout": LAYOUT,
        "geometry": PACK_GEOMETRY,
        "images": PACK_IMAGES,
        "model3d": PACK_MODEL3D,
        "camera": CAMERA,
    }

    @classmethod
    def check_input(cls, port: str, path: Path) -> str | None:
        """The pack's manifest and every file it names (images by their headers,
        :func:`stages.actor_pack.check_pack`), checked before a run starts."""
        try:
            check_pack(path)
        except StageError as exc:  # a PackError, or a layout file's error
            return str(exc)
        return None

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        pack = load_pack(inputs["pack"])
        ctx.log.info(
            "%s: pack %r, layout %s, %d examples, %d teeth examples, %d captured geometries",
            self.name,
            pack.name,
            pack.layout.name,
            len(pack.examples),
            len(pack.teeth_examples),
            len(pack.captured_points),
        )
        return pack_to_bundles(pack)
