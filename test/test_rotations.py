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
