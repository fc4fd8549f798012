"""Rigid-body geometry: SE(3) as 4x4 arrays, SE(2) poses, rotation averaging.

Conventions (see docs/formats.md and DESIGN §2):

* A pose is a 4x4 homogeneous numpy array named ``T_<to>_<from>``: ``p_to = T_to_from @ p_from``.
  ``T_map_base`` is the robot (``base_link``) in the map frame.
* Quaternions are (x, y, z, w), as in ROS, and appear only where messages and files need them.
* SE(2) poses are (x, y, yaw) with yaw in radians, wrapped to [-pi, pi).
* Roll/pitch/yaw (``rpy``) are fixed-axis angles as in tf: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

Every function validates what it is given and raises :class:`GeometryError` (a ``ValueError``)
with a message that names the argument, never returning NaN silently.
"""
from __future__ import annotations

import logging
import math
from typing import Iterable, List, Optional, Sequence, Tuple

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import GeometryError

logger = logging.getLogger(__name__)

_ORTHO_TOL = 1e-5


def _as_array(value, shape: Tuple[int, ...], name: str) -> np.ndarray:
    """Return ``value`` as a finite float64 array of ``shape`` or raise GeometryError."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{name}: expected numbers, got {type(value).__name__} ({exc})") from None
    if arr.shape != shape:
        raise GeometryError(f"{name}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise GeometryError(f"{name}: contains NaN or infinite values")
    return arr


def _as_flat(value, n: int, name: str) -> np.ndarray:
    """``value`` flattened to ``n`` finite floats, or GeometryError (also for ragged nested lists)."""
    try:
        flat = np.ravel(np.asarray(value, dtype=np.float64))
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{name}: expected numbers, got {type(value).__name__} ({exc})") from None
    return _as_array(flat, (n,), name)


def validate_rotation(R, name: str = "rotation", tol: float = _ORTHO_TOL) -> np.ndarray:
    """Check that ``R`` is a 3x3 proper rotation (orthonormal, det +1) and return it as float64."""
    R = _as_array(R, (3, 3), name)
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > tol:
        raise GeometryError(f"{name}: not orthonormal (max |R^T R - I| = {err:.2e})")
    if np.linalg.det(R) < 0.0:
        raise GeometryError(f"{name}: determinant is negative (a reflection, not a rotation)")
    return R


def validate_transform(T, name: str = "transform", tol: float = _ORTHO_TOL) -> np.ndarray:
    """Check that ``T`` is a 4x4 rigid transform and return it as a float64 array."""
    T = _as_array(T, (4, 4), name)
    validate_rotation(T[:3, :3], f"{name} (rotation block)", tol)
    if np.abs(T[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        raise GeometryError(f"{name}: last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    return T


def make_transform(R=None, t=None) -> np.ndarray:
    """Build a 4x4 transform from a 3x3 rotation ``R`` (default identity) and translation ``t`` (m)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = validate_rotation(R, "R")
    if t is not None:
        T[:3, 3] = _as_array(t, (3,), "t")
    return T


def inverse(T) -> np.ndarray:
    """Inverse of a rigid transform (uses R^T, exact for rotations): ``inverse(T_a_b) = T_b_a``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise GeometryError(f"inverse: expected a 4x4 transform, got shape {T.shape}")
    R_t = T[:3, :3].T
    out = _EYE4.copy()   # (a copy of a constant: np.eye's set-up costs more than the rest here)
    out[:3, :3] = R_t
    out[:3, 3] = -R_t @ T[:3, 3]
    return out


_EYE4 = np.eye(4)
_EYE4.flags.writeable = False


def compose(*transforms) -> np.ndarray:
    """Chain transforms left to right: ``compose(T_a_b, T_b_c) = T_a_c``."""
    if not transforms:
        return np.eye(4)
    out = np.asarray(transforms[0], dtype=np.float64)
    for T in transforms[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def transform_points(T, points) -> np.ndarray:
    """Apply ``T`` (4x4) to an (N, 3) array of points; returns (N, 3)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    T = np.asarray(T, dtype=np.float64)
    return pts @ T[:3, :3].T + T[:3, 3]


# --- rotation parametrisations (scipy.spatial.transform.Rotation) ----------------------------

def rotation_from_rvec(rvec) -> np.ndarray:
    """Rodrigues rotation vector (axis * angle, rad) -> 3x3 rotation matrix."""
    return Rotation.from_rotvec(_as_flat(rvec, 3, "rvec")).as_matrix()


def rvec_from_rotation(R) -> np.ndarray:
    """3x3 rotation matrix -> Rodrigues rotation vector (3,), angle in [0, pi]."""
    return Rotation.from_matrix(_as_array(R, (3, 3), "rotation")).as_rotvec()


def skew(v) -> np.ndarray:
    """Cross-product matrices: (..., 3) -> (..., 3, 3) with ``skew(a) @ b == cross(a, b)``.

    Vectorised over leading axes (the bundle adjustment's Jacobians); SciPy has no public one.
    """
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_left_jacobian(w) -> np.ndarray:
    """Left Jacobians of SO(3), (K, 3) -> (K, 3, 3): ``exp(w + d) ~ exp(J_l(w) d) exp(w)``.

    ``J_l(w) = I + (1 - cos t)/t^2 [w]x + (t - sin t)/t^3 [w]x^2`` with ``t = |w|`` (second-order
    Taylor terms below 1e-6 rad). SciPy's Rotation has no Jacobians; vectorised for the bundle
    adjustment.
    """
    w = np.asarray(w, dtype=np.float64)
    th = np.linalg.norm(w, axis=-1)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    b = np.where(small, 0.5 - th ** 2 / 24.0, (1.0 - np.cos(ths)) / ths ** 2)
    c = np.where(small, 1.0 / 6.0 - th ** 2 / 120.0, (ths - np.sin(ths)) / ths ** 3)
    W = skew(w)
    return np.eye(3) + b[..., None, None] * W + c[..., None, None] * (W @ W)


def transform_from_rvec_tvec(rvec, tvec) -> np.ndarray:
    """OpenCV (rvec, tvec) -> 4x4 transform (``T_cam_obj`` for solvePnP output)."""
    T = np.eye(4)
    T[:3, :3] = rotation_from_rvec(rvec)
    T[:3, 3] = _as_flat(tvec, 3, "tvec")
    return T


def rvec_tvec_from_transform(T) -> Tuple[np.ndarray, np.ndarray]:
    """4x4 transform -> (rvec (3,), tvec (3,)) as OpenCV expects them."""
    T = validate_transform(T, "T")
    return rvec_from_rotation(T[:3, :3]), T[:3, 3].copy()


def quaternion_from_matrix(M) -> np.ndarray:
    """Rotation part of a 3x3 or 4x4 matrix -> unit quaternion (x, y, z, w) with w >= 0."""
    M = np.asarray(M, dtype=np.float64)
    if M.shape == (4, 4):
        M = M[:3, :3]
    q = Rotation.from_matrix(_as_array(M, (3, 3), "rotation")).as_quat()
    return -q if q[3] < 0.0 else q


def matrix_from_quaternion(q, name: str = "quaternion") -> np.ndarray:
    """Quaternion (x, y, z, w) -> 3x3 rotation. It must have a norm near 1 (0.9 .. 1.1)."""
    q = _as_flat(q, 4, name)
    n = float(np.linalg.norm(q))
    if not 0.9 < n < 1.1:
        raise GeometryError(f"{name}: norm {n:.4f} is not close to 1 (expected a unit quaternion x, y, z, w)")
    return Rotation.from_quat(q).as_matrix()


def transform_from_translation_quaternion(t, q, name: str = "transform") -> np.ndarray:
    """(x, y, z) and quaternion (x, y, z, w) -> 4x4 transform."""
    T = np.eye(4)
    T[:3, :3] = matrix_from_quaternion(q, f"{name} rotation")
    T[:3, 3] = _as_flat(t, 3, f"{name} translation")
    return T


def matrix_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Fixed-axis roll, pitch, yaw (rad) -> 3x3 rotation ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    return Rotation.from_euler("xyz", [roll, pitch, yaw]).as_matrix()


def transform_from_rpy(roll: float, pitch: float, yaw: float, t) -> np.ndarray:
    """4x4 transform of rotation :func:`matrix_from_rpy` (``Rz(yaw) Ry(pitch) Rx(roll)``) and
    translation ``t`` (3,), on Python floats without validation: a node's per-frame output (SciPy's
    ``Rotation.from_euler`` and :func:`make_transform`'s checks cost ~50 us a call; this ~3)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    x, y, z = (float(v) for v in t)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr, x],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr, y],
                     [-sp, cp * sr, cp * cr, z],
                     [0.0, 0.0, 0.0, 1.0]])


def rpy_from_matrix(M) -> Tuple[float, float, float]:
    """3x3 or 4x4 -> fixed-axis (roll, pitch, yaw) in rad, inverse of :func:`matrix_from_rpy`.

    Not SciPy's ``as_euler("xyz")``: within 1e-7 rad of gimbal lock (pitch +-90 deg) it warns and
    its angles rebuild the matrix only to 2e-7 (measured on random roll and yaw), where these
    formulas stay exact to 3e-16 and put the shared roll/yaw angle in yaw, silently.
    """
    R = np.asarray(M, dtype=np.float64)[:3, :3]
    pitch = float(np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0])))
    if abs(abs(pitch) - np.pi / 2) < 1e-9:
        # Gimbal lock: roll and yaw share one axis; put it all in yaw.
        roll = 0.0
        yaw = float(np.arctan2(-R[0, 1], R[1, 1]))
    else:
        roll = float(np.arctan2(R[2, 1], R[2, 2]))
        yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    return roll, pitch, yaw


def rot_z(yaw: float) -> np.ndarray:
    """3x3 rotation about z by ``yaw`` rad."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_angle(R) -> float:
    """Angle (rad, in [0, pi]) of the rotation ``R`` (3x3 or the rotation block of a 4x4)."""
    R = np.asarray(R, dtype=np.float64)[:3, :3]
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


# --- SE(2) ---------------------------------------------------------------------------------

def wrap_angle(angle):
    """Wrap an angle (or array of angles) in rad to [-pi, pi)."""
    if type(angle) is float:   # the usual call (np.ndim costs more than the arithmetic)
        out = (angle + np.pi) % (2.0 * np.pi) - np.pi
        return -np.pi if out >= np.pi else out
    if np.ndim(angle):
        out = (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi
        # For angles just below -pi the modulo rounds up to exactly 2 pi, giving +pi.
        return np.where(out >= np.pi, -np.pi, out)
    out = float((angle + np.pi) % (2.0 * np.pi) - np.pi)
    return -np.pi if out >= np.pi else out


def angle_diff(a, b):
    """Smallest signed difference ``a - b`` of two angles, in [-pi, pi)."""
    if type(a) is float and type(b) is float:
        return wrap_angle(a - b)
    return wrap_angle(np.asarray(a) - np.asarray(b)) if np.ndim(a) or np.ndim(b) else wrap_angle(a - b)


def se2_from_transform(T) -> np.ndarray:
    """Project a 3D pose onto the ground plane: returns (x, y, yaw).

    yaw is the heading of the frame's x axis projected on the x-y plane, which stays correct for
    small roll and pitch (a robot on a slightly uneven plate).
    """
    T = np.asarray(T, dtype=np.float64)
    return np.array([T[0, 3], T[1, 3], float(np.arctan2(T[1, 0], T[0, 0]))])


def transform_from_se2(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    """(x, y, yaw) -> 4x4 transform at height ``z`` with a rotation about z only."""
    T = _EYE4.copy()
    T[:3, :3] = rot_z(yaw)
    T[:3, 3] = (x, y, z)
    return T


def circular_mean(angles, weights=None) -> float:
    """Weighted mean of angles (rad) on the circle; raises if they cancel out."""
    a = np.asarray(angles, dtype=np.float64).ravel()
    w = np.ones_like(a) if weights is None else np.asarray(weights, dtype=np.float64).ravel()
    s, c = float(np.sum(w * np.sin(a))), float(np.sum(w * np.cos(a)))
    if np.hypot(s, c) < 1e-12:
        raise GeometryError("circular_mean: the angles cancel out, their mean is undefined")
    return float(np.arctan2(s, c))


# --- averaging -----------------------------------------------------------------------------

def _check_weights(n: int, weights: Optional[Sequence[float]]) -> np.ndarray:
    if n == 0:
        raise GeometryError("cannot average an empty list of poses")
    if weights is None:
        return np.full(n, 1.0 / n)
    w = np.asarray(weights, dtype=np.float64).ravel()
    if w.shape != (n,):
        raise GeometryError(f"weights: expected {n} values, got {w.shape[0]}")
    if not np.all(np.isfinite(w)) or np.any(w < 0.0) or w.sum() <= 0.0:
        raise GeometryError("weights: must be finite, non-negative and not all zero")
    return w / w.sum()


def average_rotations(rotations: Iterable, weights: Optional[Sequence[float]] = None) -> np.ndarray:
    """Weighted mean rotation (3x3) of several rotations: SciPy's ``Rotation.mean``.

    That is the quaternion method of Markley et al. (2007): the eigenvector of
    ``sum w_i q_i q_i^T`` with the largest eigenvalue, insensitive to the sign of each
    quaternion, the chordal L2 mean. Averaging Euler angles would be wrong near +-pi.
    """
    Rs = [_as_array(R, (3, 3), f"rotations[{i}]") for i, R in enumerate(rotations)]
    w = _check_weights(len(Rs), weights)
    return Rotation.from_matrix(np.stack(Rs)).mean(weights=w).as_matrix()


def average_transforms(transforms: Iterable, weights: Optional[Sequence[float]] = None) -> np.ndarray:
    """Weighted mean of rigid transforms: rotation by :func:`average_rotations`, translation
    by the weighted arithmetic mean. Exact for identical inputs."""
    transforms = list(transforms)
    A = _valid_transform_stack(transforms)
    if A is None:   # one of them is not a rigid transform (or none given): the per-item check names it
        Ts = [validate_transform(T, f"transforms[{i}]") for i, T in enumerate(transforms)]
        _check_weights(len(Ts), weights)
        A = np.stack(Ts)
    w = _check_weights(len(A), weights)
    out = np.eye(4)
    out[:3, :3] = Rotation.from_matrix(A[:, :3, :3]).mean(weights=w).as_matrix()
    out[:3, 3] = np.sum([wi * T[:3, 3] for wi, T in zip(w, A)], axis=0)
    return out


def _valid_transform_stack(transforms: List) -> Optional[np.ndarray]:
    """The (K, 4, 4) stack of ``transforms`` when every one passes :func:`validate_transform`'s
    checks (all at once: the mapping averages thousands of small sets), else None."""
    try:
        A = np.asarray(transforms, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if A.ndim != 3 or A.shape[1:] != (4, 4) or len(A) == 0 or not np.all(np.isfinite(A)):
        return None
    R = A[:, :3, :3]
    if np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() > _ORTHO_TOL or np.any(np.linalg.det(R) < 0.0):
        return None
    if np.abs(A[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        return None
    return A


def rigid_fit(P, Q, weights: Optional[Sequence[float]] = None) -> np.ndarray:
    """Weighted least-squares rigid transform ``T`` (4x4) with ``Q ≈ T · P`` for (K, 3) point sets.

    The closed-form SVD solution (Kabsch / Umeyama without scale), with the reflection case
    excluded. Needs three non-collinear points for a unique rotation.
    """
    P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
    Q = np.asarray(Q, dtype=np.float64).reshape(-1, 3)
    if P.shape != Q.shape or len(P) < 1:
        raise GeometryError(f"rigid_fit: point sets must have the same shape (K, 3), got {P.shape} and {Q.shape}")
    w = _check_weights(len(P), weights)
    pc, qc = w @ P, w @ Q
    H = ((P - pc) * w[:, None]).T @ (Q - qc)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return make_transform(R, qc - R @ pc)


def pose_distance(T_a, T_b) -> Tuple[float, float]:
    """(translation distance in m, rotation angle in rad) between two poses."""
    D = inverse(T_a) @ np.asarray(T_b, dtype=np.float64)
    return float(np.linalg.norm(D[:3, 3])), rotation_angle(D)


def so3_exp(w) -> np.ndarray:
    """Exponential map so(3) -> SO(3) (alias of :func:`rotation_from_rvec`)."""
    return rotation_from_rvec(w)


def se3_adjoint(T) -> np.ndarray:
    """(6, 6) adjoint of ``T`` for motions ordered (w, v): ``T · exp(xi) = exp(Ad_T xi) · T``, i.e.
    a small motion in ``T``'s child frame expressed in its parent frame."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = skew(t) @ R
    return A


def se3_perturb(T, delta) -> np.ndarray:
    """Left-multiply ``T`` by a small motion ``delta = (wx, wy, wz, tx, ty, tz)``: used by solvers."""
    d = np.asarray(delta, dtype=np.float64).ravel()
    D = np.eye(4)
    D[:3, :3] = rotation_from_rvec(d[:3])
    D[:3, 3] = d[3:6]
    return D @ np.asarray(T, dtype=np.float64)
