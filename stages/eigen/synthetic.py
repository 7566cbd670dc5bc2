"""The fixture generator's performer face as the eigenfeature face model (Valente & Dugelay,
"Synthesis of facial expressions": the realistic face model rendered under sampled animation
vectors V = (P, mu); training in :mod:`.training`).

The face is the fixture generator's (:mod:`stages.eigen.facegen`) of the performer's identity, which a
fixture pack names in its ``generator`` entry, rendered with the pack's camera; the animation
parameters are the generator's 12 expression controls, each in [0, 1] (truth known). A pack made
from footage of a real performer has no generator: :mod:`.packface` is its face model.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.eigen.facegen import face as face_mod
from stages.eigen.facegen import render
from stages.eigen.sampling import paper_sampling, rich_sampling
from stages.layout import load_layout, read_yaml


@dataclass
class PerformerRig:
    """The performer's face model posed like the pack's images: the generator's face, camera,
    reference pose ``R0 (3, 3)``, ``t0 (3,)`` mm, texture resolution, the neck pivot (mm) the
    clips turn the head about and the antialiasing of the renders (the fixture clips use 2). A
    :class:`.training.FaceModel`."""

    face: object
    camera: object
    R0: np.ndarray
    t0: np.ndarray
    ppm: float
    pivot: np.ndarray
    param_names: tuple[str, ...]
    supersample: int = 2

    @property
    def point_names(self) -> tuple[str, ...]:
        return tuple(self.face.layout.point_names)

    @property
    def rigid(self) -> tuple[int, ...]:
        return tuple(self.face.layout.rigid)

    @property
    def param_range(self) -> tuple[np.ndarray, np.ndarray]:
        """Each control in [0, 1] (0 = neutral)."""
        return np.zeros(len(self.param_names)), np.ones(len(self.param_names))

    def sampling(self, kind: str, *, samples: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Controls ``(m, C)`` and angles ``(m, 3)``: ``paper`` (each control alone over {0, 0.25,
        0.5, 0.75, 1} x 9 orientations) or ``rich`` (the paper's set plus ``samples`` random
        combinations, each control active with probability 0.35, under +-25 yaw, +-15 pitch, +-10
        roll deg: the live fixture clip's range)."""
        controls, angles = paper_sampling(len(self.param_names))
        if kind == "rich":
            more_c, more_a = rich_sampling(len(self.param_names), samples, seed=seed)
            controls, angles = np.concatenate([controls, more_c]), np.concatenate([angles, more_a])
        return controls, angles

    def pose(self, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``R, t`` of the head turned by (yaw, pitch, roll) deg about the pivot from the reference."""
        R = render.rotation(*angles) @ self.R0
        return R, self.t0 + self.R0 @ self.pivot - R @ self.pivot

    def points(self, controls: np.ndarray, angles: np.ndarray | None = None) -> np.ndarray:
        """Exact projections ``(N, 2)`` px of the layout points (no rendering)."""
        R, t = self.pose(np.zeros(3) if angles is None else angles)
        p3 = face_mod.expression_points3d(self.face.neutral, controls, self.face.layout)
        return render.project(p3, R, t, self.camera.A)[0]

    def render(self, controls: np.ndarray, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image ``(H, W, 3)`` uint8 and points ``(N, 2)`` px of one animation vector."""
        R, t = self.pose(angles)
        p3 = face_mod.expression_points3d(self.face.neutral, controls, self.face.layout)
        out = render.render(self.face, p3, R, t, self.camera, supersample=self.supersample, ppm=self.ppm)
        return out.image, out.points

    def render_batch(self, controls: np.ndarray, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Images ``(B, H, W, 3)`` uint8 and points ``(B, N, 2)`` px, one :meth:`render` each."""
        images, points = zip(*(self.render(c, a) for c, a in zip(controls, angles)))
        return np.stack(images), np.stack(points)


def performer_rig(pack_dir: Path, *, supersample: int = 2) -> PerformerRig:
    """The face model of a fixture pack's performer (``pack.yaml: generator.identity_seed`` and
    the pose and camera of ``generator.truth``); ValueError naming the field for other packs."""
    manifest = read_yaml(Path(pack_dir) / "pack.yaml", what="actor pack", noun="manifest")
    gen = manifest.get("generator") if isinstance(manifest, dict) else None
    if not isinstance(gen, dict) or "identity_seed" not in gen or "truth" not in gen:
        raise ValueError(
            f"{pack_dir}/pack.yaml: field 'generator': expected the generator's identity_seed and truth "
            "of the face generator), got none"
        )
    truth = np.load(Path(pack_dir) / str(gen["truth"]), allow_pickle=False)
    size = tuple(int(v) for v in manifest["image_size"])
    camera = render.Camera(np.asarray(truth["intrinsics"], dtype=np.float64), size)
    face = render.make_face(int(gen["identity_seed"]), load_layout(manifest.get("layout", "zhang134")))
    t0 = np.asarray(truth["t"], dtype=np.float64)
    return PerformerRig(
        face,
        camera,
        np.asarray(truth["R"], dtype=np.float64),
        t0,
        render.texture_ppm(camera, t0[2]),
        np.asarray(render.NECK_PIVOT, dtype=np.float64),
        tuple(face_mod.CONTROLS),
        int(supersample),
    )
