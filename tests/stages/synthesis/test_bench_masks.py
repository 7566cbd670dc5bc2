"""The benchmark's wrinkle areas, defined from layout points, land where the wrinkles are."""

from pathlib import Path

import numpy as np

from scripts.bench_synthesis import face_mask, wrinkle_mask
from stages.actor_pack import load_pack

PACK = Path(__file__).resolve().parents[3] / "fixtures" / "packs" / "target"


def test_wrinkle_areas_cover_forehead_furrow_eye_corners_nasolabial_only():
    pack = load_pack(PACK)
    L, pts, size = pack.layout, pack.neutral.points, pack.image_size
    mask = wrinkle_mask(L, pts, size)

    def at(p: np.ndarray) -> bool:
        x, y = np.round(p).astype(int)
        return bool(mask[y, x])

    P = lambda n: pts[L.index(n)]
    assert at(P("forehead_c")) and at(P("glabella"))
    for s, sx in (("l", -1), ("r", 1)):
        eye_w = np.linalg.norm(P(f"eye_{s}_0") - P(f"eye_{s}_6"))
        assert at(P(f"eye_{s}_6") + [sx * 0.5 * eye_w, 0])  # crow's feet, lateral of the outer corner
        assert at(P(f"nasolabial_{s}_1"))
        assert not at(P(f"eye_{s}_0") - [sx * 0.2 * eye_w, 0])  # not the inner eye corner
    for name in ("nose_tip", "chin", "mouth_outer_4", "cheek_l", "cheek_r"):
        assert not at(P(name)), name
    assert 0.05 < mask.sum() / face_mask(L, pts, size).sum() < 0.5
