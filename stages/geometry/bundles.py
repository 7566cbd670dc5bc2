"""The bundle types of the geometry stages: feature points, displacements, the 2D similarity and
the two head poses (:mod:`runner.bundle`).

Points are px (x right, y down, origin at the centre of the top-left pixel); T is the frame
count, N the points (rows in layout order).
"""

from __future__ import annotations

from runner.bundle import BundleType, Field

#: The stream scalars a bundle may carry from the clip it was computed on.
STREAM_FIELDS = (
    Field("fps", "fiu", (), "Hz", "frames per second of the clip", optional=True),
    Field("size", "iuf", (2,), "px", "(W, H) of the clip's frames", optional=True),
)

POINTS = BundleType(
    "points",
    "Feature points per frame (tracked, smoothed, mapped or propagated).",
    (
        Field("xy", "f", ("T", "N", 2), "px", "point positions"),
        Field("valid", "b", ("T", "N"), "", "positions that are known"),
        Field("names", "U", ("N",), "", "layout point names"),
        Field("confidence", "f", ("T", "N"), "", "tracker confidence (the final NCC), from track.correlation", optional=True),
        Field("z", "f", ("T", "N"), "px", "depth of each point away from the camera, from landmarks.layout", optional=True),
        Field(
            "range_limited",
            "b",
            ("T",),
            "",
            "frames where a displacement lay outside the pack's range (map.expression)",
            optional=True,
        ),
        Field(
            "lips_clamped", "b", ("T",), "", "frames where the inner lips or lids were separated (map.expression)", optional=True
        ),
        Field(
            "state_names", "U", ("S",), "", "expression states (stages/geometry/states.py), from map.expression", optional=True
        ),
        Field("beyond_pack", "b", ("T", "S"), "", "states beyond what the pack's examples show", optional=True),
        Field("coverage", "f", ("S", 2), "", "the pack's range of each state's relative value", optional=True),
        Field("state_values", "f", ("T", "S"), "", "each state's relative value per frame", optional=True),
        *STREAM_FIELDS,
    ),
)

DISPLACEMENTS = BundleType(
    "displacements",
    "Displacements of the feature points from the neutral geometry (in the neutral's frame after compensation).",
    (
        Field("d", "f", ("T", "N", 2), "px", "displacement of each point from the neutral"),
        Field("valid", "b", ("T", "N"), "", "displacements that are known"),
        Field("names", "U", ("N",), "", "layout point names"),
        Field("neutral", "f", ("N", 2), "px", "the performer's neutral geometry, from the compensation stages", optional=True),
        Field("neutral_frame", "iu", (), "", "the head frame (compensate.rigid3d)", optional=True),
        Field("neutral_estimated", "b", (), "", "the neutral was estimated region by region (compensate.rigid3d)", optional=True),
        Field("neutral_nearest_frame", "iu", (), "", "the frame closest to the estimated neutral", optional=True),
        Field("eye_open_known", "b", (2,), "", "per eye, image left then right: False when never seen open", optional=True),
        Field("held", "b", ("T",), "", "frames without a face, holding the nearest frame's expression", optional=True),
        Field("occluded", "b", ("T",), "", "frames where a region was held from the frames around it", optional=True),
        *STREAM_FIELDS,
    ),
)

SIMILARITY = BundleType(
    "similarity",
    "The 2D similarity of the rigid points per frame, mapping the neutral to the frame.",
    (
        Field("params", "f", ("T", 4), "", "(a, b, tx, ty) of eq. 8; tx, ty in px"),
        Field("residual_px", "f", ("T",), "px", "RMS distance of the fitted rigid points"),
        Field("valid", "b", ("T",), "", "frames with a fit"),
    ),
)

HEAD_POSE_PNP = BundleType(
    "pose_pnp",
    "The head pose of pose.pnp: the 3D face model's rigid motion into the camera (OpenCV convention), absolute.",
    (
        Field("rvec", "f", ("T", 3), "rad", "Rodrigues rotation vector, model -> camera"),
        Field("tvec", "f", ("T", 3), "mm", "translation, model -> camera"),
        Field("R", "f", ("T", 3, 3), "", "rotation matrix of rvec"),
        Field("reproj_err_px", "f", ("T",), "px", "RMS reprojection error of the model points"),
        Field("valid", "b", ("T",), "", "frames with a solved pose"),
        Field("camera", "f", (3, 3), "px", "the intrinsics A of eq. 10 it was solved with"),
    ),
)

HEAD_POSE_RELATIVE = BundleType(
    "pose_relative",
    "The head pose of compensate.rigid3d: a weak-perspective 3D similarity relative to the head "
    "frame (neutral_frame); camera frame x right, y down, z away.",
    (
        Field("R", "f", ("T", 3, 3), "", "rotation relative to the head frame"),
        Field("rvec", "f", ("T", 3), "rad", "Rodrigues vector of R"),
        Field("tvec", "f", ("T", 3), "px", "translation of the 3D similarity"),
        Field("scale", "f", ("T",), "", "scale of the 3D similarity"),
        Field("reproj_err_px", "f", ("T",), "px", "RMS residual of the fit"),
        Field("valid", "b", ("T",), "", "frames with a fit"),
        Field("ypr_deg", "f", ("T", 3), "deg", "yaw, pitch, roll (R = Ry Rx Rz)"),
        Field("neutral_frame", "iu", (), "", "the head frame: the named frame, or the clip's most frontal"),
    ),
)

#: What a stage reading either head pose (the writers, the report, the eigenfeature analysis) accepts.
HEAD_POSES = (HEAD_POSE_PNP, HEAD_POSE_RELATIVE)
