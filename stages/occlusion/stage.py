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
from stages.occlusion import model, profiles
from stages.occlusion.regions import REGIONS, region_points


def _params(stage: SequenceStage, params: Mapping[str, Any]) -> dict[str, Any]:
    return {p.name: p.default for p in stage.params} | dict(params)


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
    inputs = {"frames": "frames", "points": "points"}
    outputs = {"occlusion": "occlusion"}
    params = (
        Param("threshold", float, 0.3, "occluded where the region's visibility is below this (1 = as typical)",
              min=0.0, max=1.0),
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
            raise StageError(f"{self.name}: input 'points': expected xy (T, N, 2), valid (T, N), names (N,); got "
                             f"xy {xy.shape}, valid {np.shape(points['valid'])}, names {len(names)}")
        frames = len(xy)
        if stream.info.frames != frames:
            raise StageError(f"{self.name}: input 'frames' has {stream.info.frames} frames, 'points' has {frames}")
        covers = region_points(names)
        judged = [r for r in REGIONS if set(profiles.PROFILES[r].contour) | set(profiles.PROFILES[r].pair)
                  | set(profiles.PROFILES[r].away) | set(profiles.POSE_POINTS) <= set(names)]
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
            shape = sampler.shapes[region]
            strips = profiles.channels(rgb[valid, ends[j]:ends[j + 1]].reshape(-1, *shape, 3))
            win = model.windows(strips, profiles.SHIFT)
            t, seen = model.template(win, positions=shape[0], keep=float(params["keep"]))
            seen_score = model.visibility(win, t, seen)
            suspect = np.flatnonzero(seen_score < float(params["keep"]))
            shape_ = profiles.shape(sampler, xy[valid], j)
            seen_score[suspect] = np.maximum(seen_score[suspect], model.local_visibility(
                win, shape_, seen, suspect, neighbours=max(model.MIN_FRAMES, min(25, int(seen.sum()) // 10))))
            if profiles.PROFILES[region].redder is not None:
                seen_score = np.maximum(seen_score, model.relative(profiles.redness_contrast(strips, profiles.PROFILES[region]), seen))
            seen_score = model.median_filter(seen_score, int(params["median_frames"]))
            r = REGIONS.index(region)
            score[valid, r] = seen_score
            occluded[valid, r] = seen_score < float(params["threshold"])
        counts = ", ".join(f"{region} {int(occluded[:, r].sum())}" for r, region in enumerate(REGIONS))
        ctx.log.info("%s: occluded frames of %d judged (of %d): %s", self.name, int(valid.sum()), frames, counts)
        return {"occlusion": {
            "regions": np.array(REGIONS), "occluded": occluded, "score": score, "region_points": covers,
            "names": np.array(names), "valid": valid,
        }}
