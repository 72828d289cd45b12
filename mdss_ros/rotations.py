"""Rotation helpers. Quaternions are (qx, qy, qz, qw), as in ROS messages."""
import numpy as np
from numba import njit


def quat_from_matrix(R):
    """(4,) unit quaternion x y z w of a rotation matrix R (3, 3), w >= 0."""
    t = np.trace(R)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = np.empty(4)
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def matrix_from_quat(q):
    """(3, 3) rotation of a quaternion x y z w (normalised here)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrices_from_quats(q):
    """(n, 3, 3) rotations of quaternions q (n, 4) x y z w (each normalised here):
    matrix_from_quat's formula over all rows at once (that one stays scalar: a collider's
    pose reads it every step, where array slicing would cost more than it saves)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    x, y, z, w = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    R = np.empty((len(q), 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - z * w)
    R[:, 0, 2] = 2 * (x * z + y * w)
    R[:, 1, 0] = 2 * (x * y + z * w)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - x * w)
    R[:, 2, 0] = 2 * (x * z - y * w)
    R[:, 2, 1] = 2 * (y * z + x * w)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def skew(w):
    """(3, 3) cross-product matrix [w]x."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def exp_so3(w):
    """Rotation matrix exp([w]x) (Rodrigues), accurate for small |w|."""
    th = float(np.linalg.norm(w))
    K = skew(w)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th ** 2 * K @ K


def exp_so3_batch(w):
    """exp([w_i]x) for a stack w (n, 3): (n, 3, 3), the same formula as exp_so3 per row
    (one compiled pass: the numpy expression of a dozen small ops cost about 50 us a call)."""
    w = np.ascontiguousarray(w, dtype=np.float64).reshape(-1, 3)
    out = np.empty((len(w), 3, 3))
    _exp_so3_kernel(w, out)
    return out


@njit(cache=True)
def _exp_so3_kernel(w, out):
    for n in range(w.shape[0]):
        exp_so3_into(w[n, 0], w[n, 1], w[n, 2], out[n])


@njit(cache=True)
def exp_so3_into(x, y, z, E):
    """E (3, 3) = exp([w]x) = I + a [w]x + b [w]x^2 for w = (x, y, z), a = sin(t)/t,
    b = (1 - cos t)/t^2 (t = |w|; the limits 1 and 1/2 below t = 1e-8). exp(0) is exactly I."""
    th = np.sqrt(x * x + y * y + z * z)
    if th < 1e-8:
        a, b = 1.0, 0.5
    else:
        a = np.sin(th) / th
        b = (1.0 - np.cos(th)) / th ** 2
    # [w]x^2 = w w^T - |w|^2 I
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    E[0, 0] = 1.0 + b * (-yy - zz)
    E[0, 1] = -a * z + b * xy
    E[0, 2] = a * y + b * xz
    E[1, 0] = a * z + b * xy
    E[1, 1] = 1.0 + b * (-xx - zz)
    E[1, 2] = -a * x + b * yz
    E[2, 0] = -a * y + b * xz
    E[2, 1] = a * x + b * yz
    E[2, 2] = 1.0 + b * (-xx - yy)


def orthonormalise_batch(R):
    """The nearest rotations of a stack R (n, 3, 3) of nearly orthonormal matrices (products
    of rotations, off by round-off), each by orthonormalise_into."""
    R = np.ascontiguousarray(R, dtype=np.float64)
    out = np.empty_like(R)
    _orthonormalise_kernel(R, out)
    return out


@njit(cache=True)
def _orthonormalise_kernel(R, out):
    T = np.empty((3, 3))
    for n in range(R.shape[0]):
        orthonormalise_into(R[n], out[n], T)


@njit(cache=True)
def orthonormalise_into(X, out, T):
    """out (3, 3) = the rotation nearest X (3, 3), a product of rotations off by round-off:
    one Bjorck step X (3 I - X^T X) / 2, which takes an orthonormality error e to O(e^2)
    and converges to the polar factor U V^T. A batched SVD cost 13 us a frame in every
    reduced step (0.08 ms of star_limbs' 1.3 ms); its answer and this one agree to
    round-off for the errors a step leaves (test_rotations). X off by more than 1e-6 (not
    a step's product), or NaN, takes the SVD. T (3, 3) scratch. out must not be X."""
    off = 0.0
    for i in range(3):
        for j in range(3):
            t = X[0, i] * X[0, j] + X[1, i] * X[1, j] + X[2, i] * X[2, j]
            T[i, j] = t
            e = abs(t - (1.0 if i == j else 0.0))
            if not e <= off:
                off = e          # NaN sticks
    if off <= 1e-6:
        for i in range(3):
            for j in range(3):
                out[i, j] = 1.5 * X[i, j] - 0.5 * (X[i, 0] * T[0, j] + X[i, 1] * T[1, j] + X[i, 2] * T[2, j])
    else:
        U, _, Vt = np.linalg.svd(X)
        for i in range(3):
            for j in range(3):
                out[i, j] = U[i, 0] * Vt[0, j] + U[i, 1] * Vt[1, j] + U[i, 2] * Vt[2, j]


def rotation_angles(R):
    """The angle (rad) of each rotation R (..., 3, 3): atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2).

    Why not arccos((tr R - 1) / 2): near the identity it turns the round-off of the trace
    (about 1e-16) into an angle of sqrt(2e-16) ~ 1.5e-8 rad, and a body moved whole read as
    bent by 1e-6 degrees; the sine from the skew part keeps small angles to round-off."""
    R = np.asarray(R, dtype=np.float64)
    s = 0.5 * np.sqrt((R[..., 2, 1] - R[..., 1, 2]) ** 2 + (R[..., 0, 2] - R[..., 2, 0]) ** 2
                      + (R[..., 1, 0] - R[..., 0, 1]) ** 2)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(s, c)


def cross(a, b):
    """a x b for 3-vectors or stacks (..., 3), broadcasting like np.cross. np.cross checks
    and moves axes on every call (~20 us), which the reduced step pays dozens of times."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim == 1 and b.ndim == 1:
        return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    # Written column by column into one array instead of np.stack's expand-and-concatenate:
    # 8.0 -> 7.3 us for a (3,) x (30, 3) call (min of 5,000), the same values.
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out

