"""Stages ``pack.filter``, ``pack.select`` and ``pack.write``: an actor pack from a clip of the
target's face (``pack_build.yaml``; docs/packbuild.md)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Mapping

import numpy as np

from runner.depends import not_recording
from runner.stage import SUMMARY, Context, Param, SequenceStage, StageError
from stages.geometry.bundles import POINTS
from stages.landmarks.bundles import LANDMARKS
from stages.packbuild.bundles import FRAME_FILTER, PACK_SELECTION
from stages.actor_pack import MAX_CAPTURED, MAX_EXAMPLES, MAX_TEETH_EXAMPLES
from stages.geometry.pose import default_intrinsics
from stages.landmarks.stage import layout_and_correspondence
from stages.layout import load_layout
from stages.packbuild.filters import CAUSES, KEEP, cause_counts, classify_frames, head_angles, measure_frames
from stages.geometry.states import SEALED_GAP, coverage_record
from stages.packbuild.selection import FRAMINGS, Selection, compose_similarity, select_frames
from stages.packbuild.writing import write_pack


def _params(stage: SequenceStage, params: Mapping[str, Any]) -> dict[str, Any]:
    return {p.name: p.default for p in stage.params} | dict(params)


def _field(bundle: Mapping[str, Any], key: str, *, stage: str, port: str) -> np.ndarray:
    if key not in bundle:
        raise StageError(f"{stage}: input '{port}': missing key '{key}'")
    return np.asarray(bundle[key])


def _points(inputs: Mapping[str, Any], *, stage: str, frames: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The ``points`` input's ``xy (T, N, 2)`` and per-frame validity ``(T,)``."""
    xy = _field(inputs["points"], "xy", stage=stage, port="points").astype(np.float64)
    valid = _field(inputs["points"], "valid", stage=stage, port="points").astype(bool)
    if xy.ndim != 3 or valid.shape != xy.shape[:2]:
        raise StageError(f"{stage}: input 'points': expected xy (T, N, 2) and valid (T, N), got {xy.shape} and {valid.shape}")
    if frames is not None and len(xy) != frames:
        raise StageError(f"{stage}: input 'points' has {len(xy)} frames, input 'frames' {frames}")
    return xy, valid.all(axis=1) & np.isfinite(xy).all(axis=(1, 2))


def summary(cause: np.ndarray) -> str:
    """``"head_pose 12, blur 3"``: the frames each cause rejected (causes with none left out)."""
    counts = cause_counts(cause)
    return ", ".join(f"{name} {n}" for name, n in zip(CAUSES, counts) if n) or "none"


class PackFilter(SequenceStage):
    """``pack.filter``: usable frames for a pack (:mod:`stages.packbuild.filters`).

    Output bundle ``frame_filter``: ``keep (T,) bool``, ``cause (T,) i1`` (index into
    ``cause_names``, -1 kept), ``cause_names (C,) str``, ``counts (C,) i8`` (frames rejected per
    cause), ``angles (T, 3)`` yaw/pitch/roll in degrees, ``sharpness (T,)``, ``sharpness_rel (T,)``,
    ``colour_change (T,)`` Delta E, ``teeth_fraction (T,)``.
    """

    name = "pack.filter"
    version = "1"
    doc = "reject frames unusable for an actor pack: no face, cut by the border, head turned, blurred, eyes/mouth occluded"
    inputs = {"frames": "frames", "landmarks": LANDMARKS, "points": POINTS}
    outputs = {"filter": FRAME_FILTER}
    params = (
        Param("max_yaw", float, 20.0, "largest |yaw| of a usable frame, degrees", min=0.0, max=180.0),
        Param("max_pitch", float, 15.0, "largest |pitch|, degrees", min=0.0, max=180.0),
        Param("max_roll", float, 15.0, "largest |roll|, degrees", min=0.0, max=180.0),
        Param(
            "min_sharpness",
            float,
            0.5,
            "least Laplacian variance in the face box, fraction of the clip's median",
            min=0.0,
            max=100.0,
        ),
        Param(
            "max_colour_change",
            float,
            10.0,
            "largest Delta E of an eye zone's mean colour (the lips': a*b* only) from the clip's median",
            min=0.0,
            max=500.0,
        ),
        Param("layout", str, "zhang134", "layout name or YAML path", file=True),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = _params(self, params)
        layout = load_layout(params["layout"])
        stream = inputs["frames"]
        xy, valid = _points(inputs, stage=self.name, frames=stream.info.frames)
        matrix = _field(inputs["landmarks"], "matrix", stage=self.name, port="landmarks")
        if matrix.shape != (len(xy), 4, 4):
            raise StageError(f"{self.name}: input 'landmarks' field 'matrix': expected ({len(xy)}, 4, 4), got {matrix.shape}")
        angles = head_angles(matrix, valid)
        measured = measure_frames(self._chunks(stream, ctx), xy, valid, layout)
        cause, scores = classify_frames(
            valid=valid,
            inside=measured["inside"],
            angles=angles,
            sharpness=measured["sharpness"],
            colours=measured["colours"],
            max_yaw=params["max_yaw"],
            max_pitch=params["max_pitch"],
            max_roll=params["max_roll"],
            min_sharpness=params["min_sharpness"],
            max_colour_change=params["max_colour_change"],
        )
        keep = cause == KEEP
        ctx.log.log(SUMMARY, "%s: %d of %d frames usable; rejected: %s", self.name, int(keep.sum()), len(keep), summary(cause))
        if keep.sum() < 2:
            raise StageError(
                f"{self.name}: {int(keep.sum())} of {len(keep)} frames passed the filters (a pack needs 2); "
                f"rejected: {summary(cause)}"
            )
        return {
            "filter": {
                "keep": keep,
                "cause": cause,
                "cause_names": np.array(CAUSES),
                "counts": cause_counts(cause),
                "angles": angles,
                "sharpness": measured["sharpness"],
                "sharpness_rel": scores["sharpness_rel"],
                "colour_change": scores["colour_change"],
                "teeth_fraction": measured["teeth_fraction"],
            }
        }

    @staticmethod
    def _chunks(stream: Any, ctx: Context):
        for start, chunk in stream.chunks():
            if chunk.ndim != 4 or chunk.shape[3] != 3 or chunk.dtype != np.uint8:
                raise StageError(
                    f"pack.filter: input 'frames': expected (H, W, 3) uint8 RGB frames, got {chunk.shape[1:]} {chunk.dtype}"
                )
            yield start, chunk
            ctx.progress(len(chunk))


class PackSelect(SequenceStage):
    """``pack.select``: neutral, standard, examples (greedy k-center), teeth examples and captured
    geometries (:func:`stages.packbuild.selection.select_frames`; with ``compare_3d`` the geometries
    are compared with the head rotation removed in 3D, from the ``points`` input's ``z``).

    Output bundle ``pack_selection``: ``neutral ()``, ``standard ()``, ``examples (k,)``,
    ``teeth (m,)``, ``captured (K,)`` frame indices (int64); ``to_pack (T, 4)`` per frame the
    similarity (a, b, tx, ty) into the pack image; ``size (2,)`` (W, H); ``example_radius_px ()``,
    ``captured_radius_px ()`` coverage radii; ``mouth_open (T,)``; ``warnings (w,) str``.
    """

    name = "pack.select"
    version = "4"
    doc = "choose a pack's neutral, standard, examples (greedy k-center), teeth examples and captured geometries"
    inputs = {"points": POINTS, "landmarks": LANDMARKS, "filter": FRAME_FILTER}
    outputs = {"selection": PACK_SELECTION}
    params = (
        Param("width", int, 384, "pack image width, px", min=32, max=4096),
        Param("height", int, 512, "pack image height, px", min=32, max=4096),
        Param(
            "framing",
            str,
            "head",
            "what the pack's images hold: the face edge to edge, the whole head with a margin, or head and shoulders",
            choices=tuple(FRAMINGS),
        ),
        Param("examples", int, 12, "example expressions (paper: 10-15)", min=2, max=MAX_EXAMPLES),
        Param("captured", int, 35, "captured geometries for PCA, examples included (paper: 30-40)", min=2, max=MAX_CAPTURED),
        Param("teeth", int, 4, "teeth examples (different mouth openings)", min=1, max=MAX_TEETH_EXAMPLES),
        Param("min_distinct_px", float, 1.0, "expressions closer than this (RMS, pack px) are not distinct", min=0.0, max=1000.0),
        Param(
            "pose_deg", float, 10.0, "candidate frames' yaw and pitch within this of the neutral's, degrees", min=0.0, max=180.0
        ),
        Param("min_teeth_open", float, 0.08, "least inner-lip gap of a teeth example, eye distances", min=0.0, max=10.0),
        Param("min_teeth_fraction", float, 0.1, "least share of light, grey pixels inside the inner lips", min=0.0, max=1.0),
        Param("compare_3d", bool, False, "compare expressions with the head rotation removed in 3D (the points' z)"),
        Param("layout", str, "zhang134", "layout name or YAML path", file=True),
        Param(
            "warn_turn_deg",
            float,
            10.0,
            "warn when the neutral's head is turned (yaw or pitch) more than this, degrees",
            min=0.0,
            max=90.0,
        ),
    )

    def _depth(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> np.ndarray | None:
        if not params["compare_3d"]:
            return None
        return _field(inputs["points"], "z", stage=self.name, port="points").astype(np.float64)

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = _params(self, params)
        layout = load_layout(params["layout"])
        xy, _ = _points(inputs, stage=self.name)
        marks, filt = inputs["landmarks"], inputs["filter"]
        keep = _field(filt, "keep", stage=self.name, port="filter").astype(bool)
        if keep.shape != (len(xy),):
            raise StageError(f"{self.name}: input 'filter' field 'keep': expected ({len(xy)},), got {keep.shape}")
        angles = _field(filt, "angles", stage=self.name, port="filter")
        if params["captured"] < params["examples"]:
            raise StageError(
                f"{self.name}: parameter 'captured' ({params['captured']}) must be at least 'examples' ({params['examples']})"
            )
        try:
            chosen = select_frames(
                xy,
                keep,
                layout=layout,
                blendshapes=_field(marks, "blendshapes", stage=self.name, port="landmarks"),
                blendshape_names=_field(marks, "blendshape_names", stage=self.name, port="landmarks"),
                matrix=_field(marks, "matrix", stage=self.name, port="landmarks"),
                angles=angles,
                teeth_fraction=_field(filt, "teeth_fraction", stage=self.name, port="filter"),
                size=(params["width"], params["height"]),
                n_examples=params["examples"],
                n_captured=params["captured"],
                n_teeth=params["teeth"],
                min_distinct_px=params["min_distinct_px"],
                pose_deg=params["pose_deg"],
                min_teeth_open=params["min_teeth_open"],
                min_teeth_fraction=params["min_teeth_fraction"],
                depth=self._depth(inputs, params),
                framing=params["framing"],
                footage=tuple(int(v) for v in marks["size"]) if "size" in marks else None,
            )
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from None
        for line in chosen.warnings:
            ctx.log.warning("%s: %s", self.name, line)
        shown = ", ".join(f"{state.replace('_', ' ')} f{frame}" for state, frame in chosen.states.items())
        yaw, pitch, roll = angles[chosen.neutral]
        ctx.log.log(
            SUMMARY,
            "%s: neutral frame %d (head yaw %+.0f, pitch %+.0f, roll %+.0f deg), standard %d; %d examples "
            "(coverage radius %.2f px) seeded by the states the footage shows: %s; %d teeth, %d captured "
            "(radius %.2f px)",
            self.name,
            chosen.neutral,
            yaw,
            pitch,
            roll,
            chosen.standard,
            len(chosen.examples),
            chosen.example_radius_px,
            shown or "none",
            len(chosen.teeth),
            len(chosen.captured),
            chosen.captured_radius_px,
        )
        if max(abs(yaw), abs(pitch)) > params["warn_turn_deg"]:
            ctx.log.warning(
                "%s: the pack is built at a turned pose (yaw %+.0f, pitch %+.0f deg at the neutral frame %d): "
                "its examples show the face turned, and a frontal performer's expressions are drawn on it "
                "as it is turned",
                self.name,
                yaw,
                pitch,
                chosen.neutral,
            )
        missing = [name for name in ("eye_l_shut", "eye_r_shut") if name not in chosen.states]
        if not (chosen.mouth_open[keep] < SEALED_GAP).any():
            missing.append("lips_sealed")
        if missing:
            ctx.log.warning(
                "%s: no usable frame shows %s: the pack cannot show it (a run still warps the geometry "
                "there, with the nearest example's texture)",
                self.name,
                " or ".join(m.replace("_", " ") for m in missing),
            )
        return {"selection": selection_bundle(chosen, (params["width"], params["height"]))}


def _scaled(params: np.ndarray, scale: float) -> np.ndarray:
    """Similarities ``(..., 4)`` followed by the scaling of an image by ``scale`` about the
    top-left pixel's corner (pixel centres: ``x' = scale (x + 0.5) - 0.5``)."""
    outer = np.array([scale, 0.0, 0.5 * scale - 0.5, 0.5 * scale - 0.5])
    return compose_similarity(outer, params)


def selection_bundle(chosen: Selection, size: tuple[int, int]) -> dict[str, np.ndarray]:
    """A :class:`Selection` as a ``pack_selection`` bundle (see :class:`PackSelect`)."""
    return {
        "neutral": np.int64(chosen.neutral),
        "standard": np.int64(chosen.standard),
        "examples": np.array(chosen.examples, np.int64),
        "teeth": np.array(chosen.teeth, np.int64),
        "captured": np.array(chosen.captured, np.int64),
        "to_pack": chosen.to_pack,
        "size": np.array(size, np.int64),
        "example_radius_px": np.float64(chosen.example_radius_px),
        "captured_radius_px": np.float64(chosen.captured_radius_px),
        "mouth_open": chosen.mouth_open,
        "warnings": np.array(chosen.warnings, dtype=str).reshape(-1),
    }


def selection_from_bundle(bundle: Mapping[str, Any]) -> tuple[Selection, tuple[int, int]]:
    """The inverse of :func:`selection_bundle`: the :class:`Selection` and the pack size (W, H)."""
    try:
        chosen = Selection(
            neutral=int(bundle["neutral"]),
            standard=int(bundle["standard"]),
            examples=[int(v) for v in bundle["examples"]],
            teeth=[int(v) for v in bundle["teeth"]],
            captured=[int(v) for v in bundle["captured"]],
            to_pack=np.asarray(bundle["to_pack"], np.float64),
            example_radius_px=float(bundle["example_radius_px"]),
            captured_radius_px=float(bundle["captured_radius_px"]),
            mouth_open=np.asarray(bundle["mouth_open"]),
            warnings=[str(w) for w in bundle["warnings"]],
        )
    except KeyError as exc:
        raise StageError(f"pack.write: input 'selection': missing key {exc}") from None
    return chosen, (int(bundle["size"][0]), int(bundle["size"][1]))


class PackWrite(SequenceStage):
    """``pack.write``: the actor pack folder (``files`` output ``pack``), validated by
    :func:`stages.actor_pack.load_pack` before the stage returns (:mod:`stages.packbuild.writing`).
    The optional ``valid`` frames (255 = a real pixel, ``photos.decode``'s) say which pixels of
    each frame the validity mattes may count as real."""

    name = "pack.write"
    version = "3"
    doc = "write the actor pack: aligned, exposure-matched images, validity mattes, points, captured.npz, model3d, pack.yaml, sheet.png"
    inputs = {"frames": "frames", "points": POINTS, "selection": PACK_SELECTION, "valid": "frames"}
    optional_inputs = frozenset({"valid"})
    outputs = {"pack": "files"}
    params = (
        Param("name", str, "actor", "the pack's name"),
        Param(
            "width",
            int,
            0,
            "the pack images' width, px (the height keeps pack.select's aspect ratio); 0: pack.select's size",
            min=0,
            max=8192,
        ),
        Param(
            "max_upscale",
            float,
            2.0,
            "refuse a pack whose images would enlarge the footage more than this (pack px per "
            "footage px); any enlargement is warned about with the sizes",
            min=0.01,
            max=100.0,
        ),
        Param(
            "max_gain", float, 2.0, "largest exposure/white-balance gain per channel (and 1 / it the least)", min=1.0, max=100.0
        ),
        Param("layout", str, "zhang134", "layout name or YAML path", file=True),
        Param("correspondence", str, "zhang134_mediapipe", "mesh correspondence name or YAML path (generic 3D model)", file=True),
    )

    @staticmethod
    def _resized(chosen: Selection, size: tuple[int, int], width: int) -> tuple[Selection, tuple[int, int]]:
        """The selection's similarities and size for images ``width`` px wide (0: as selected)."""
        if width in (0, size[0]):
            return chosen, size
        scale = width / size[0]
        return replace(chosen, to_pack=_scaled(chosen.to_pack, scale)), (width, max(round(size[1] * scale), 1))

    def _check_scale(
        self, chosen: Selection, size: tuple[int, int], footage: tuple[int, int], max_upscale: float, ctx: Context
    ) -> None:
        """Warn when the pack images enlarge the footage, refuse beyond ``max_upscale`` (the neutral's scale)."""
        scale = float(np.hypot(*chosen.to_pack[chosen.neutral][:2]))
        if scale <= 1.0:
            return
        held = (round(size[0] / scale), round(size[1] / scale))
        line = (
            f"{self.name}: {size[0]}x{size[1]} pack images enlarge the {footage[0]}x{footage[1]} footage "
            f"{scale:.2f}x (the crop spans {held[0]}x{held[1]} footage px)"
        )
        if scale > max_upscale:
            raise StageError(
                f"{line}, more than max_upscale={max_upscale:g}: ask for width <= "
                f"{int(size[0] * max_upscale / scale)} or raise max_upscale"
            )
        ctx.log.warning("%s; the pack holds no more detail than the footage", line)

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        from stages.actor_pack import load_pack

        params = _params(self, params)
        layout, correspondence = layout_and_correspondence(self.name, params)
        stream = inputs["frames"]
        xy, _ = _points(inputs, stage=self.name, frames=stream.info.frames)
        chosen, size = selection_from_bundle(inputs["selection"])
        chosen, size = self._resized(chosen, size, int(params["width"]))
        self._check_scale(chosen, size, (stream.info.width, stream.info.height), float(params["max_upscale"]), ctx)
        folder = ctx.files_dir("pack")
        folder.mkdir(parents=True, exist_ok=True)
        valid = inputs.get("valid")
        done = write_pack(
            folder,
            name=params["name"],
            layout=layout,
            correspondence=correspondence,
            selection=chosen,
            xy=xy,
            read_frame=lambda t: stream.read(t, t + 1)[0],
            size=size,
            intrinsics=default_intrinsics(size),
            max_gain=params["max_gain"],
            read_valid=None if valid is None else lambda t: valid.read(t, t + 1)[0, ..., 0],
        )
        if done["clipped_points"]:
            ctx.log.warning(
                "%s: %d points of the chosen frames fell outside the %dx%d pack image and were moved to its border",
                self.name,
                done["clipped_points"],
                *size,
            )
        if done["missing"]:
            worst = max(done["missing"], key=done["missing"].get)
            ctx.log.info(
                "%s: %d of %d images reach beyond the footage's frame (at most %.1f %% of %s's pixels); "
                "their mattes (mattes/) mark those pixels, filled from the rest",
                self.name,
                len(done["missing"]),
                2 + len(chosen.examples) + len(chosen.teeth),
                100 * done["missing"][worst],
                worst,
            )
        for label, g in done["gains"].items():
            ctx.log.info("%s: %s exposure gains (linear R, G, B) %.3f %.3f %.3f", self.name, label, *g)
        record = coverage_record(done["coverage"])
        ctx.log.log(
            SUMMARY,
            "%s: the examples show %s; none shows %s (pack.yaml: coverage)",
            self.name,
            ", ".join(n.replace("_", " ") for n in record["shows"]) or "no expression state",
            ", ".join(n.replace("_", " ") for n in record["does_not_show"]) or "-",
        )
        with not_recording():  # a check of what was just written, not an input
            load_pack(folder)
        ctx.progress(len(xy))
        return {"pack": None}
