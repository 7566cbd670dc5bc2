"""Stage ``occlusion.detect``: which face regions an occluder hides, frame by frame, from the image.

A face landmarker stays confident under a hand: its points are a guess there, and nothing in its
output says so. This stage looks at the image where the points put each region (mouth, eyes,
brows, nose; :mod:`stages.occlusion.regions`): a strip across the region's contour
(:mod:`stages.occlusion.profiles`) compared with the clip's own appearance model of that region
(:mod:`stages.occlusion.model`). A region whose structure is not there is occluded.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.bundles import POINTS
from stages.occlusion.bundles import OCCLUSION
from stages.occlusion import model, profiles
from stages.occlusion.regions import REGIONS, region_points


def _params(stage: SequenceStage, params: Mapping[str, Any]) -> dict[str, Any]:
    return {p.name: p.default for p in stage.params} | dict(params)


def region_visibility(
    strips: np.ndarray, face_shape: np.ndarray, profile: profiles.Profile, *, keep: float, median_frames: int
) -> np.ndarray:
    """The visibility of one region in each frame with a face (:mod:`stages.occlusion.model`).

    Parameters
    ----------
    strips : (F, K, M + 2 SHIFT, 2) the region's strips (:func:`profiles.channels`).
    face_shape : (F, P) the face's shape in those frames (:func:`profiles.shape`).
    profile : the region's strip (its ``redder`` test, if any).
    keep, median_frames : the stage's parameters.

    Returns
    -------
    (F,) the running median of the visibility: the template's weight, raised by the template of
    the frames nearest in shape where it is below ``keep`` and, for a region that must be redder
    inside, by its redness contrast.
    """
    win = model.windows(strips, profiles.SHIFT)
    template, seen = model.template(win, positions=strips.shape[1], keep=keep)
    visible = model.visibility(win, template, seen)
    suspect = np.flatnonzero(visible < keep)
    neighbours = max(model.MIN_FRAMES, min(25, int(seen.sum()) // 10))
    visible[suspect] = np.maximum(visible[suspect], model.local_visibility(win, face_shape, seen, suspect, neighbours=neighbours))
    if profile.redder is not None:
        visible = np.maximum(visible, model.relative(profiles.redness_contrast(strips, profile), seen))
    return model.median_filter(visible, median_frames)


class DetectOcclusion(SequenceStage):
    """``occlusion.detect``: per frame and region, whether the region is hidden.

    Inputs: ``frames`` (the decoded clip, streamed chunk by chunk), ``points`` (a
    ``landmarks.layout`` bundle: ``xy (T, N, 2)`` px, ``valid (T, N)``, ``names (N,)``).

    Output bundle ``occlusion``:
    ``regions (R,) str`` (:data:`stages.occlusion.regions.REGIONS`), ``occluded (T, R) bool``,
    ``score (T, R) float32`` the visibility of the region's structure (1.0: as in the clip's
    typical frame; 0: none of it; occluded where the running median of ``median_frames`` frames
    is below ``threshold``; NaN where not judged), ``region_points (R, N) bool`` (which points
    each region covers), ``names (N,) str``, ``valid (T,) bool`` (frames judged: the face's
    points are there). Every frame has a record; a frame without a face is not occluded.
    """

    name = "occlusion.detect"
    version = "1"
    doc = "occluded face regions (mouth, eyes, brows, nose) per frame, from the image against the clip's own appearance"
    inputs = {"frames": "frames", "points": POINTS}
    outputs = {"occlusion": OCCLUSION}
    params = (
        Param("threshold", float, 0.3, "occluded where the region's visibility is below this (1 = as typical)", min=0.0, max=1.0),
        Param("keep", float, 0.5, "visibility above which a frame re-estimates the region's model", min=0.0, max=1.0),
        Param("median_frames", int, 5, "running median of the visibility over this many frames (odd)", min=1, max=31),
    )
    imports = ("cv2",)

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = _params(self, params)
        if int(params["median_frames"]) % 2 == 0:
            raise StageError(f"{self.name}: parameter 'median_frames' must be odd, got {params['median_frames']}")
        points, stream = inputs["points"], inputs["frames"]
        for key in ("xy", "valid", "names"):
            if key not in points:
                raise StageError(f"{self.name}: input 'points': missing key '{key}'")
        xy, names = np.asarray(points["xy"], np.float64), [str(n) for n in points["names"]]
        if xy.ndim != 3 or xy.shape[1:] != (len(names), 2) or np.shape(points["valid"]) != xy.shape[:2]:
            raise StageError(
                f"{self.name}: input 'points': expected xy (T, N, 2), valid (T, N), names (N,); got "
                f"xy {xy.shape}, valid {np.shape(points['valid'])}, names {len(names)}"
            )
        frames = len(xy)
        if stream.info.frames != frames:
            raise StageError(f"{self.name}: input 'frames' has {stream.info.frames} frames, 'points' has {frames}")
        covers = region_points(names)
        judged = [
            r
            for r in REGIONS
            if set(profiles.PROFILES[r].contour)
            | set(profiles.PROFILES[r].pair)
            | set(profiles.PROFILES[r].away)
            | set(profiles.POSE_POINTS)
            <= set(names)
        ]
        valid = np.asarray(points["valid"], bool).all(axis=1) & np.isfinite(xy).all(axis=(1, 2))
        sampler = profiles.make_sampler(names, xy, valid, judged)
        sizes = [int(np.prod(s)) for s in sampler.shapes.values()]
        rgb = np.zeros((frames, sum(sizes), 3), np.float32)
        for start, chunk in stream.chunks():
            for k, frame in enumerate(chunk):
                t = start + k
                if valid[t]:
                    grid, eye = profiles.sample_grid(sampler, xy[t])
                    rgb[t] = profiles.sample_frame(frame, grid, eye)
            ctx.progress(len(chunk))
        score = np.full((frames, len(REGIONS)), np.nan, np.float32)
        occluded = np.zeros((frames, len(REGIONS)), bool)
        ends = np.cumsum([0, *sizes])
        for j, region in enumerate(judged):
            if valid.sum() < model.MIN_FRAMES:
                break
            strips = profiles.channels(rgb[valid, ends[j] : ends[j + 1]].reshape(-1, *sampler.shapes[region], 3))
            seen_score = region_visibility(
                strips,
                profiles.shape(sampler, xy[valid], j),
                profiles.PROFILES[region],
                keep=float(params["keep"]),
                median_frames=int(params["median_frames"]),
            )
            r = REGIONS.index(region)
            score[valid, r] = seen_score
            occluded[valid, r] = seen_score < float(params["threshold"])
        counts = ", ".join(f"{region} {int(occluded[:, r].sum())}" for r, region in enumerate(REGIONS))
        ctx.log.info("%s: occluded frames of %d judged (of %d): %s", self.name, int(valid.sum()), frames, counts)
        return {
            "occlusion": {
                "regions": np.array(REGIONS),
                "occluded": occluded,
                "score": score,
                "region_points": covers,
                "names": np.array(names),
                "valid": valid,
            }
        }
