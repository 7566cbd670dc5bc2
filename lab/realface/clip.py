"""A real-texture clip with its truth: fit once, then render each frame's known pose and expression."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from lab.facegen.io import save_npz
from stages.eigen.facegen.render import rotation
from stages.video import CODECS, VideoWriter

from .expression import EXPRESSIONS, STATE_EXPRESSIONS, deform, expression_basis, state_basis
from .landmarks import MODEL_PATH, N_LANDMARKS, detect, open_landmarker
from .mesh import RealFaceMesh, build_mesh, clean_plate, mouth_texture
from .motion import make_motion, state_motion
from .photo import CROP, source_photo
from .render import Frame, render


@dataclass(frozen=True)
class RealFace:
    """The photo, its landmarks ``(478, 3)`` px, the fitted mesh, its expression basis
    ``(3, V, 3)`` mm, the two textures (photo, mouth) as float32, and the backdrop (the clean plate
    behind the head, :func:`lab.realface.mesh.clean_plate`; None: the whole mesh moves)."""

    photo: np.ndarray
    landmarks: np.ndarray
    mesh: RealFaceMesh
    basis: np.ndarray
    textures: tuple[np.ndarray, np.ndarray]
    backdrop: np.ndarray | None = None


def fit_real_face(size: int, *, model_path: Path | str = MODEL_PATH, backdrop: bool = False) -> RealFace:
    """Crop and upscale the portrait to ``size`` px, run MediaPipe once, fit the mesh (and with
    ``backdrop``, inpaint the plate behind the head)."""
    photo = source_photo(size)
    with open_landmarker(model_path=model_path) as landmarker:
        landmarks = detect(landmarker, photo)
    if landmarks is None:
        raise ValueError(f"no face found by MediaPipe in the {size} px source photo")
    mesh = build_mesh(landmarks, size=size)
    mouth = mouth_texture(photo, landmarks, eye_px=mesh.eye_px)
    return RealFace(
        photo,
        landmarks,
        mesh,
        expression_basis(mesh),
        (photo.astype(np.float32), mouth.astype(np.float32)),
        clean_plate(photo, mesh) if backdrop else None,
    )


def pose(face: RealFace, angles: np.ndarray, shift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R = Rz(roll) Ry(yaw) Rx(pitch)`` from ``angles`` (yaw, pitch, roll) degrees and
    ``t = C + shift`` mm (C: the head centre at the identity pose)."""
    return rotation(*angles), face.mesh.head_centre + shift


def render_state(
    face: RealFace, params: np.ndarray, angles: np.ndarray, shift: np.ndarray, *, supersample: int = 2
) -> tuple[Frame, np.ndarray, np.ndarray, np.ndarray]:
    """One frame of expression ``params`` ``(3,)`` at head ``angles`` ``(3,)`` deg and ``shift``
    ``(3,)`` mm; returns the frame, the head-frame vertices ``(V, 3)`` mm and the pose
    ``R (3, 3)``, ``t (3,)`` mm."""
    vertices = deform(face.mesh, face.basis, params)
    R, t = pose(face, angles, shift)
    return render(face.mesh, face.textures, vertices, R, t, supersample=supersample, backdrop=face.backdrop), vertices, R, t


def make_clip(
    out: Path,
    *,
    frames: int,
    seed: int,
    size: int = 512,
    fps: int = 25,
    codec: str = "h264",
    crf: int = 12,
    supersample: int = 2,
    name: str = "astro",
    model_path: Path | str = MODEL_PATH,
    script: str | None = None,
    backdrop: bool = False,
) -> tuple[Path, Path]:
    """Write ``out/<name>.mp4`` (or ``.mkv`` for ``codec="ffv1"``, lossless) and ``out/<name>_truth.npz``.

    ``script`` (:data:`lab.realface.motion.STATE_SCRIPTS`): a states clip instead of the seeded
    events, whose length is the script's (``frames`` is ignored) and whose truth also holds the
    held spans (``state_names (S,)``, ``state_spans (S, 2)`` inclusive frames). With ``backdrop``
    the head moves in front of a static background (:mod:`lab.realface.render`).

    Returns the two paths. Same arguments, same truth file bytes.
    """
    if codec not in CODECS:
        raise ValueError(f"codec: expected one of {', '.join(CODECS)}, got {codec!r}")
    face = fit_real_face(size, model_path=model_path, backdrop=backdrop)
    spans: list[tuple[str, int, int]] = []
    names = EXPRESSIONS
    if script is None:
        params, angles, shift = make_motion(frames, seed=seed, fps=fps)
    else:
        params, angles, shift, spans = state_motion(script, seed=seed, fps=fps)
        face = replace(face, basis=state_basis(face.mesh))
        frames, names = len(params), STATE_EXPRESSIONS
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    clip_path = out / f"{name}{CODECS[codec][2]}"
    truth = {k: [] for k in ("points", "visible", "depth", "points3d", "R", "tvec")}
    with VideoWriter(clip_path, fps=fps, width=size, height=size, codec=codec, crf=crf) as writer:
        for f in range(frames):
            frame, vertices, R, t = render_state(face, params[f], angles[f], shift[f], supersample=supersample)
            writer.write(frame.image[None])
            for key, value in zip(truth, (frame.points, frame.visible, frame.depth, vertices[:N_LANDMARKS], R, t)):
                truth[key].append(value)
    arrays = {k: np.stack(v) for k, v in truth.items()}
    arrays.update(
        rvec=np.stack([cv2.Rodrigues(R)[0].ravel() for R in arrays["R"]]),
        angles_deg=angles,
        expression=params,
        expression_names=np.array(names),
        intrinsics=face.mesh.intrinsics,
        head_centre=face.mesh.head_centre,
        fps=np.array(float(fps)),
        frame_size=np.array([size, size]),
        seed=np.array(seed),
        crop=np.array(CROP),
        source_landmarks=face.landmarks,
        mm_per_px=np.array(face.mesh.mm_per_px),
    )
    if spans:
        arrays.update(state_names=np.array([n for n, _, _ in spans]), state_spans=np.array([(a, b) for _, a, b in spans]))
    truth_path = out / f"{name}_truth.npz"
    save_npz(truth_path, arrays)
    return clip_path, truth_path
