"""rotations.py: the nearest rotation of nearly orthonormal frames."""
import numpy as np

from mdss_ros.rotations import exp_so3_batch, orthonormalise_batch


def test_orthonormalise_is_the_polar_factor():
    """orthonormalise_batch against the SVD's polar factor U V^T: equal to round-off for
    the orthonormality errors a step's product of rotations leaves (1e-15 .. 1e-8), the
    result orthonormal to round-off; a matrix far from a rotation takes the SVD itself."""
    rng = np.random.default_rng(0)
    R = exp_so3_batch(rng.normal(size=(500, 3)))
    for eps in (1e-15, 1e-12, 1e-8, 1e-3):
        X = R @ (np.eye(3) + eps * rng.normal(size=(500, 3, 3)))
        U, _, Vt = np.linalg.svd(X)
        Y = orthonormalise_batch(X)
        assert np.abs(Y - U @ Vt).max() < 1e-14
        assert np.abs(Y.transpose(0, 2, 1) @ Y - np.eye(3)).max() < 1e-14
        assert np.all(np.linalg.det(Y) > 0)


def test_matrices_from_quats_are_matrix_from_quat_row_by_row():
    """The batched quaternion -> rotation against the scalar one, for random quaternions of
    any length (both normalise) and both signs of w; the result is a rotation."""
    from scipy.spatial.transform import Rotation

    from mdss_ros.rotations import matrices_from_quats, matrix_from_quat
    rng = np.random.default_rng(1)
    q = rng.normal(size=(200, 4)) * rng.uniform(0.1, 10.0, size=(200, 1))
    R = matrices_from_quats(q)
    assert R.shape == (200, 3, 3)
    for k in range(0, 200, 17):
        np.testing.assert_allclose(R[k], matrix_from_quat(q[k]), rtol=0, atol=1e-15)   # norms round apart
    np.testing.assert_allclose(R, Rotation.from_quat(q).as_matrix(), atol=1e-14)
    assert np.abs(R.transpose(0, 2, 1) @ R - np.eye(3)).max() < 1e-14


def test_rotation_angles_from_tiny_to_half_turn():
    """rotation_angles against the angle R was made with (exp_so3 of a random axis), from
    1e-12 rad to pi - 1e-6, batched over any leading shape; an identity that round-off has
    touched reads round-off, not the sqrt(2e-16) ~ 1.5e-8 rad of arccos((tr R - 1) / 2)."""
    from mdss_ros.rotations import rotation_angles
    rng = np.random.default_rng(2)
    axis = rng.normal(size=(7, 3))
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    theta = np.array([1e-12, 1e-8, 1e-4, 0.3, 1.5, 3.0, np.pi - 1e-6])
    R = exp_so3_batch(theta[:, None] * axis)
    got = rotation_angles(R)
    np.testing.assert_allclose(got, theta, rtol=1e-6, atol=0)
    assert rotation_angles(R.reshape(7, 1, 3, 3)).shape == (7, 1)
    # A rotation of nothing with its round-off: R_b^T R_d of two equal rotations.
    Q = exp_so3_batch(rng.normal(size=(50, 3)))
    rel = Q.transpose(0, 2, 1) @ Q
    assert rotation_angles(rel).max() < 1e-15
    assert np.arccos(np.clip(0.5 * (np.trace(rel, axis1=1, axis2=2) - 1.0), -1, 1)).max() > 1e-9   # what it replaces
