"""The trackers' options and their defaults, in one place (``NCCTracker``, ``make_tracker`` and
``track.correlation``'s parameters all read them from :class:`TrackerOptions`)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Mapping


@dataclass(frozen=True)
class TrackerOptions:
    """Options of the point trackers (:mod:`stages.geometry.tracking`); the meaning of each is in
    the help of ``track.correlation``'s parameter of the same name.

    ``template_px``, ``search_px`` (px) apply to every method (the LK window, the OpenCV
    trackers' box ``template_px + 2 * search_px``); ``fb_px`` to ``lk``; the others to ``ncc``,
    the ``model_*`` ones with a face model only.
    """

    template_px: int = 15
    search_px: int = 8
    min_score: float = 0.7
    min_psr: float = 0.0
    min_contrast: float = 2.0
    anchor_score: float = 0.9
    warp_frac: float = 0.3
    lk_iterations: int = 2
    lk_sigma_px: float = 2.0
    prior: float = 0.03
    prior_frac: float = 1.5
    fb_px: float = 1.0
    model_prior: float = 1.0
    model_ridge: float = 1.0
    model_noise_px: float = 3.0
    model_noise_rate: float = 0.2

    @classmethod
    def of(cls, values: Mapping[str, Any]) -> "TrackerOptions":
        """The options named in ``values`` (other keys ignored), defaults for the rest."""
        return cls(**{f.name: values[f.name] for f in fields(cls) if f.name in values})


DEFAULTS = TrackerOptions()
