"""The bundle type of ``landmarks.mediapipe`` (:mod:`runner.bundle`): MediaPipe's face mesh per frame.

T is the frame count, M the mesh's landmarks (478), B the blendshapes (52).
"""

from __future__ import annotations

from runner.bundle import BundleType, Field

LANDMARKS = BundleType(
    "landmarks",
    "MediaPipe's face landmarks, blendshapes and face frame per frame.",
    (
        Field("xy", "f", ("T", "M", 2), "px", "landmark positions (NaN where no face)"),
        Field("z", "f", ("T", "M"), "px", "landmark depth, away from the camera"),
        Field("valid", "b", ("T",), "", "frames with a face"),
        Field("blendshapes", "f", ("T", "B"), "", "blendshape scores in [0, 1]"),
        Field("blendshape_names", "U", ("B",), "", "blendshape names"),
        Field("matrix", "f", ("T", 4, 4), "", "MediaPipe's face frame (y up, z towards the camera)"),
        Field("face_width_px", "f", ("T",), "px", "face width"),
        Field("faces", "iuf", ("T",), "", "faces found in the frame"),
        Field("region", "iuf", ("T", 4), "px", "the face's region in the frame"),
        Field("fps", "fiu", (), "Hz", "frames per second of the clip"),
        Field("size", "iu", (2,), "px", "(W, H) of the clip's frames"),
    ),
)
