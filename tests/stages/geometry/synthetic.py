"""Synthetic ground truth for the geometry tests: a smooth random texture moved by known
sub-pixel similarity transforms and a rigid 3D point model; ``MemoryStream`` and ``context`` come
from :mod:`tests.memory_stream`."""

from __future__ import annotations

import cv2
import numpy as np

from tests.memory_stream import MemoryStream, files_context as context  # noqa: F401 - re-exported for the geometry tests


def similarity_matrix(a: float, b: float, tx: float, ty: float) -> np.ndarray:
    return np.array([[a, -b, tx], [b, a, ty]], dtype=np.float64)


def texture(height: int, width: int, *, seed: int = 0, blur: float = 1.5) -> np.ndarray:
    """A smooth random gray texture ``(height, width)`` float32 in [0, 255]."""
    rng = np.random.default_rng(seed)
    image = cv2.GaussianBlur(rng.uniform(0, 255, (height, width)).astype(np.float32), (0, 0), blur)
    image = (image - image.min()) / (image.max() - image.min()) * 255.0
    return image.astype(np.float32)


def moving_clip(
    n_frames: int, *, size: tuple[int, int] = (160, 120), seed: int = 0, amplitude: float = 4.0
) -> tuple[np.ndarray, np.ndarray]:
    """A clip ``(T, H, W, 3)`` uint8 of a texture under known similarity transforms.

    Returns the frames and the transforms ``(T, 2, 3)`` mapping texture coordinates to frame
    coordinates (frame 0 is the identity); a texture point ``p`` is at ``M_t @ (p, 1)`` in frame t.
    """
    width, height = size
    base = texture(height, width, seed=seed)
    frames, transforms = [], []
    for t in range(n_frames):
        angle = 0.04 * np.sin(t / 7.0)
        scale = 1.0 + 0.03 * np.sin(t / 11.0)
        shift = (amplitude * np.sin(t / 5.0) + 0.13 * t, 0.7 * amplitude * np.sin(t / 6.0 + 0.5))
        a, b = scale * np.cos(angle), scale * np.sin(angle)
        centre = np.array([width / 2.0, height / 2.0])
        # rotate/scale about the image centre, then shift
        t_xy = centre - np.array([a * centre[0] - b * centre[1], b * centre[0] + a * centre[1]]) + shift
        m = similarity_matrix(a, b, *t_xy)
        image = cv2.warpAffine(base, m, (width, height), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        frames.append(np.repeat(np.clip(np.rint(image), 0, 255).astype(np.uint8)[..., None], 3, axis=2))
        transforms.append(m)
    transforms = np.array(transforms)
    first = np.vstack([transforms[0], [0, 0, 1]])
    transforms = np.einsum(
        "tij,jk->tik", np.concatenate([transforms, np.tile([[[0, 0, 1]]], (n_frames, 1, 1))], 1), np.linalg.inv(first)
    )[:, :2]
    return np.stack(frames), transforms


def apply(transforms: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Points ``xy (N, 2)`` of frame 0 carried through ``transforms (T, 2, 3)`` -> ``(T, N, 2)``."""
    return np.einsum("tij,nj->tni", transforms[:, :, :2], xy) + transforms[:, None, :, 2]


def pack_inputs(
    layout,
    *,
    model3d: np.ndarray | None = None,
    camera: np.ndarray | None = None,
    size: tuple[int, int] = (640, 480),
    neutral: np.ndarray | None = None,
    captured: np.ndarray | None = None,
) -> dict:
    """``pack.load``'s ``layout``, ``model3d``, ``camera`` and ``geometry`` bundles of a made-up
    pack of ``layout`` (zeros where an array is not given; ``captured`` defaults to the neutral
    +- 1000 px, a range nothing leaves)."""
    from stages.pack.bundles import layout_to_bundle

    n = layout.n_points
    names = np.array(layout.point_names)
    neutral = np.zeros((n, 2)) if neutral is None else neutral
    captured = neutral[None] + np.array([-1000.0, 1000.0])[:, None, None] if captured is None else captured
    return {
        "layout": layout_to_bundle(layout),
        "model3d": {"names": names, "xyz": np.zeros((n, 3)) if model3d is None else model3d},
        "camera": {"intrinsics": np.eye(3) if camera is None else camera, "size": np.array(size)},
        "geometry": {"names": names, "neutral": neutral, "captured": captured, "examples": neutral[None], "size": np.array(size)},
    }
