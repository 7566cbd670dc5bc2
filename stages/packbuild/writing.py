"""Writing an actor pack from chosen frames (format: ``docs/fixtures.md``, ``stages/actor_pack.py``).

Every chosen frame is mapped into the pack's image by its similarity (frame -> neutral's frame ->
upright, centred pack image; :mod:`stages.packbuild.selection`) with ``cv2.warpAffine`` (bilinear),
its layout points by the same similarity. Where the pack image reaches beyond the footage's frame
nothing is repeated from the edge: the image's *validity matte* (the same warp of a plane of ones,
:mod:`stages.fill`) is written beside it (``mattes/<name>.png``, 8-bit, 255 = a real pixel), and
the pixels it leaves out are filled by the push-pull fill of the real ones, so that a bilinear
sample across the matte's edge meets a plausible colour, never black or a streak.

**Exposure and white balance.** Each image other than the neutral is multiplied, per channel and
in linear light (sRGB decoded, IEC 61966-2-1), by the gain ``g_c = mean(neutral_c) /
mean(image_c)`` over the *skin* pixels both faces share: the layout's forehead, glabella, eye-zone,
nose, cheek, philtrum and chin subregions, eyes, brows, lips and mouth excluded (they change with
the expression), rasterized from each face's own points and intersected. Gains are limited to
``[1 / max_gain, max_gain]``. So a frame taken while the light or the camera's automatic exposure
drifted is brought to the neutral's brightness and colour before the examples are blended.

The generic 3D model (``model3d.csv``, Sec. 12.1) is MediaPipe's canonical face mesh
(:func:`stages.landmarks.canonical.canonical_mesh`) through the layout's mesh correspondence,
converted from the mesh's frame (cm; x image-right, y up, z towards the camera) to the pack's head
frame (mm; x right, y down, z away from the camera, origin midway between the inner eye corners).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import yaml

from stages.color import linear_to_srgb, srgb_to_linear
from stages.geometry.compensate import apply_similarity
from stages.geometry.states import coverage, coverage_record
from stages.landmarks.canonical import canonical_mesh
from stages.landmarks.correspondence import Correspondence, layout_from_mesh
from stages.layout import Layout, subregion_mask
from stages.packbuild.selection import Selection

SKIN_SUBREGIONS = ("forehead", "glabella", "eyezone_l", "eyezone_r", "nose", "cheek_l", "cheek_r", "philtrum", "chin")
INNER_EYE_CORNERS = ("eye_l_0", "eye_r_0")


def align_image(
    image: np.ndarray, params: np.ndarray, size: tuple[int, int], *, valid: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Map ``image (H, W, 3) uint8`` by the similarity ``params = (a, b, tx, ty)`` (eq. 8) into an
    image of ``size = (W', H')`` (bilinear), with its validity matte (of the frame's pixels that are
    real: ``valid (H, W) uint8``, 255 = real; every pixel of the frame when omitted).

    Returns
    -------
    image : (H', W', 3) uint8
        The mapped image; the pixels the source does not hold are the push-pull fill of the rest
        (:func:`stages.fill.fill_invalid`).
    matte : (H', W') uint8
        255 where the pixel comes from the source whole, 0 where from beyond its frame, between
        where a bilinear sample straddles the edge.
    """
    import cv2
    from stages.fill import fill_invalid

    a, b, tx, ty = (float(v) for v in params)
    M = np.array([[a, -b, tx], [b, a, ty]])
    size = tuple(int(v) for v in size)
    inside = (
        np.full(image.shape[:2], 255, np.uint8)
        if valid is None
        else np.ascontiguousarray(valid, np.uint8).reshape(image.shape[:2])
    )
    source = (
        np.ascontiguousarray(image) if valid is None else cv2.bitwise_and(image, image, mask=(inside == 255).astype(np.uint8))
    )
    matte = cv2.warpAffine(inside, M, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    mapped = cv2.warpAffine(source, M, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if matte.min() == 255:
        return mapped, matte
    valid = matte.astype(np.float32) / 255.0
    colour = np.divide(
        mapped.astype(np.float32), valid[..., None], out=np.zeros(mapped.shape, np.float32), where=valid[..., None] > 0
    )  # the edge pixels' colour, the black border's share taken out
    filled = fill_invalid(colour, valid)
    return np.clip(np.round(filled), 0, 255).astype(np.uint8), matte


def skin_mask(layout: Layout, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``(H, W) bool``: pixels of the :data:`SKIN_SUBREGIONS` of the face with ``points (N, 2)``."""
    region = subregion_mask(layout, points, size)
    wanted = [k for k, s in enumerate(layout.subregions) if s.name in SKIN_SUBREGIONS]
    return np.isin(region, wanted)


def exposure_gains(image: np.ndarray, reference: np.ndarray, mask: np.ndarray, *, max_gain: float = 2.0) -> np.ndarray:
    """Per-channel linear-light gains bringing ``image`` to ``reference`` over ``mask``.

    Parameters
    ----------
    image, reference : (H, W, 3) uint8 sRGB
    mask : (H, W) bool
        Pixels compared (at least one).
    max_gain : float
        Gains are clipped to ``[1 / max_gain, max_gain]``.

    Returns
    -------
    (3,) float64 ``g_c = mean(srgb_to_linear(reference_c)) / mean(srgb_to_linear(image_c))``.
    """
    if not np.any(mask):
        raise ValueError("exposure_gains: the mask selects no pixel")
    lin = srgb_to_linear(np.asarray(image, np.float64)[mask] / 255.0).mean(0)
    ref = srgb_to_linear(np.asarray(reference, np.float64)[mask] / 255.0).mean(0)
    return np.clip(ref / np.maximum(lin, 1e-6), 1.0 / max_gain, max_gain)


def apply_gains(image: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """``image (H, W, 3) uint8`` sRGB times ``gains (3,)`` in linear light, re-encoded to uint8."""
    lin = srgb_to_linear(np.asarray(image, np.float64) / 255.0) * np.asarray(gains, np.float64)
    return np.round(np.clip(linear_to_srgb(lin), 0.0, 1.0) * 255.0).astype(np.uint8)


def generic_model3d(layout: Layout, correspondence: Correspondence) -> np.ndarray:
    """``(N, 3)`` float64 mm: the canonical face mesh at the layout's points, in the pack's head
    frame (module docstring)."""
    vertices = canonical_mesh().vertices
    m = correspondence.n_vertices
    padded = np.zeros((1, m, 3))
    padded[0, : min(m, len(vertices))] = vertices[:m]
    used = np.flatnonzero(correspondence.weights.any(axis=0))
    if used.max() >= len(vertices):
        raise ValueError(
            f"correspondence {correspondence.name!r} uses mesh vertex {used.max()}, the canonical mesh has {len(vertices)}"
        )
    points = layout_from_mesh(padded, correspondence)[0] * np.array([10.0, -10.0, -10.0])
    origin = points[list(layout.indices(INNER_EYE_CORNERS))].mean(0)
    return points - origin


def _label(image: np.ndarray, text: str) -> np.ndarray:
    import cv2

    out = image.copy()
    for colour, width in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, width, cv2.LINE_AA)
    return out


def contact_sheet(images: Sequence[tuple[str, np.ndarray]], *, columns: int, thumb_height: int) -> np.ndarray:
    """A labelled grid of thumbnails ``thumb_height`` px high (2 px white gaps), ``(H, W, 3) uint8``.

    ``images``: ``(label, (h, w, 3) uint8)`` pairs, all of one aspect ratio, row by row.
    """
    import cv2

    if not images or columns < 1:
        raise ValueError("contact_sheet needs at least one image and one column")
    thumbs = []
    for label, image in images:
        h, w = image.shape[:2]
        thumb = cv2.resize(image, (int(round(w * thumb_height / h)), thumb_height), interpolation=cv2.INTER_AREA)
        thumbs.append(np.pad(_label(thumb, label), ((2, 2), (2, 2), (0, 0)), constant_values=255))
    blank = np.full_like(thumbs[0], 255)
    rows = [
        np.hstack(thumbs[r : r + columns] + [blank] * (columns - len(thumbs[r : r + columns])))
        for r in range(0, len(thumbs), columns)
    ]
    return np.vstack(rows)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an RGB ``(H, W, 3)`` or grey ``(H, W)`` uint8 image as PNG (``OSError`` if it cannot be encoded)."""
    import cv2

    pixels = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, data = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise OSError(f"cannot encode {path}")
    path.write_bytes(data.tobytes())


def write_rows(path: Path, names: Sequence[str], rows: np.ndarray, columns: tuple[str, ...]) -> None:
    """Write a CSV ``name,<columns>`` with one row per name (6 decimals)."""
    lines = [",".join(("name", *columns))]
    lines += [",".join([n] + [f"{v:.6f}" for v in row]) for n, row in zip(names, np.asarray(rows, np.float64))]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def write_pack(
    folder: Path,
    *,
    name: str,
    layout: Layout,
    correspondence: Correspondence,
    selection: Selection,
    xy: np.ndarray,
    read_frame: Callable[[int], np.ndarray],
    size: tuple[int, int],
    intrinsics: np.ndarray,
    max_gain: float = 2.0,
    read_valid: Callable[[int], np.ndarray] | None = None,
) -> dict[str, object]:
    """Write the pack folder: images, points, ``captured.npz``, ``model3d.csv``, ``pack.yaml``, ``sheet.png``.

    Parameters
    ----------
    folder : Path
        An existing, empty folder.
    selection : Selection
        The chosen frames and their similarities into the pack image.
    xy : (T, N, 2) float
        Layout points per frame, px (frame coordinates).
    read_frame : callable
        ``read_frame(t) -> (H, W, 3) uint8`` RGB frame ``t`` of the clip (only chosen frames are read).
    size : (W, H)
        The pack's image size.
    intrinsics : (3, 3)
        Camera matrix written to the manifest.
    read_valid : callable, optional
        ``read_valid(t) -> (H, W) uint8``: which pixels of frame ``t`` are real (255; photos
        brought to one frame size fill a border that is not); every pixel when omitted.

    Returns
    -------
    dict
        ``gains``: ``{entry name: (3,) gains}``; ``clipped_points``: points moved inside the image
        (chosen frames whose face reached past the pack image's border); ``missing``: ``{entry
        name: fraction of the image's pixels beyond the footage's frame}`` (entries with any).

    Each entry of the manifest names its image, points and validity matte (``mattes/<name>.png``,
    :func:`align_image`), the clip frame it was cut from (``frame``) and the similarity that cut it
    (``similarity``: (a, b, tx, ty), footage px -> pack px); ``source`` records the footage's frame
    size and the neutral's scale (pack px per footage px).
    """
    W, H = size
    names = layout.point_names
    points_in_pack = {
        t: apply_similarity(selection.to_pack[t], xy[t])
        for t in {selection.neutral, selection.standard, *selection.examples, *selection.teeth, *selection.captured}
    }
    lo, hi = np.array([-0.5, -0.5]), np.array([W - 0.5, H - 0.5])
    clipped = sum(int(np.sum((p < lo) | (p > hi))) for p in points_in_pack.values())
    points_in_pack = {t: np.clip(p, lo, hi) for t, p in points_in_pack.items()}
    for sub in ("images", "points", "mattes"):
        (folder / sub).mkdir()

    def cut(t: int) -> tuple[np.ndarray, np.ndarray]:
        return align_image(read_frame(t), selection.to_pack[t], size, valid=None if read_valid is None else read_valid(t))

    footage = read_frame(selection.neutral)
    neutral_image, neutral_matte = cut(selection.neutral)
    neutral_skin = skin_mask(layout, points_in_pack[selection.neutral], size) & (neutral_matte == 255)
    gains: dict[str, np.ndarray] = {}
    missing: dict[str, float] = {}
    sheet: list[tuple[str, np.ndarray]] = []

    def entry(label: str, t: int) -> dict[str, object]:
        image, matte = neutral_image, neutral_matte
        if t != selection.neutral:
            image, matte = cut(t)
            mask = neutral_skin & skin_mask(layout, points_in_pack[t], size) & (matte == 255)
            gains[label] = exposure_gains(image, neutral_image, mask, max_gain=max_gain) if mask.any() else np.ones(3)
            image = apply_gains(image, gains[label])
        if matte.min() < 255:
            missing[label] = float(np.mean(255 - matte.astype(np.float64)) / 255.0)
        write_png(folder / "images" / f"{label}.png", image)
        write_png(folder / "mattes" / f"{label}.png", matte)
        write_rows(folder / "points" / f"{label}.csv", names, points_in_pack[t], ("x", "y"))
        sheet.append((label, image))
        return {
            "name": label,
            "image": f"images/{label}.png",
            "points": f"points/{label}.csv",
            "matte": f"mattes/{label}.png",
            "frame": int(t),
            "similarity": [round(float(v), 9) for v in selection.to_pack[t]],
        }

    manifest = {
        "format": "actor-pack/1",
        "name": name,
        "layout": layout.name,
        "image_size": [int(W), int(H)],
        "intrinsics": np.asarray(intrinsics, np.float64).tolist(),
        "model3d": "model3d.csv",
        "source": {
            "size": [int(footage.shape[1]), int(footage.shape[0])],
            "scale": round(float(np.hypot(*selection.to_pack[selection.neutral][:2])), 6),
        },
        "neutral": entry("neutral", selection.neutral),
        "standard": entry("standard", selection.standard),
        "examples": [entry(f"ex_f{t:05d}", t) for t in selection.examples],
        "teeth_examples": [entry(f"teeth_f{t:05d}", t) for t in selection.teeth],
        "captured": "captured.npz",
    }
    covered = coverage(np.stack([points_in_pack[t] for t in selection.examples]), names, points_in_pack[selection.neutral])
    manifest["coverage"] = coverage_record(covered)
    write_rows(folder / "model3d.csv", names, generic_model3d(layout, correspondence), ("x", "y", "z"))
    captured = np.stack([points_in_pack[t] for t in selection.captured])
    np.savez(folder / "captured.npz", points=captured, frames=np.array(selection.captured, np.int64))
    (folder / "pack.yaml").write_text(
        "# Actor pack built from footage by stages.packbuild (docs/packbuild.md)\n"
        + yaml.safe_dump(manifest, sort_keys=False, default_flow_style=None, width=120),
        encoding="utf-8",
    )
    write_png(folder / "sheet.png", contact_sheet(sheet, columns=6, thumb_height=160))
    return {"gains": gains, "clipped_points": clipped, "coverage": covered, "missing": missing}
