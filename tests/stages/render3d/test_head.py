"""The performer's relative head pose carried onto the target mesh (Sec. 14.1)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.render3d.head import apply_head, head_motion_3d

A = np.array([[384.0, 0.0, 119.5], [0.0, 384.0, 159.5], [0.0, 0.0, 1.0]])
PIVOT = np.array([3.0, -10.0, 330.0])
CENTER = np.array([160.0, 120.0])


def project(X: np.ndarray) -> np.ndarray:
    q = X @ A.T
    return q[..., :2] / q[..., 2:3]


def motion(R, tvec, scale, ratio=1.0):
    return head_motion_3d(
        np.asarray(R)[None],
        np.asarray(tvec, float)[None],
        np.array([scale]),
        source_center=CENTER,
        pivot=PIVOT,
        A=A,
        size_ratio=ratio,
    )


def test_reference_pose_leaves_the_mesh_in_place():
    R, t = motion(np.eye(3), [0, 0, 0], 1.0)
    np.testing.assert_allclose(R[0], np.eye(3))
    np.testing.assert_allclose(t[0], 0.0, atol=1e-9)


def test_rotation_turns_about_the_pivot():
    Rp = Rotation.from_euler("y", 20, degrees=True).as_matrix()
    c = np.array([*CENTER, 0.0])
    R, t = motion(Rp, c - Rp @ c, 1.0)  # the performer turns about its face centre: the centre stays
    np.testing.assert_allclose(apply_head(PIVOT[None], R[0], t[0])[0], PIVOT, atol=1e-9)
    np.testing.assert_allclose(R[0], Rp)


def test_translation_is_scaled_by_the_face_size_ratio_and_scale_moves_in_depth():
    _, t = motion(np.eye(3), [10.0, -4.0, 0.0], 1.0, ratio=0.5)
    moved = apply_head(PIVOT[None], np.eye(3), t[0])[0]
    np.testing.assert_allclose(project(moved) - project(PIVOT), [5.0, -2.0], atol=1e-9)
    assert moved[2] == pytest.approx(PIVOT[2])
    _, t = motion(np.eye(3), [0.0, 0.0, 0.0], 2.0)
    moved = apply_head(PIVOT[None], np.eye(3), t[0])[0]
    assert moved[2] == pytest.approx(PIVOT[2] / 2.0)
    c = np.array([*CENTER, 0.0])
    np.testing.assert_allclose(project(moved), project(PIVOT) + (2.0 * c - c)[:2], atol=1e-9)


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="scale"):
        motion(np.eye(3), [0, 0, 0], 0.0)
    with pytest.raises(ValueError, match="expected"):
        head_motion_3d(np.eye(3), np.zeros(3), np.ones(1), source_center=CENTER, pivot=PIVOT, A=A, size_ratio=1.0)


def test_reference_rotation_turns_the_mesh_but_not_the_pivot_path():
    Rref = Rotation.from_euler("y", 15, degrees=True).as_matrix()
    R, t = head_motion_3d(
        np.eye(3)[None],
        np.array([[6.0, 0.0, 0.0]]),
        np.ones(1),
        source_center=CENTER,
        pivot=PIVOT,
        A=A,
        size_ratio=1.0,
        reference=Rref,
    )
    np.testing.assert_allclose(R[0], Rref)
    moved = apply_head(PIVOT[None], R[0], t[0])[0]
    np.testing.assert_allclose(project(moved) - project(PIVOT), [6.0, 0.0], atol=1e-9)
