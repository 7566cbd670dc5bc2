"""``mesh3d.synthesize``: the target's 3D expression per frame (Sec. 9).

The target's 2D geometry per frame (motion propagation's output) is lifted to 3D at the target
model's depths (:mod:`stages.mesh3d.model`), projected per subregion onto the convex hull of the
3D examples and composited by vertex position (:mod:`stages.mesh3d.synthesis`).

Output bundle ``mesh3d``:

=================  ==================  =====================================================
``vertices``       (T, N, 3) f8        Sec. 9 synthesis, pack camera frame, mm
``lifted``         (T, N, 3) f8        the input geometry lifted to 3D (no QP), mm
``uv``             (T, N, 2) f8        texture position of each vertex in the frame's synthesized
                                       image (= the input 2D geometry), px
``coeffs``         (T, S, M) f8        per-subregion coefficients (eq. 2-5)
``triangles``      (F, 3) i4           counter-clockwise on screen
``neutral``        (N, 3) f8           the lifted neutral, mm
``pivot``          (3,) f8             head centre (mean of the neutral's skin vertices), mm
``camera``         (3, 3) f8           pack intrinsics, px
``size``           (2,) i8             pack image (W, H)
``names``          (N,) str            layout point names
``fps``            ()                  when the input has it
=================  ==================  =====================================================

With the ``model`` input (the synthesis model: its anchors and triangulation,
:mod:`stages.synthesis.surround`) the bundle also holds the whole head: the face mesh extended to
hair, ears, neck and the background, the geometry the 2D result's head turn warps by.

=================  ==================  =====================================================
``surround``       (A, 3) f8           the anchors lifted at their depths (static), mm
``surround_uv``    (A, 2) f8           their texture positions (fixed), px
``head_triangles`` (K, 3) i4           the synthesis model's triangulation over the N points
                                       and then the A anchors
``weight``         (N + A,) f8         how much each vertex follows the head (1: face, head ring)
=================  ==================  =====================================================
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.bundles import POINTS
from stages.mesh3d.bundles import MESH3D
from stages.pack.bundle_types import CAMERA, LAYOUT, PACK_IMAGES, PACK_MODEL3D
from stages.synthesis.bundles import SYNTHESIS_MODEL
from stages.mesh3d.model import build_target_model, lift
from stages.mesh3d.synthesis import synthesize_3d
from stages.pack.bundles import camera_from_bundle, images_from_bundle, layout_from_bundle, model3d_from_bundle


#: The parameter of the stages that read a ``mesh3d`` bundle: which geometry they take.
GEOMETRY = Param(
    "geometry",
    str,
    "synthesized",
    "synthesized: the Sec. 9 mesh; lifted: the 2D geometry lifted at the model depth",
    choices=("synthesized", "lifted"),
)


def mesh_vertices(mesh: Mapping[str, np.ndarray], geometry: str, *, stage: str) -> np.ndarray:
    """``(T, N, 3)`` mm: the ``mesh3d`` bundle's vertices chosen by the :data:`GEOMETRY` parameter."""
    key = "vertices" if geometry == "synthesized" else "lifted"
    if key not in mesh:
        raise StageError(f"{stage}: input 'mesh' has no field '{key}'")
    return np.asarray(mesh[key], np.float64)


class Mesh3DSynthesize(SequenceStage):
    """``mesh3d.synthesize``: lift the target geometry to 3D and synthesize it from 3D examples."""

    name = "mesh3d.synthesize"
    version = "3"
    doc = "Sec. 9: target 2D geometry per frame -> 3D expression mesh (per-subregion QP on 3n-vectors, vertex blending)"
    inputs = {
        "layout": LAYOUT,
        "images": PACK_IMAGES,
        "model3d": PACK_MODEL3D,
        "camera": CAMERA,
        "points": POINTS,
        "model": SYNTHESIS_MODEL,
    }
    optional_inputs = frozenset({"model"})
    outputs = {"mesh": MESH3D}

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        try:
            layout = layout_from_bundle(inputs["layout"])
            pack = images_from_bundle(inputs["images"], layout)
            model3d = model3d_from_bundle(inputs["model3d"], layout.point_names)
            intrinsics = camera_from_bundle(inputs["camera"], size=pack.image_size)
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from None
        try:
            model = build_target_model(pack, model3d, intrinsics)
        except ValueError as exc:
            raise StageError(f"{self.name}: pack {pack.path}: model3d: {exc}") from None
        bundle = inputs["points"]
        if "xy" not in bundle:
            raise StageError(f"{self.name}: input 'points' has no field 'xy'")
        xy = np.asarray(bundle["xy"], np.float64)
        N = len(model.names)
        if xy.ndim != 3 or xy.shape[1:] != (N, 2):
            raise StageError(f"{self.name}: input 'points' field 'xy' is {xy.shape}, the pack's layout needs (T, {N}, 2)")
        if not np.isfinite(xy).all():
            raise StageError(f"{self.name}: input 'points' field 'xy' has non-finite values")
        lifted = lift(xy, model.depth, model.camera)
        vertices, coeffs = synthesize_3d(model.examples, lifted, model.members, device=ctx.device)
        ctx.progress(len(xy))
        skin = np.unique(model.triangles)
        out = {
            "vertices": vertices,
            "lifted": lifted,
            "uv": xy,
            "coeffs": coeffs,
            "triangles": model.triangles,
            "neutral": model.neutral,
            "pivot": model.neutral[skin].mean(0),
            "camera": model.camera,
            "size": np.array(model.size, np.int64),
            "names": model.names,
        }
        if "fps" in bundle:
            out["fps"] = np.asarray(bundle["fps"])
        if inputs.get("model") is not None:
            out.update(whole_head(inputs["model"], model.depth, model.camera, stage=self.name))
        return {"mesh": out}


def whole_head(model: Mapping[str, np.ndarray], depth: np.ndarray, A: np.ndarray, *, stage: str) -> dict[str, np.ndarray]:
    """The ``surround``, ``surround_uv``, ``head_triangles`` and ``weight`` fields (module docstring)
    from a synthesis model and the target's point depths ``(N,)`` mm."""
    from stages.synthesis.surround import anchor_depth, motion_weights

    for key in ("anchors", "anchor_kind", "anchor_hull", "face_outline", "triangles", "standard_points"):
        if key not in model:
            raise StageError(f"{stage}: input 'model' has no field '{key}'")
    standard = np.asarray(model["standard_points"], np.float64)
    if len(standard) != len(depth):
        raise StageError(f"{stage}: input 'model' has {len(standard)} points, the pack's layout {len(depth)}")
    anchors, kind = np.asarray(model["anchors"], np.float64), np.asarray(model["anchor_kind"])
    z = anchor_depth(
        lift(standard, depth, A), standard, anchors, kind, np.asarray(model["anchor_hull"]), np.asarray(model["face_outline"])
    )
    return {
        "surround": lift(anchors, z, A),
        "surround_uv": anchors,
        "head_triangles": np.asarray(model["triangles"], np.int32),
        "weight": np.concatenate([np.ones(len(depth)), motion_weights(kind)]),
    }
