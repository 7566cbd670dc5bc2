"""A real performer's face model for the eigenfeature training: the performer's actor pack driven
by this project's example-based synthesis (Valente & Dugelay's "realistic face model", built
from footage instead of a scan).

- **Animation parameters** (:func:`pca_parameters`): the principal directions of the pack's
  captured geometries (Sec. 10, 14: the geometries of every usable frame the pack was built
  from), ``x(mu) = x_neutral + sum_k mu_k sigma_k e_k`` in the pack's (neutral's) frame, so that
  ``mu = 0`` is the neutral and ``mu_k`` is in standard deviations of the captured set along
  ``e_k``. The first components reaching ``variance`` of the captured variance are kept (at most
  ``max_params``): on the dev-clip packs (35 captured geometries) 95 % takes 4-5 components; the
  rest is landmark noise that 35 samples cannot tell from expression.
- **Images**: the synthesis (:class:`stages.synthesis.synthesize.Synthesizer`, the paper's
  per-subregion blending of the pack's examples) renders the face at ``x(mu)``, composited over
  the pack's neutral image warped to the same geometry (what lies outside the face).
- **Pose**: an out-of-plane rotation ``R = Rz(roll) Ry(yaw) Rx(pitch)`` is applied to the points
  with the depth of the pack's generic 3D model (``model3d``, scaled to the neutral's px by least
  squares) under orthographic projection about the face's centroid, and the image is warped
  piecewise-affinely to the rotated points (the synthesis model's triangulation, its border
  anchors fixed): a 2.5D approximation valid for the small rotations sampled (no occlusion).
  The in-plane placement (the 2D similarity) is what the patch normalization removes.

Pixels: x right, y down, origin at the centre of the top-left pixel; depth z away from the camera.
"""

from __future__ import annotations

import numpy as np

from stages.actor_pack import ActorPack
from stages.eigen.sampling import paper_sampling, rich_sampling
from stages.geometry.rotation import rotation_zyx

PAPER_LEVELS_SD = (-2.0, -1.0, 0.0, 1.0, 2.0)  # the paper's {-1, -0.5, 0, 0.5, 1} over +-2 standard deviations
RICH_ACTIVE = 0.5  # chance that a parameter is non-zero in a random combination
RICH_MAX_DEG = (15.0, 10.0, 10.0)  # (yaw, pitch, roll) range of the rich sampling


def pca_parameters(captured: np.ndarray, *, variance: float = 0.95, max_params: int = 8) -> np.ndarray:
    """The animation parameters' directions: ``sigma_k e_k`` ``(C, N, 2)`` px per unit parameter.

    Parameters
    ----------
    captured : (K, N, 2) float
        The pack's captured geometries, px, in the neutral's frame.
    variance : float
        Fraction of the captured variance the kept components reach, in (0, 1].
    max_params : int
        Most components kept.

    Returns
    -------
    (C, N, 2) float64
        Principal directions scaled by their standard deviation over the captured set, by
        decreasing variance; ``1 <= C <= max_params``.
    """
    X = np.asarray(captured, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 2 or len(X) < 2:
        raise ValueError(f"expected captured geometries (K >= 2, N, 2), got {X.shape}")
    if not 0.0 < variance <= 1.0 or max_params < 1:
        raise ValueError(f"expected 0 < variance <= 1 and max_params >= 1, got {variance} and {max_params}")
    flat = X.reshape(len(X), -1)
    _, s, vt = np.linalg.svd(flat - flat.mean(axis=0), full_matrices=False)
    share = np.cumsum(s**2) / max(float((s**2).sum()), 1e-300)
    C = min(int(np.searchsorted(share, variance - 1e-12)) + 1, max_params, len(s))
    sigma = s[:C] / np.sqrt(len(X) - 1)
    return (sigma[:, None] * vt[:C]).reshape(C, *X.shape[1:])


def point_depth(model3d: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """Depth ``(N,)`` px of each point: the generic model's ``z`` (mm, away from the camera) times
    the scale (px/mm) of the least-squares fit ``s * (x, y)_model + t ~ neutral``, centred."""
    M = np.asarray(model3d, dtype=np.float64)
    P = np.asarray(neutral, dtype=np.float64)
    if M.ndim != 2 or M.shape != (len(P), 3):
        raise ValueError(f"expected model3d ({len(P)}, 3), got {M.shape}")
    m, p = M[:, :2] - M[:, :2].mean(axis=0), P - P.mean(axis=0)
    scale = float((m * p).sum() / max(float((m * m).sum()), 1e-300))
    return scale * (M[:, 2] - M[:, 2].mean())


class PackFace:
    """The performer's pack as a :class:`.training.FaceModel` (module docstring).

    Parameters
    ----------
    pack : ActorPack
        The performer's pack (built from footage: ``pack_build.yaml``).
    variance, max_params
        Which PCA components are the animation parameters (:func:`pca_parameters`).
    """

    def __init__(self, pack: ActorPack, *, variance: float = 0.95, max_params: int = 8) -> None:
        import torch

        from stages.synthesis.build import build_synthesis_model
        from stages.synthesis.synthesize import Synthesizer

        self.pack = pack
        self.neutral = np.asarray(pack.neutral.points, dtype=np.float64)
        self.basis = pca_parameters(pack.captured_points, variance=variance, max_params=max_params)
        self.param_names = tuple(f"pc{k}" for k in range(len(self.basis)))
        self.point_names = tuple(pack.layout.point_names)
        self.rigid = tuple(pack.layout.rigid)
        self.depth = point_depth(pack.model3d, self.neutral)
        self.synthesizer = Synthesizer(build_synthesis_model(pack))
        self.anchors = torch.from_numpy(self.synthesizer.anchors)

    @property
    def param_range(self) -> tuple[np.ndarray, np.ndarray]:
        """+-2 standard deviations of the captured set."""
        C = len(self.param_names)
        return np.full(C, PAPER_LEVELS_SD[0]), np.full(C, PAPER_LEVELS_SD[-1])

    def sampling(self, kind: str, *, samples: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Parameters ``(m, C)`` and angles ``(m, 3)``: ``paper`` (each parameter alone over {-2,
        -1, 0, 1, 2} standard deviations x 9 orientations, X and Y in {-3, 0, 3} deg) or ``rich``
        (the paper's set plus ``samples`` random combinations, each parameter non-zero with
        probability 0.5 and then uniform in +-2, under +-15 yaw, +-10 pitch, +-10 roll deg)."""
        C = len(self.param_names)
        params, angles = paper_sampling(C, levels=PAPER_LEVELS_SD)
        if kind == "rich":
            more_p, more_a = rich_sampling(C, samples, seed=seed, active=RICH_ACTIVE, span=self.param_range, max_deg=RICH_MAX_DEG)
            params, angles = np.concatenate([params, more_p]), np.concatenate([angles, more_a])
        return params, angles

    def points(self, params: np.ndarray) -> np.ndarray:
        """Geometry ``(..., N, 2)`` px of parameters ``(..., C)`` in the neutral's frame and pose."""
        return self.neutral + np.einsum("...c,cnk->...nk", np.asarray(params, dtype=np.float64), self.basis)

    def rotate(self, points: np.ndarray, angles: np.ndarray) -> np.ndarray:
        """Points ``(B, N, 2)`` turned by (yaw, pitch, roll) deg ``(B, 3)`` with the model's depth,
        orthographic, about each geometry's centroid."""
        centre = points.mean(axis=1, keepdims=True)
        xyz = np.concatenate([points - centre, np.broadcast_to(self.depth[None, :, None], points.shape[:2] + (1,))], -1)
        return np.einsum("bij,bnj->bni", rotation_zyx(angles), xyz)[..., :2] + centre

    def render_batch(self, params: np.ndarray, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Images ``(B, H, W, 3)`` uint8 RGB and points ``(B, N, 2)`` px of parameters ``(B, C)``
        under rotations ``(B, 3)`` (yaw, pitch, roll) deg."""
        import torch

        from stages.synthesis.warp import warp_images

        params = np.atleast_2d(np.asarray(params, dtype=np.float64))
        angles = np.atleast_2d(np.asarray(angles, dtype=np.float64))
        if params.shape[1] != len(self.param_names) or angles.shape != (len(params), 3):
            raise ValueError(
                f"expected params (B, {len(self.param_names)}) and angles (B, 3), got {params.shape} and {angles.shape}"
            )
        geometry = self.points(params)
        face, alpha, _ = self.synthesizer.render(geometry)
        around, _, _ = self.synthesizer.render(geometry, mode="warp-only")
        image = alpha * face + (1 - alpha) * around
        turned = self.rotate(geometry, angles)
        if np.abs(angles).max() > 0:
            B = len(params)
            anchors = self.anchors.expand(B, -1, -1)
            src = torch.cat([torch.from_numpy(geometry), anchors], 1)
            dst = torch.cat([torch.from_numpy(turned), anchors], 1)
            image = warp_images(image, src, dst, self.synthesizer.triangles)
        out = (image.clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()
        return out, turned

    def render(self, params: np.ndarray, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image ``(H, W, 3)`` uint8 and points ``(N, 2)`` px of one animation vector."""
        images, points = self.render_batch(np.asarray(params)[None], np.asarray(angles)[None])
        return images[0], points[0]
