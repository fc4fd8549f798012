"""Motion between two stamps: wheel odometry (and an IMU yaw rate) or the filter's own velocity (issue 12).

Two users:

* **free-running cameras**: each camera's detections are taken at their own stamp ``t_c``; the
  robot's motion from the ring frame's stamp ``t_ref`` to ``t_c`` (a body-frame SE(2) displacement
  ``D_c`` with its covariance) moves that camera's extrinsics: the camera saw the map from
  ``T_map_base(t_ref) · D_c · T_base_cam`` (:meth:`localization.RingLocalizer.process`);
* **odometry in the filter**: the pose filter is predicted with odometry increments between
  camera frames and bridges marker blackouts (:meth:`kalman.PoseFilter.predict_increment`).

Conventions: an SE(2) pose or displacement is ``(x, y, yaw)``; a displacement ``d`` from ``t0`` to
``t1`` is expressed in the body frame at ``t0``: ``pose(t1) = pose(t0) ⊕ d``. Covariances are 3x3
over ``(x, y, yaw)`` of ``d`` in that frame.

The noise model of wheel odometry (per increment, added to the filter's covariance, summed over
increments so that it grows like a random walk with the distance driven)::

    var(x) = var(y) = translation_noise^2 * |d_xy|          translation_noise: m per sqrt(m)
    var(yaw) = rotation_noise^2 * |d_yaw| + yaw_drift^2 * |d_xy|     rad per sqrt(rad), rad per sqrt(m)
    + min_noise^2 * dt on each (the robot is never known better than that at rest)

With the IMU, the yaw increment is the integrated gyro rate (trapezoid) and its variance
``imu_yaw_rate_noise^2 * dt``.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Deque, Optional, Tuple

import numpy as np

from . import geometry as geo
from .config import param
from .errors import ConfigError


@dataclass(frozen=True)
class MotionParams:
    """Free-running cameras and odometry in the filter (the localizer's ``motion`` section)."""

    compensate_stamps: bool = param(True, "free-running cameras: each camera's detections are used at their own "
                                          "stamp, its extrinsics moved by the robot's motion from the ring frame's "
                                          "stamp (odometry when it covers the interval, else the filter's velocity), "
                                          "with that motion's uncertainty; false: every camera taken at the ring "
                                          "frame's stamp (synchronized cameras)")
    odometry: bool = param(False, "predict the filter with the wheel-odometry increments of odom's pose between "
                                  "camera frames, publish the pose at every odom message (the odometry rate) and "
                                  "bridge marker blackouts with it (filter/model 6dof: the 6-DOF tracker along the "
                                  "increments of odom's full pose, e.g. a visual-inertial odometry, its pose at every "
                                  "odom message too, up to tracker6/max_coast after the last accepted measurement); "
                                  "false: the paper's filter (odom only opens the gate)")
    imu: bool = param(False, "with odometry: the yaw increments from the yaw rate of sensor_msgs/Imu on `imu` "
                             "(angular_velocity.z) instead of the wheels'")
    translation_noise: float = param(0.02, "odometry's position error after 1 m driven (grows with the square "
                                           "root of the distance)", unit="m/sqrt(m)")
    rotation_noise: float = param(0.02, "odometry's yaw error after turning 1 rad (grows with the square root)",
                                  unit="rad/sqrt(rad)")
    yaw_drift: float = param(0.005, "odometry's yaw error after 1 m driven straight", unit="rad/sqrt(m)")
    min_noise: float = param(0.002, "floor of the odometry's error per second (on x, y and yaw), also at rest",
                             unit="m/sqrt(s)")
    imu_yaw_rate_noise: float = param(0.005, "the IMU's yaw-rate white noise (its yaw error after 1 s)",
                                      unit="rad/sqrt(s)")
    max_gap: float = param(0.25, "two odom (or imu) messages farther apart than this are not bridged: the filter "
                                 "uses its own motion model over the gap", unit="s")
    history: float = param(3.0, "odometry kept for stamps this far back (camera latency, free-running cameras)",
                           unit="s")

    def __post_init__(self) -> None:
        for name in ("translation_noise", "rotation_noise", "yaw_drift", "min_noise", "imu_yaw_rate_noise"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"must be finite and >= 0, got {v!r}", key=name)
        for name in ("max_gap", "history"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"must be finite and > 0, got {v!r}", key=name)
        if self.imu and not self.odometry:
            raise ConfigError("imu: true needs odometry: true (the IMU replaces the wheels' yaw increments)",
                              key="imu")


# --- SE(2) helpers ------------------------------------------------------------------------------

def se2_compose(a, b) -> np.ndarray:
    """``a ⊕ b``: ``b`` (in ``a``'s frame) after ``a``."""
    x, y, t = float(a[0]), float(a[1]), float(a[2])
    c, s = np.cos(t), np.sin(t)
    return np.array([x + c * b[0] - s * b[1], y + s * b[0] + c * b[1], geo.wrap_angle(t + float(b[2]))])


def se2_compose_jacobians(a, b) -> Tuple[np.ndarray, np.ndarray]:
    """(J_a, J_b): 3x3 derivatives of ``a ⊕ b`` by ``a`` and by ``b``."""
    t = float(a[2])
    c, s = np.cos(t), np.sin(t)
    Ja = np.eye(3)
    Ja[0, 2] = -s * float(b[0]) - c * float(b[1])
    Ja[1, 2] = c * float(b[0]) - s * float(b[1])
    Jb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return Ja, Jb


def propagate_se2(pose, cov, d, cov_d) -> Tuple[np.ndarray, np.ndarray]:
    """``pose ⊕ d`` and its covariance (first order; the errors of ``pose`` and ``d`` independent)."""
    Ja, Jb = se2_compose_jacobians(pose, d)
    C = Ja @ np.asarray(cov, dtype=np.float64) @ Ja.T + Jb @ np.asarray(cov_d, dtype=np.float64) @ Jb.T
    return se2_compose(pose, d), 0.5 * (C + C.T)


def se2_between(a, b) -> np.ndarray:
    """``a^-1 ⊕ b``: ``b`` in ``a``'s frame (the displacement from pose ``a`` to pose ``b``)."""
    dx, dy = float(b[0]) - float(a[0]), float(b[1]) - float(a[1])
    c, s = np.cos(float(a[2])), np.sin(float(a[2]))
    return np.array([c * dx + s * dy, -s * dx + c * dy, geo.angle_diff(float(b[2]), float(a[2]))])


def se2_inverse(d) -> np.ndarray:
    """``d^-1``."""
    return se2_between(d, np.zeros(3))


def constant_velocity_displacement(twist, dt: float) -> np.ndarray:
    """Body-frame displacement after ``dt`` s at the constant body twist ``(v_x, v_y, w)`` (an exact
    arc; ``dt`` may be negative: the displacement back in time)."""
    vx, vy, w = (float(v) for v in twist)
    th = w * dt
    if abs(th) < 1e-9:
        a, b = dt, 0.5 * w * dt * dt
    else:
        a, b = np.sin(th) / w, (1.0 - np.cos(th)) / w
    return np.array([a * vx - b * vy, b * vx + a * vy, th])


def displacement_to_transform(d) -> np.ndarray:
    """(4, 4) of a planar displacement (z, roll, pitch zero)."""
    return geo.transform_from_se2(float(d[0]), float(d[1]), float(d[2]))


def odometry_in_base(T_odom_child: Optional[np.ndarray], linear, angular,
                     T_base_child: np.ndarray) -> Tuple[Optional[np.ndarray], np.ndarray, np.ndarray]:
    """An odometry of a body rigidly mounted on the robot (nav_msgs/Odometry ``child_frame_id``, e.g.
    a visual-inertial odometry's IMU frame) as base_link's: the pose ``T_odom_base = T_odom_child ·
    T_base_child⁻¹`` (None stays None) and the twist, given in the child frame (nav_msgs), in
    base_link's: ``ω_b = R ω_c``, ``v_b = R v_c - ω_b × t`` (the base origin's velocity; ``R``, ``t``:
    ``T_base_child``'s rotation and translation)."""
    R, t = T_base_child[:3, :3], T_base_child[:3, 3]
    w = R @ np.asarray(angular, dtype=float)
    v = R @ np.asarray(linear, dtype=float) - np.cross(w, t)
    T = None if T_odom_child is None else T_odom_child @ geo.inverse(T_base_child)
    return T, v, w


def _append(buf: deque, stamp: float, value, history: float) -> bool:
    """``(stamp, value)`` appended to a stamp-sorted history ``buf``, whose entries older than
    ``history`` s before it go (the last two kept); False, and nothing appended, when ``stamp`` is
    not after the latest one."""
    if buf and stamp <= buf[-1][0]:
        return False
    buf.append((stamp, value))
    _trim(buf, stamp, history)
    return True


def _trim(buf: deque, stamp: float, history: float) -> None:
    """Drop the entries of ``buf`` older than ``history`` s before ``stamp`` (the last two kept)."""
    while len(buf) > 2 and buf[1][0] < stamp - history:
        buf.popleft()


def _bracket(buf, t: float):
    """The two entries of a stamp-sorted history ``buf`` ((stamp, pose) pairs) around ``t``, by
    binary search (short: history / odometry period entries); None outside the history."""
    if not buf or t < buf[0][0] or t > buf[-1][0]:
        return None
    lo, hi = 0, len(buf) - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if buf[mid][0] <= t:
            lo = mid
        else:
            hi = mid
    return buf[lo], buf[hi]


def body_covariance_to_perturbation(cov3: np.ndarray) -> np.ndarray:
    """(6, 6) covariance over a left perturbation (w, v) from a 3x3 one over (x, y, yaw)."""
    C = np.zeros((6, 6))
    idx = [3, 4, 2]
    C[np.ix_(idx, idx)] = np.asarray(cov3, dtype=np.float64).reshape(3, 3)
    return C


def body_factor_to_perturbation(F3: np.ndarray) -> np.ndarray:
    """(6, k) factor over a left perturbation (w, v) from a (3, k) one over (x, y, yaw), as
    :func:`body_covariance_to_perturbation` (``F F^T`` maps to that of the covariance)."""
    F3 = np.asarray(F3, dtype=np.float64)
    if F3.ndim != 2 or F3.shape[0] != 3:
        raise ValueError(f"a displacement error factor must be (3, k), got shape {F3.shape}")
    F = np.zeros((6, F3.shape[1]))
    F[[3, 4, 2]] = F3
    return F


def psd_factor(S: np.ndarray) -> np.ndarray:
    """``L`` with ``L L^T = S`` for a symmetric positive semi-definite ``S`` (negative eigenvalues,
    rounding, clipped to zero)."""
    lam, U = np.linalg.eigh(0.5 * (np.asarray(S, dtype=np.float64) + np.asarray(S, dtype=np.float64).T))
    return U * np.sqrt(np.clip(lam, 0.0, None))


# --- the odometry history -----------------------------------------------------------------------

class OdometryHistory:
    """Recent odometry poses (and IMU yaw) by stamp, for increments between any two stamps in them.

    ``add_odometry(stamp, pose)`` takes base_link's pose in the odom frame (``(x, y, yaw)``);
    :meth:`increment` interpolates it at both stamps (linearly within a gap no longer than
    ``max_gap``) and returns the body-frame displacement with its covariance. With ``use_imu``
    the yaw of the displacement is the IMU's integrated yaw rate over the same interval.
    Stamps must increase; an older one is refused (returns False).
    """

    def __init__(self, params: MotionParams):
        self.params = params
        self._odom: Deque[Tuple[float, np.ndarray]] = deque()
        self._imu: Deque[Tuple[float, float, float]] = deque()   # (stamp, integrated yaw, rate)

    def reset(self) -> None:
        self._odom.clear()
        self._imu.clear()

    @property
    def latest_stamp(self) -> Optional[float]:
        return self._odom[-1][0] if self._odom else None

    def add_odometry(self, stamp: float, pose) -> bool:
        return _append(self._odom, float(stamp), np.array(pose, dtype=np.float64).reshape(3), self.params.history)

    def add_yaw_rate(self, stamp: float, rate: float) -> bool:
        stamp, rate = float(stamp), float(rate)
        if self._imu and stamp <= self._imu[-1][0]:
            return False
        if self._imu and stamp - self._imu[-1][0] <= self.params.max_gap:
            t0, yaw0, r0 = self._imu[-1]
            yaw = yaw0 + 0.5 * (r0 + rate) * (stamp - t0)
        else:
            yaw = self._imu[-1][1] if self._imu else 0.0   # a gap: the integral restarts (only differences count)
            if self._imu:
                self._imu.clear()
        self._imu.append((stamp, yaw, rate))
        _trim(self._imu, stamp, self.params.history)
        return True

    def pose_at(self, t: float) -> Optional[np.ndarray]:
        """Odometry pose (x, y, yaw) at ``t``, interpolated; None outside the history or in a gap."""
        pair = _bracket(self._odom, t)
        if pair is None:
            return None
        (ta, pa), (tb, pb) = pair
        if tb - ta > self.params.max_gap and ta != t and tb != t:
            return None
        if tb <= ta:
            return pa.copy()
        f = (t - ta) / (tb - ta)
        d = se2_between(pa, pb)
        return se2_compose(pa, f * d)

    def _imu_yaw_at(self, t: float) -> Optional[float]:
        buf = self._imu
        if not buf or t < buf[0][0] or t > buf[-1][0]:
            return None
        for k in range(len(buf) - 1, -1, -1):
            if buf[k][0] <= t:
                ta, ya, ra = buf[k]
                if k + 1 == len(buf):
                    return ya
                tb, yb, _ = buf[k + 1]
                if tb - ta > self.params.max_gap:
                    return None
                return ya + (yb - ya) * (t - ta) / (tb - ta) if tb > ta else ya
        return None

    def covers(self, t0: float, t1: float) -> bool:
        return self.pose_at(t0) is not None and self.pose_at(t1) is not None

    def increment(self, t0: float, t1: float) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """``(d, cov)``: base_link's displacement from ``t0`` to ``t1`` in its frame at ``t0`` and the
        3x3 covariance of the odometry's error on it; None when the history does not cover both
        stamps (or the IMU's, with ``use_imu``). ``t1 < t0`` gives the displacement back in time."""
        a, b = self.pose_at(t0), self.pose_at(t1)
        if a is None or b is None:
            return None
        d = se2_between(a, b)
        p = self.params
        dist = float(np.hypot(d[0], d[1]))
        dt = abs(float(t1) - float(t0))
        var_xy = p.translation_noise ** 2 * dist + p.min_noise ** 2 * dt
        if p.imu:
            ya, yb = self._imu_yaw_at(t0), self._imu_yaw_at(t1)
            if ya is None or yb is None:
                return None
            d[2] = yb - ya
            var_yaw = p.imu_yaw_rate_noise ** 2 * dt + p.min_noise ** 2 * dt
        else:
            var_yaw = p.rotation_noise ** 2 * abs(float(d[2])) + p.yaw_drift ** 2 * dist + p.min_noise ** 2 * dt
        return d, np.diag([var_xy, var_xy, var_yaw])


class OdometryHistory6:
    """Recent 6-DOF odometry poses (``T_odom_base``, 4x4) by stamp, for the 6-DOF tracker
    (``filter/model: 6dof`` with ``motion.odometry``: a handheld rig's or a drone's visual-inertial
    odometry). :meth:`increment` interpolates the pose at both stamps (translation linearly,
    rotation by slerp, within a gap no longer than ``max_gap``) and returns base_link's
    displacement in its frame at the first stamp with a 6x6 covariance over (translation,
    rotation) in that frame, the same noise model as :class:`OdometryHistory` on every axis::

        var(t) = translation_noise^2 * |d_t| + min_noise^2 * dt
        var(r) = rotation_noise^2 * |d_angle| + yaw_drift^2 * |d_t| + min_noise^2 * dt

    Stamps must increase; an older one is refused (returns False)."""

    def __init__(self, params: MotionParams):
        self.params = params
        self._odom: Deque[Tuple[float, np.ndarray]] = deque()

    def reset(self) -> None:
        self._odom.clear()

    @property
    def latest_stamp(self) -> Optional[float]:
        return self._odom[-1][0] if self._odom else None

    def add_odometry(self, stamp: float, T_odom_base) -> bool:
        return _append(self._odom, float(stamp), np.array(T_odom_base, dtype=np.float64).reshape(4, 4),
                       self.params.history)

    def pose_at(self, t: float) -> Optional[np.ndarray]:
        """(4, 4) odometry pose at ``t``, interpolated; None outside the history or in a gap."""
        pair = _bracket(self._odom, t)
        if pair is None:
            return None
        (ta, A), (tb, B) = pair
        if t == ta or tb <= ta:
            return A.copy()
        if t == tb:
            return B.copy()
        if tb - ta > self.params.max_gap:
            return None
        f = (t - ta) / (tb - ta)
        D = geo.inverse(A) @ B
        out = np.eye(4)
        out[:3, :3] = A[:3, :3] @ geo.so3_exp(f * geo.rvec_from_rotation(D[:3, :3]).ravel())
        out[:3, 3] = (1.0 - f) * A[:3, 3] + f * B[:3, 3]
        return out

    def increment(self, t0: float, t1: float) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """``(D, cov)``: base_link's displacement (4x4) from ``t0`` to ``t1`` in its frame at ``t0``
        and its 6x6 covariance over (translation, rotation vector) in that frame; None when the
        history does not cover both stamps."""
        a, b = self.pose_at(t0), self.pose_at(t1)
        if a is None or b is None:
            return None
        D = geo.inverse(a) @ b
        p = self.params
        dist = float(np.linalg.norm(D[:3, 3]))
        angle = float(np.linalg.norm(geo.rvec_from_rotation(D[:3, :3])))
        dt = abs(float(t1) - float(t0))
        var_t = p.translation_noise ** 2 * dist + p.min_noise ** 2 * dt
        var_r = p.rotation_noise ** 2 * angle + p.yaw_drift ** 2 * dist + p.min_noise ** 2 * dt
        return D, np.diag([var_t] * 3 + [var_r] * 3)


__all__ = ["MotionParams", "OdometryHistory", "OdometryHistory6",
           "se2_compose", "se2_compose_jacobians", "propagate_se2", "se2_between", "se2_inverse",
           "constant_velocity_displacement", "displacement_to_transform", "body_covariance_to_perturbation",
           "body_factor_to_perturbation", "psd_factor", "odometry_in_base"]
