"""The fixture generator: same seed same bytes, self-consistent ground truth, packs that load."""

from __future__ import annotations

import hashlib
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from stages.eigen.facegen.face import CONTROLS, expression_points3d
from lab.facegen.sequences import controls_of, farthest_point_selection, similarity_eq9
from stages.eigen.facegen.texture import detail_strengths
from scripts.make_fixtures import Spec, main, make_set, render_identity
from stages.actor_pack import load_pack
from stages.layout import load_layout

REPO = Path(__file__).resolve().parents[2]
TINY = Spec(
    target_size=(72, 96), clip_size=(96, 72), clip_frames=6, fps=30, captured=30, examples=10, heldout_images=2, supersample=1
)


def _digests(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def tiny_set(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fx") / "a"
    make_set(out, seed=5, spec=TINY)
    return out


def test_same_seed_same_bytes(tiny_set, tmp_path):
    again = tmp_path / "b"
    make_set(again, seed=5, spec=TINY)
    first, second = _digests(tiny_set), _digests(again)
    assert first.keys() == second.keys()
    assert {k for k in first if first[k] != second[k]} == set()
    assert "clips/live.mp4" in first and "packs/target/pack.yaml" in first


def _truth_sets() -> list[Path]:
    return sorted((REPO / "fixtures" / "clips").glob("*_truth.npz"))


def _check_clip_truth(path: Path) -> None:
    with np.load(path, allow_pickle=False) as z:
        t = {k: z[k] for k in z.files}
    T, N = t["points"].shape[:2]
    assert t["points3d"].shape == (T, N, 3) and t["visible"].shape == (T, N) and t["R"].shape == (T, 3, 3)
    # projection of the stored 3D points with the stored pose and intrinsics (eq. 10)
    cam = np.einsum("tij,tnj->tni", t["R"], t["points3d"]) + t["tvec"][:, None, :]
    proj = cam @ t["intrinsics"].T
    np.testing.assert_allclose(proj[..., :2] / proj[..., 2:], t["points"], atol=0.01)
    # the same through OpenCV's projectPoints with the stored rvec (an independent implementation)
    for f in (0, T // 2, T - 1):
        img, _ = cv2.projectPoints(t["points3d"][f], t["rvec"][f], t["tvec"][f], t["intrinsics"], None)
        np.testing.assert_allclose(img.reshape(-1, 2), t["points"][f], atol=0.01)
    # similarity = least-squares solution of eq. 9 over the rigid points, by an independent lstsq
    rigid = t["rigid"]
    src = t["neutral_points"][rigid]
    for f in range(T):
        dst = t["points"][f, rigid]
        A = np.zeros((2 * len(rigid), 4))
        A[0::2] = np.column_stack([src[:, 0], -src[:, 1], np.ones(len(src)), np.zeros(len(src))])
        A[1::2] = np.column_stack([src[:, 1], src[:, 0], np.zeros(len(src)), np.ones(len(src))])
        sol = np.linalg.lstsq(A, dst.reshape(-1), rcond=None)[0]
        np.testing.assert_allclose(t["similarity"][f], sol, atol=1e-9)
    # frame 0 is the neutral face at the reference pose
    np.testing.assert_allclose(t["points"][0], t["neutral_points"], atol=1e-9)
    np.testing.assert_allclose(t["similarity"][0], [1, 0, 0, 0], atol=1e-9)
    assert t["controls"].shape == (T, len(CONTROLS)) and t["target_points"].shape == (T, N, 2)
    w, h = t["size"]
    with av.open(str(path.with_name(path.name.replace("_truth.npz", ".mp4")))) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(frames) == T and frames[0].shape == (h, w, 3)


def test_generated_truth_is_self_consistent(tiny_set):
    for kind in ("calm", "live"):
        _check_clip_truth(tiny_set / "clips" / f"{kind}_truth.npz")


def test_committed_truth_is_self_consistent():
    paths = _truth_sets()
    assert [p.name for p in paths] == ["calm_truth.npz", "live_truth.npz"]  # what the loop checks is there
    for path in paths:
        _check_clip_truth(path)


def test_live_clip_covers_the_pose_range(tiny_set):
    with np.load(tiny_set / "clips" / "live_truth.npz") as z:
        rvec, ang = z["rvec"], z["angles_deg"]
    # recompute yaw from R with OpenCV's decomposition and compare with the stored angles
    assert np.max(np.abs(ang[:, 0])) > 15 and np.max(np.abs(np.rad2deg(np.linalg.norm(rvec, axis=1)))) > 15


def test_generated_packs_load_and_follow_the_paper(tiny_set):
    for name in ("performer", "target"):
        pack = load_pack(tiny_set / "packs" / name)
        assert len(pack.examples) == TINY.examples and pack.captured_points.shape[0] == TINY.captured
        with np.load(tiny_set / "packs" / name / "truth.npz") as z:
            ex, held, cap = z["example_index"], z["heldout_index"], z["captured_points"]
            assert len(held) >= 20 and not set(ex) & set(held)
            np.testing.assert_allclose(pack.captured_points, cap)
            for e, k in zip(pack.examples, ex):
                np.testing.assert_allclose(e.points, cap[k], atol=1e-5)  # CSV keeps 6 decimals
        # the generic model is the mean shape, not this identity's own
        with np.load(tiny_set / "packs" / name / "truth.npz") as z:
            assert np.abs(pack.model3d - z["neutral_points3d"]).max() > 0.5


def test_farthest_point_selection_picks_extremes_first():
    v = np.array([[0.0], [1.0], [10.0], [-6.0], [4.0], [5.0]])
    assert list(farthest_point_selection(v, 2)) == [2, 3]
    assert list(farthest_point_selection(v, 3)) == [1, 2, 3]  # 1.0 is 7 from -6, farther than 4.0 from either


def test_similarity_matches_opencv():
    rng = np.random.default_rng(0)
    src = rng.uniform(0, 100, (7, 2))
    a, b, tx, ty = 1.1 * np.cos(0.2), 1.1 * np.sin(0.2), 5.0, -3.0
    dst = src @ np.array([[a, -b], [b, a]]).T + (tx, ty) + rng.normal(0, 0.3, (7, 2))
    M, _ = cv2.estimateAffinePartial2D(src, dst, method=cv2.LMEDS)
    ours = similarity_eq9(src, dst)
    np.testing.assert_allclose(ours, [M[0, 0], M[1, 0], M[0, 2], M[1, 2]], atol=0.05)
    exact = src @ np.array([[a, -b], [b, a]]).T + (tx, ty)
    np.testing.assert_allclose(similarity_eq9(src, exact), [a, b, tx, ty], atol=1e-9)


def test_details_follow_the_deformation():
    layout = load_layout("zhang134")
    from stages.eigen.facegen.face import make_identity, neutral_points3d

    neutral = neutral_points3d(make_identity(3, layout), layout)

    def strengths(**c):
        return detail_strengths(neutral, expression_points3d(neutral, controls_of(**c), layout), layout)

    calm = strengths()
    assert calm["forehead_lines"] == 0 and calm["glabella_furrows"] == 0 and calm["crows_feet_l"] == 0
    assert strengths(inner_brow_raise=1, outer_brow_raise=1)["forehead_lines"] > 0.8
    assert strengths(brow_lower=1)["glabella_furrows"] > 0.8
    smile = strengths(smile=1)
    assert smile["crows_feet_l"] > 0.5 and smile["nasolabial_r"] > calm["nasolabial_r"] + 0.3
    assert strengths(lip_corner_depress=1)["lip_corner_l"] > 0.6
    assert strengths(inner_brow_raise=0.5)["forehead_lines"] < strengths(inner_brow_raise=1)["forehead_lines"]


def test_wrinkles_are_not_a_warp_of_the_neutral():
    """Raised brows add horizontal forehead lines: more vertical-gradient energy above the brows
    than the neutral image has, beyond what the same region of the neutral shows."""
    layout = load_layout("zhang134")
    neutral = render_identity(4, {}, size=(300, 400))
    raised = render_identity(4, {"inner_brow_raise": 1.0, "outer_brow_raise": 1.0}, size=(300, 400))

    def energy(res):
        p = res["points"]
        x0, x1 = int(p[layout.index("brow_l_5"), 0]), int(p[layout.index("brow_r_5"), 0])
        y0 = int(p[layout.index("forehead_c"), 1])
        y1 = int(min(p[layout.index("brow_l_5"), 1], p[layout.index("brow_r_5"), 1])) - 4
        g = cv2.cvtColor(res["image"], cv2.COLOR_RGB2GRAY).astype(np.float64)
        return np.mean(np.abs(np.diff(g[y0:y1, x0:x1], axis=0)))

    assert energy(raised) > 1.3 * energy(neutral)


def test_render_command_writes_image_and_truth(tmp_path):
    prefix = tmp_path / "face"
    assert (
        main(
            [
                "render",
                "--identity",
                "9",
                "--controls",
                "smile=0.7,jaw_drop=0.5",
                "--pose",
                "10,-5,3",
                "--size",
                "64x80",
                "--out",
                str(prefix),
            ]
        )
        == 0
    )
    img = cv2.imread(str(prefix.with_suffix(".png")))
    assert img.shape == (80, 64, 3)
    with np.load(prefix.with_suffix(".npz"), allow_pickle=False) as z:
        assert z["points"].shape == (134, 2) and z["controls"][CONTROLS.index("smile")] == 0.7
        cam = z["points3d"] @ z["R"].T + z["t"]
        proj = cam @ z["intrinsics"].T
        np.testing.assert_allclose(proj[:, :2] / proj[:, 2:], z["points"], atol=1e-9)


def test_teeth_visible_only_with_open_mouth():
    layout = load_layout("zhang134")
    teeth = [layout.index(n) for n in ("teeth_upper_1", "teeth_upper_2", "teeth_lower_1", "teeth_lower_2")]
    closed = render_identity(6, {}, size=(150, 200))
    opened = render_identity(6, {"jaw_drop": 1.0, "upper_lip_raise": 0.5}, size=(150, 200))
    assert not closed["visible"][teeth].any()
    assert opened["visible"][teeth].all()


def test_render_command_reproduces_the_committed_target_pack():
    pack = load_pack(REPO / "fixtures" / "packs" / "target")
    with np.load(REPO / "fixtures" / "packs" / "target" / "truth.npz") as z:
        seed, controls = int(z["identity_seed"]), z["captured_controls"][z["example_index"][0]]
    res = render_identity(seed, controls, size=pack.image_size)
    np.testing.assert_array_equal(res["image"], pack.examples[0].image)
    np.testing.assert_allclose(res["points"], pack.examples[0].points, atol=1e-5)


def test_mesh_barely_folds_under_single_controls():
    """Seen frontally, the face triangles that turn over at any single control at full strength
    cover under 5 mm^2 in all (of about 25,000 mm^2 of face; slivers at the closed mouth corners
    and under the brows)."""
    from stages.eigen.facegen.mesh import HEAD_A, HEAD_B, HEAD_Y0, vertex_positions
    from stages.eigen.facegen.render import make_face

    layout = load_layout("zhang134")
    for seed in (1, 2, 3):
        face = make_face(seed, layout)
        uv, tri = face.mesh.uv, face.mesh.triangles
        rho = np.sqrt((uv[:, 0] / HEAD_A) ** 2 + ((uv[:, 1] - HEAD_Y0) / HEAD_B) ** 2)
        inner = rho[tri].max(axis=1) < 0.97
        for name in CONTROLS:
            v = vertex_positions(face.mesh, expression_points3d(face.neutral, controls_of(**{name: 1.0}), layout))[:, :2]
            e1, e2 = v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]]
            area = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
            assert -area[(area < 0) & inner].sum() < 5.0, (seed, name)


def _opening(points: np.ndarray, layout) -> np.ndarray:
    """Inner-lip gap (mean of the two middle pairs) over the outer-eye-corner distance, ``(...)``."""
    i = layout.index
    gap = points[..., [i("mouth_inner_7"), i("mouth_inner_8")], 1].mean(-1) - points[
        ..., [i("mouth_inner_2"), i("mouth_inner_3")], 1
    ].mean(-1)
    return gap / np.linalg.norm(points[..., i("eye_l_6"), :] - points[..., i("eye_r_6"), :], axis=-1)


def test_jaw_drop_is_the_hinge_then_the_wide_rotation():
    """Chin and lower lip (fully jaw-borne) against scipy's rotations about the two documented axes."""
    from scipy.spatial.transform import Rotation

    from stages.eigen.facegen import face as F

    layout = load_layout("zhang134")
    neutral = F.neutral_points3d(F.make_identity(3, layout), layout)
    rows = [layout.index(n) for n in ("chin", "mouth_inner_7", "teeth_lower_1")]

    def about(points, pivot, deg):
        return Rotation.from_euler("x", deg, degrees=True).apply(points - pivot) + pivot

    for jaw in (0.3, 0.5, 0.8, 1.0):
        got = F.expression_points3d(neutral, controls_of(jaw_drop=jaw), layout)[rows]
        want = about(neutral[rows], F.JAW_PIVOT, F.JAW_MAX_DEG * min(jaw, F.JAW_HINGE_END))
        if jaw > F.JAW_HINGE_END:
            want = about(want, F.JAW_WIDE_PIVOT, F.JAW_WIDE_DEG * (jaw - F.JAW_HINGE_END) / (1 - F.JAW_HINGE_END))
        np.testing.assert_allclose(got, want, atol=1e-9)
    wide = F.expression_points3d(neutral, controls_of(jaw_drop=1.0), layout)
    assert wide[layout.index("chin"), 1] - neutral[layout.index("chin"), 1] > 25.0  # the chin swings down


def test_wide_jaw_drop_opens_the_mouth_to_half_the_eye_distance():
    layout = load_layout("zhang134")
    for seed in (2, 4, 6):
        opening = [
            _opening(render_identity(seed, {"jaw_drop": j}, supersample=1)["points"], layout) for j in (0.0, 0.25, 0.5, 0.75, 1.0)
        ]
        assert np.all(np.diff(opening) > 0.02) and abs(opening[0]) < 0.02
        assert 0.44 < opening[-1] < 0.56, (seed, opening)


def test_committed_target_pack_covers_what_performers_do():
    """Mouth openings to about half the outer-eye-corner distance in the captured geometries, the
    examples and the teeth examples; brows raised and lowered, broad smiles, closed lids among the examples."""
    layout = load_layout("zhang134")
    pack = load_pack(REPO / "fixtures" / "packs" / "target")
    with np.load(REPO / "fixtures" / "packs" / "target" / "truth.npz") as z:
        controls = dict(zip(z["control_names"], z["captured_controls"][z["example_index"]].T))
    assert _opening(pack.captured_points, layout).max() > 0.45
    assert _opening(np.stack([e.points for e in pack.examples]), layout).max() > 0.45
    teeth = _opening(np.stack([e.points for e in pack.teeth_examples]), layout)
    assert teeth.max() > 0.45 and teeth.min() < 0.1
    for name in ("inner_brow_raise", "brow_lower", "smile", "jaw_drop", "lid_close"):
        assert controls[name].max() > 0.8, name


def test_combo_pack_moves_one_region_per_example_and_combines_them_held_out(tmp_path):
    from lab.facegen.sequences import COMBO_HELDOUT, REGION_MOVES
    from scripts.make_fixtures import make_part

    make_part(tmp_path, "pack:combo", seed=5, spec=TINY)
    root = tmp_path / "packs" / "combo"
    pack = load_pack(root)
    layout = pack.layout
    with np.load(root / "truth.npz") as z:
        t = {k: z[k] for k in z.files}
    names = list(t["captured_names"])
    assert [e.name for e in pack.examples] == list(REGION_MOVES) == [names[k] for k in t["example_index"]]
    assert [names[k] for k in t["heldout_index"]] == ["+".join(m) for m in COMBO_HELDOUT]
    assert all((root / p).is_file() for p in t["heldout_image"])
    for k in t["heldout_index"]:
        moves = names[k].split("+")
        np.testing.assert_allclose(t["captured_controls"][k], sum(controls_of(**REGION_MOVES[m]) for m in moves))
    # raised brows with a smile: the brows are those of the brows example, the lip line that of the smile
    both = t["captured_points"][names.index("brows_raised+smile")]
    brows = [i for i, n in enumerate(layout.point_names) if n.startswith("brow_")]
    lips = [i for i, n in enumerate(layout.point_names) if n.startswith("mouth_outer_")]
    np.testing.assert_allclose(both[brows], t["captured_points"][names.index("brows_raised")][brows], atol=1e-9)
    np.testing.assert_allclose(both[lips], t["captured_points"][names.index("smile")][lips], atol=1e-9)
