"""Motion propagation of a drag with the pinned set's sweeps recorded (stages/propagation/pinned.py)
against the library's propagate_edit, and the recording in use."""

from __future__ import annotations

import numpy as np
import pytest

from editor.geometry import edited_geometry
from stages.actor_pack import load_pack
from stages.propagation.pinned import MAX_RECORDED_PINS, PinnedPropagation
from stages.propagation.propagate import propagate_edit
from tests.editor.conftest import PACK

LIP, WING, BROW = "mouth_outer_12", "nose_ala_l", "brow_l_2"


@pytest.fixture(scope="module")
def pca(pipeline):
    return pipeline[1]


def index(name: str) -> int:
    return load_pack(PACK).layout.point_names.index(name)


def drag(pca, names, steps: int = 6):
    """Pinned sets along a drag of the first of ``names`` (the others pinned where they are)."""
    neutral = pca.neutral
    points = [index(n) for n in names]
    for t in np.linspace(0.2, 2 * np.pi, steps):
        yield {i: neutral[i] + ([6.0 * np.sin(t), 9.0 * (1 - np.cos(t))] if k == 0 else [0.0, 0.0]) for k, i in enumerate(points)}


def test_drags_are_propagate_edit(pca):
    propagation = PinnedPropagation(pca)
    # one set dragged, another set, then the first again (the recording is replaced each time)
    for names in ([LIP], [LIP, BROW], [LIP]):
        for fixed in drag(pca, names):
            np.testing.assert_allclose(
                propagation(pca, pca.neutral, fixed), propagate_edit(pca, pca.neutral, fixed), rtol=0, atol=1e-9
            )


def test_touching_up_a_frame_is_edited_geometry_with_propagate_edit(pca):
    base = load_pack(PACK).captured_points[3]
    propagation = PinnedPropagation(pca)
    for fixed in drag(pca, [LIP, WING]):
        pinned = {i: xy - pca.neutral[i] + base[i] for i, xy in fixed.items()}
        expected = edited_geometry(pca, pinned, base=base)
        np.testing.assert_allclose(edited_geometry(pca, pinned, base=base, propagate=propagation), expected, rtol=0, atol=1e-9)


def test_the_recorded_sweeps_are_replayed(pca, monkeypatch):
    propagation = PinnedPropagation(pca)
    sweeps = []
    real = propagation.sweep
    monkeypatch.setattr(propagation, "sweep", lambda v, start: (sweeps.append(start), real(v, start)))
    fixed = list(drag(pca, [LIP], steps=8))
    propagation(pca, pca.neutral, fixed[3])  # the largest displacement of the drag first
    recorded = len(sweeps)
    assert recorded > 0
    for f in fixed:
        np.testing.assert_allclose(propagation(pca, pca.neutral, f), propagate_edit(pca, pca.neutral, f), rtol=0, atol=1e-9)
    # the other positions stopped within the recorded iterations, or needed few more
    assert len(sweeps) < recorded + 32


def test_many_pins_and_bad_input_go_to_propagate_edit(pca):
    propagation = PinnedPropagation(pca)
    rng = np.random.default_rng(5)
    many = {int(i): pca.neutral[i] + rng.normal(0, 1, 2) for i in rng.choice(pca.n_points, MAX_RECORDED_PINS + 1, replace=False)}
    np.testing.assert_array_equal(propagation(pca, pca.neutral, many), propagate_edit(pca, pca.neutral, many))
    with pytest.raises(ValueError, match="outside"):
        propagation(pca, pca.neutral, {pca.n_points: (1.0, 2.0)})
    with pytest.raises(ValueError, match="NaN or infinite"):
        propagation(pca, pca.neutral, {3: (np.nan, 2.0)})
    with pytest.raises(ValueError, match="another HierarchicalPCA"):
        propagation(object(), pca.neutral, {3: (1.0, 2.0)})
