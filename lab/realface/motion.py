"""Known motion of a clip: expression parameters over time and the head pose, from a seed.

Expressions are sequences of events on a neutral rest (frame 0 is neutral at the identity pose):

- ``mouth_open``: openings lasting 3-8 frames (a ``sin^2`` bump), 4-25 frames apart;
- ``brow_raise``: raises of 8-14 frames (``sin^2`` bump), 10-40 frames apart;
- ``smile``: 25-60 frames with 6-12-frame smoothstep onsets and offsets, 10-50 frames apart;

amplitudes uniform in [0.5, 1]; each expression's first event starts within frames 3-15. Head motion: yaw, pitch, roll each ``L tanh(r(t) / L)`` with
``r(t) = sum_j a_j (sin(2 pi f_j t + phi_j) - sin(phi_j))`` (two terms, ``f_j`` 0.2-0.6 Hz,
``a_j = 0.7 L``), so the angles start at 0, move slowly and stay within ``+-L``
(:data:`ANGLE_LIMITS_DEG`); translations the same within :data:`SHIFT_LIMITS_MM`.
"""

from __future__ import annotations

import numpy as np

from .expression import EXPRESSIONS, STATE_EXPRESSIONS, smoothstep

ANGLE_LIMITS_DEG = (20.0, 10.0, 10.0)  # yaw, pitch, roll
SHIFT_LIMITS_MM = (8.0, 6.0, 15.0)  # x, y, z
# per expression: event length range, gap range (frames), onset/offset length range (0: a sin^2 bump)
EVENTS = {"mouth_open": ((3, 8), (4, 25), None), "brow_raise": ((8, 14), (10, 40), None), "smile": ((25, 60), (10, 50), (6, 12))}
FIRST_EVENT_BY = 15  # every expression starts by this frame (a short clip shows all three)


def _events(
    rng: np.random.Generator, frames: int, length: tuple[int, int], gap: tuple[int, int], ramp: tuple[int, int] | None
) -> np.ndarray:
    """``(frames,)`` in [0, 1]: events of ``length`` frames separated by ``gap`` frames, the first
    starting at a frame drawn from 3..:data:`FIRST_EVENT_BY`."""
    out = np.zeros(frames)
    f = np.arange(frames, dtype=np.float64)
    start = float(rng.integers(3, FIRST_EVENT_BY + 1))
    while start < frames:
        n = int(rng.integers(length[0], length[1] + 1))
        amp = rng.uniform(0.5, 1.0)
        if ramp is None:
            inside = (f >= start) & (f < start + n)
            shape = np.where(inside, np.sin(np.pi * (f - start + 1) / (n + 1)) ** 2, 0.0)
        else:
            r = int(rng.integers(ramp[0], ramp[1] + 1))
            shape = smoothstep(start, start + r, f) * smoothstep(start + n, start + n - r, f)
        out = np.maximum(out, amp * shape)
        start += n + int(rng.integers(gap[0], gap[1] + 1))
    return out


def _slow(rng: np.random.Generator, seconds: np.ndarray, limit: float) -> np.ndarray:
    raw = np.zeros_like(seconds)
    for _ in range(2):
        f, phi = rng.uniform(0.2, 0.6), rng.uniform(0, 2 * np.pi)
        raw += 0.7 * limit * (np.sin(2 * np.pi * f * seconds + phi) - np.sin(phi))
    return limit * np.tanh(raw / limit)


def make_motion(frames: int, *, seed: int, fps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Expression parameters ``(T, 3)`` in [0, 1] (:data:`EXPRESSIONS` order), head angles
    ``(T, 3)`` degrees (yaw, pitch, roll) and head translation offsets ``(T, 3)`` mm.
    Deterministic from ``seed``."""
    if frames < 1:
        raise ValueError(f"frames: expected >= 1, got {frames}")
    rng = np.random.default_rng(seed)
    params = np.column_stack([_events(rng, frames, *EVENTS[name]) for name in EXPRESSIONS])
    seconds = np.arange(frames) / float(fps)
    angles = np.column_stack([_slow(rng, seconds, lim) for lim in ANGLE_LIMITS_DEG])
    shift = np.column_stack([_slow(rng, seconds, lim) for lim in SHIFT_LIMITS_MM])
    return np.clip(params, 0.0, 1.0), angles, shift


#: The states clip: each state held in turn (``{expression: parameter}``), ramped in over
#: :data:`STATE_RAMP` frames, held :data:`STATE_HOLD`, ramped out, then :data:`STATE_REST` neutral
#: frames. ``no_neutral`` alternates shut eyes with an open mouth, so that no frame is a neutral face,
#: from frame 0 on (a clip cut into the middle of an expression).
STATE_SCRIPTS = {
    "states": (
        ("blink", {"blink_l": 1.0, "blink_r": 1.0}),
        ("wink_l", {"blink_l": 1.0}),
        ("wink_r", {"blink_r": 1.0}),
        ("squint", {"blink_l": 0.5, "blink_r": 0.5}),
        ("wide", {"eye_wide": 1.0}),
        ("jaw_open", {"mouth_open": 1.0}),
        ("smile", {"smile": 1.0}),
        ("o_mouth", {"pucker": 1.0, "mouth_open": 0.5}),
        ("pucker", {"pucker": 1.0}),
        ("lip_press", {"lip_press": 1.0}),
        ("brow_raise", {"brow_raise": 1.0}),
        ("brow_furrow", {"brow_furrow": 1.0}),
    ),
    "no_neutral": (("blink", {"blink_l": 1.0, "blink_r": 1.0}), ("jaw_open", {"mouth_open": 0.6})) * 4,
}
STATE_RAMP, STATE_HOLD, STATE_REST = 3, 8, 4
STATE_ANGLE_LIMITS_DEG = (8.0, 5.0, 4.0)


def state_motion(script: str, *, seed: int, fps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[str, int, int]]]:
    """The motion of a states clip (:data:`STATE_SCRIPTS`): parameters ``(T, 9)`` in
    :data:`STATE_EXPRESSIONS` order, head angles ``(T, 3)`` degrees within
    :data:`STATE_ANGLE_LIMITS_DEG` and translations ``(T, 3)`` mm (slow, from ``seed``), and the
    held spans ``[(state, first, last)]`` (inclusive frames at full parameter). ``no_neutral`` has no
    rest frames: it starts and ends holding a state, and each state ramps straight into the next."""
    if script not in STATE_SCRIPTS:
        raise ValueError(f"script: expected one of {', '.join(STATE_SCRIPTS)}, got {script!r}")
    rest = 0 if script == "no_neutral" else STATE_REST
    length = 2 * STATE_RAMP + STATE_HOLD
    steps = STATE_SCRIPTS[script]
    overlap = STATE_RAMP if rest == 0 else 0
    frames = rest + len(steps) * (length + rest) - overlap * (len(steps) - 1) - overlap
    params = np.zeros((frames, len(STATE_EXPRESSIONS)))
    f = np.arange(frames, dtype=np.float64)
    spans = []
    start = rest - overlap
    for name, values in steps:
        shape = smoothstep(start - 1, start + STATE_RAMP - 1, f) * smoothstep(start + length, start + length - STATE_RAMP, f)
        for expression, value in values.items():
            k = STATE_EXPRESSIONS.index(expression)
            params[:, k] = np.maximum(params[:, k], value * shape)
        spans.append((name, max(start + STATE_RAMP, 0), start + STATE_RAMP + STATE_HOLD - 1))
        start += length + rest - overlap
    if rest == 0:  # ends holding its last state too
        params, f = params[: spans[-1][2] + 1], f[: spans[-1][2] + 1]
    rng = np.random.default_rng(seed)
    seconds = f / float(fps)
    angles = np.column_stack([_slow(rng, seconds, lim) for lim in STATE_ANGLE_LIMITS_DEG])
    shift = np.column_stack([_slow(rng, seconds, lim / 2) for lim in SHIFT_LIMITS_MM])
    return np.clip(params, 0.0, 1.0), angles, shift, spans
