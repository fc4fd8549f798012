"""The paper's linear Kalman filter on the robot's planar pose (paper §II-E-1), with filterpy.

State (9,), in the paper's order::

    s = (x, y, x', y', x'', y'', phi, phi', phi'')      m, m/s, m/s^2, rad, rad/s, rad/s^2

in the map frame (x', y' are world-frame velocities), a constant-acceleration model per axis.
Measurement (3,): ``z = (x, y, phi)`` from the localizer.

Cycle (filterpy.kalman.KalmanFilter):

* predict to the measurement's stamp, ``dt = stamp - last stamp`` (seconds, from the messages)::

      # x = F x              F: per axis [[1, dt, dt^2/2], [0, 1, dt], [0, 0, 1]]
      # P = F P F^T + Q      Q: white jerk, spectral density q per axis (filterpy's
      #                      Q_continuous_white_noise)

* update with ``z`` and its covariance ``R`` (3x3; the estimator's covariance when it has one,
  never below ``min_measurement_std``)::

      # y = z - H x          yaw component wrapped to (-pi, pi]: z's yaw is moved next to the
      #                      prediction first, so the innovation never jumps by 2 pi
      # S = H P H^T + R
      # K = P H^T S^-1
      # x = x + K y
      # P = (I - K H) P (I - K H)^T + K R K^T      (Joseph form: filterpy's update)

* no measurement: predict only (the covariance grows).
* a stamp earlier than the last one by more than ``time_jump_tolerance`` (a bag that loops,
  a clock reset) resets the filter; the next measurement re-initialises it.

The Mahalanobis distance ``y^T S^-1 y`` of a candidate measurement is available for gating.
"""
from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter
from scipy.linalg import block_diag

from . import geometry as geo
from .config import param, require_positive
from .errors import ConfigError
from .odometry import se2_compose, se2_compose_jacobians

logger = logging.getLogger(__name__)

# State indices (the paper's order).
IX, IY, IVX, IVY, IAX, IAY, IPHI, IW, IALPHA = range(9)
_AXES = ((IX, IVX, IAX), (IY, IVY, IAY), (IPHI, IW, IALPHA))
_POSE_ROWS = np.array([IX, IY, IPHI])
_POSE_BLOCK = np.ix_(_POSE_ROWS, _POSE_ROWS)
_VELOCITY_BLOCK = np.ix_(np.array([IVX, IVY, IW]), np.array([IVX, IVY, IW]))
#: ``filter/model``: the paper's planar filter, or the 6-DOF tracker (:mod:`tracker6`).
FILTER_MODELS = ("planar", "6dof")


@dataclass(frozen=True)
class FilterParams:
    """Noise parameters of :class:`PoseFilter` (the localizer's ``filter`` section, config/localization.yaml)."""

    model: str = param("planar", "planar: the paper's filter of a ground robot (x, y, yaw); 6dof: the 6-DOF tracker "
                                 "of a handheld or flying rig (tracker6 section, module tracker6)")
    jerk_noise_xy: float = param(0.1, "spectral density of the white jerk driving x and y (constant-acceleration "
                                      "model): larger follows faster, smaller smooths more", unit="m^2/s^5")
    jerk_noise_yaw: float = param(0.1, "the same for the yaw", unit="rad^2/s^5")
    measurement_std_xy: float = param(0.02, "position measurement std when the estimator gives no covariance",
                                      unit="m")
    measurement_std_yaw: float = param(0.01, "yaw measurement std when the estimator gives none", unit="rad")
    min_measurement_std_xy: float = param(0.003, "floor added to the estimator's position covariance (it only "
                                                 "knows the pixel noise, not map or calibration errors)", unit="m")
    min_measurement_std_yaw: float = param(0.002, "the same for the yaw", unit="rad")
    initial_std_velocity: float = param(0.5, "initial std of the velocities (m/s and rad/s)")
    initial_std_acceleration: float = param(1.0, "initial std of the accelerations (m/s^2 and rad/s^2)")
    time_jump_tolerance: float = param(0.5, "a stamp this much earlier than the last one (a bag loop, a clock "
                                            "reset) resets the filter", unit="s")
    max_dt: float = param(5.0, "predictions longer than this are clamped (a long gap; the covariance still grows)",
                          unit="s")

    def __post_init__(self) -> None:
        if self.model not in FILTER_MODELS:
            raise ConfigError(f"expected one of {FILTER_MODELS}, got {self.model!r}", key="model")
        require_positive(self, "jerk_noise_xy", "jerk_noise_yaw", "measurement_std_xy", "measurement_std_yaw",
                         "initial_std_velocity", "initial_std_acceleration", "max_dt")


def _diag3(a: float, b: float, c: float) -> np.ndarray:
    """``np.diag([a, b, c])`` (its set-up costs more than the matrix, twice per ring frame)."""
    return np.array([[a, 0.0, 0.0], [0.0, b, 0.0], [0.0, 0.0, c]])


def transition_matrix(dt: float) -> np.ndarray:
    """F (9, 9) of the constant-acceleration model over ``dt`` seconds."""
    F = _EYE9.copy()
    for p, v, a in _AXES:
        F[p, v] = dt
        F[p, a] = 0.5 * dt * dt
        F[v, a] = dt
    return F


_EYE9 = np.eye(9)
_EYE9.flags.writeable = False

#: Derivative order of each state (x, y, x', y', x'', y'', phi, phi', phi''): how its row of Q scales with dt.
_ORDER = np.array([0, 0, 1, 1, 2, 2, 0, 1, 2])


@functools.lru_cache(maxsize=16)
def _unit_process_noise(q_xy: float, q_yaw: float) -> np.ndarray:
    """:func:`process_noise` at dt = 1 s, from filterpy (read-only, cached per noise level)."""
    Q = block_diag(Q_continuous_white_noise(dim=3, dt=1.0, spectral_density=q_xy, block_size=2,
                                            order_by_dim=False),
                   Q_continuous_white_noise(dim=3, dt=1.0, spectral_density=q_yaw))
    Q.flags.writeable = False
    return Q


@functools.lru_cache(maxsize=8)
def _interval_model(dt: float, q_xy: float, q_yaw: float) -> Tuple[np.ndarray, np.ndarray]:
    """(:func:`transition_matrix`, :func:`process_noise`) over ``dt`` (read-only, cached: a ring
    frame predicts over the same dt up to three times: the pose prediction, the gate's covariance
    and the update)."""
    F, Q = transition_matrix(dt), process_noise(dt, q_xy, q_yaw)
    F.flags.writeable = False
    Q.flags.writeable = False
    return F, Q


@functools.lru_cache(maxsize=8)
def _measurement_floor(std_xy: float, std_yaw: float) -> np.ndarray:
    """The (3, 3) floor added to every measurement covariance (read-only, cached per params)."""
    floor = _diag3(std_xy ** 2, std_xy ** 2, std_yaw ** 2)
    floor.flags.writeable = False
    return floor


def process_noise(dt: float, q_xy: float, q_yaw: float) -> np.ndarray:
    """Q (9, 9): white jerk of spectral density ``q`` per axis (filterpy's
    ``Q_continuous_white_noise``), per axis ``q * [[dt^5/20, dt^4/8, dt^3/6],
    [dt^4/8, dt^3/3, dt^2/2], [dt^3/6, dt^2/2, dt]]``.

    x and y share one call with ``block_size=2, order_by_dim=False``, which lays the state out
    as (x, y, x', y', x'', y''): the paper's order, followed by the yaw block (phi, phi', phi'').

    Entry (i, j) of a block is ``dt^(5 - i - j)`` times its value at dt = 1, so Q is filterpy's Q at
    1 s (computed once per noise level) scaled by ``s s^T`` with ``s_k = dt^(2.5 - order_k)``: two
    numpy calls per prediction instead of filterpy's construction (about 100 us, twice per ring
    frame: the prediction and the gate's predicted covariance).
    """
    s = float(dt) ** (2.5 - _ORDER)
    return _unit_process_noise(float(q_xy), float(q_yaw)) * (s[:, None] * s[None, :])   # np.outer(s, s)


class PoseFilter:
    """The 9-state linear Kalman filter on (x, y, phi); see the module docstring."""

    def __init__(self, params: Optional[FilterParams] = None):
        self.params = params or FilterParams()
        self.kf = KalmanFilter(dim_x=9, dim_z=3)
        H = np.zeros((3, 9))
        H[0, IX] = H[1, IY] = H[2, IPHI] = 1.0
        self.kf.H = H
        self.stamp: Optional[float] = None
        self.resets = 0

    # --- state ------------------------------------------------------------------------------

    @property
    def initialized(self) -> bool:
        return self.stamp is not None

    @property
    def pose(self) -> np.ndarray:
        """(x, y, phi) of the current estimate."""
        x = self.kf.x[:, 0].tolist()   # scalars: a few array calls cost more than this arithmetic
        return np.array([x[IX], x[IY], geo.wrap_angle(x[IPHI])])

    @property
    def velocity(self) -> np.ndarray:
        """(x', y', phi') in the map frame."""
        x = self.kf.x[:, 0].tolist()
        return np.array([x[IVX], x[IVY], x[IW]])

    @property
    def body_twist(self) -> np.ndarray:
        """(v_forward, v_left, omega) in the robot frame (for nav_msgs/Odometry's twist)."""
        x = self.kf.x[:, 0].tolist()
        vx, vy, w = x[IVX], x[IVY], x[IW]
        yaw = geo.wrap_angle(x[IPHI])
        c, s = math.cos(yaw), math.sin(yaw)
        return np.array([c * vx + s * vy, -s * vx + c * vy, w])

    @property
    def covariance(self) -> np.ndarray:
        """3x3 covariance of (x, y, phi)."""
        return self.kf.P[_POSE_BLOCK]   # advanced indexing: a copy

    @property
    def velocity_covariance(self) -> np.ndarray:
        """3x3 covariance of (x', y', phi')."""
        return self.kf.P[_VELOCITY_BLOCK]

    # --- cycle ------------------------------------------------------------------------------

    def reset(self, pose=None, stamp: Optional[float] = None, covariance: Optional[np.ndarray] = None) -> None:
        """Forget everything; with ``pose`` (x, y, phi) start there at rest."""
        self.resets += 1
        if pose is None:
            self.stamp = None
            return
        p = self.params
        x = np.zeros((9, 1))
        x[IX, 0], x[IY, 0], x[IPHI, 0] = pose[0], pose[1], geo.wrap_angle(float(pose[2]))
        P = np.diag([0.0, 0.0, p.initial_std_velocity ** 2, p.initial_std_velocity ** 2,
                     p.initial_std_acceleration ** 2, p.initial_std_acceleration ** 2, 0.0,
                     p.initial_std_velocity ** 2, p.initial_std_acceleration ** 2])
        R = self._measurement_covariance(covariance)
        P[IX, IX], P[IY, IY], P[IPHI, IPHI] = R[0, 0], R[1, 1], R[2, 2]
        P[IX, IY] = P[IY, IX] = R[0, 1]
        self.kf.x = x
        self.kf.P = P
        self.stamp = float(stamp) if stamp is not None else 0.0

    def check_time(self, stamp: float) -> bool:
        """Reset (and return True) when ``stamp`` jumped back beyond the tolerance."""
        if self.stamp is not None and stamp < self.stamp - self.params.time_jump_tolerance:
            logger.warning("time jumped back from %.3f to %.3f s: resetting the pose filter", self.stamp, stamp)
            self.reset()
            return True
        return False

    def predict(self, stamp: float) -> None:
        """Advance the state to ``stamp`` (s). Stamps slightly in the past are ignored."""
        if self.stamp is None or self.check_time(stamp):
            return
        dt = float(stamp) - self.stamp
        if dt <= 0.0:
            return
        dt = min(dt, self.params.max_dt)
        # x = F x ; P = F P F^T + Q      (KalmanFilter.predict's equations and order, without its
        # copies of the prior: ~30 us of the ring frame's budget, issue 16)
        kf = self.kf
        F, Q = self._model(dt)
        kf.x = F @ kf.x
        kf.P = (F @ kf.P) @ F.T + Q
        kf.x[IPHI, 0] = geo.wrap_angle(float(kf.x[IPHI, 0]))
        self.stamp = float(stamp)

    def predicted(self, stamp: float) -> np.ndarray:
        """(x, y, phi) predicted at ``stamp`` without changing the filter."""
        if self.stamp is None:
            raise ValueError("the filter is not initialised")
        dt = min(max(float(stamp) - self.stamp, 0.0), self.params.max_dt)
        x = self._model(dt)[0] @ self.kf.x.ravel()
        return np.array([x[IX], x[IY], geo.wrap_angle(float(x[IPHI]))])

    def predicted_covariance(self, stamp: float) -> np.ndarray:
        """3x3 covariance of (x, y, phi) predicted at ``stamp`` without changing the filter."""
        if self.stamp is None:
            raise ValueError("the filter is not initialised")
        dt = min(max(float(stamp) - self.stamp, 0.0), self.params.max_dt)
        # P = F P F^T + Q, only its (x, y, phi) block: F's rows of x, y and phi, Q's block.
        F, Q = self._model(dt)
        Fp = F[_POSE_ROWS]
        return Fp @ self.kf.P @ Fp.T + Q[_POSE_BLOCK]

    def _model(self, dt: float) -> Tuple[np.ndarray, np.ndarray]:
        """(F, Q) over ``dt`` s with these params' jerk noises (:func:`_interval_model`)."""
        return _interval_model(dt, self.params.jerk_noise_xy, self.params.jerk_noise_yaw)

    def measurement_covariance(self, covariance: Optional[np.ndarray] = None) -> np.ndarray:
        """The R the filter uses for a measurement with estimator covariance ``covariance`` (3x3 or None)."""
        return self._measurement_covariance(covariance)

    def _measurement_covariance(self, covariance: Optional[np.ndarray]) -> np.ndarray:
        p = self.params
        if covariance is None:
            R = _diag3(p.measurement_std_xy ** 2, p.measurement_std_xy ** 2, p.measurement_std_yaw ** 2)
        else:
            R = 0.5 * (np.asarray(covariance, dtype=np.float64) + np.asarray(covariance, dtype=np.float64).T)
        # Floors: the estimator's covariance only knows the pixel noise.
        return R + _measurement_floor(p.min_measurement_std_xy, p.min_measurement_std_yaw)

    def _wrapped(self, z) -> np.ndarray:
        """z (3,) with its yaw moved to within pi of the predicted yaw (so y = z - Hx never jumps)."""
        z = np.asarray(z, dtype=np.float64).reshape(3).copy()
        phi = float(self.kf.x[IPHI, 0])
        z[2] = phi + geo.angle_diff(float(z[2]), phi)   # (Python floats: angle_diff's scalar path)
        return z

    def mahalanobis(self, z, covariance: Optional[np.ndarray] = None) -> float:
        """sqrt(y^T S^-1 y) of measurement ``z`` against the current (predicted) state."""
        R = self._measurement_covariance(covariance)
        H = self.kf.H
        # y = z - H x ; S = H P H^T + R
        y = self._wrapped(z) - (H @ self.kf.x).ravel()
        S = H @ self.kf.P @ H.T + R
        return float(np.sqrt(y @ np.linalg.solve(S, y)))

    def update(self, z, stamp: float, covariance: Optional[np.ndarray] = None) -> None:
        """Predict to ``stamp`` and correct with ``z = (x, y, phi)`` (covariance 3x3 or None).

        The first measurement (or the first after a reset) initialises the filter.
        """
        self.check_time(stamp)
        if self.stamp is None:
            self.reset(z, stamp, covariance)
            return
        self.predict(stamp)
        R = self._measurement_covariance(covariance)
        # KalmanFilter.update's equations in its order (H selects x, y, phi: its products with H
        # are these rows and columns, the same numbers), without its bookkeeping (copies of the
        # posterior, a deep copy of z): ~50 us a ring frame less (issue 16).
        kf = self.kf
        # y = z - Hx
        y = self._wrapped(z).reshape(3, 1) - kf.x[_POSE_ROWS]
        # PH' ; S = HPH' + R ; K = PH'S^-1
        PHT = kf.P[:, _POSE_ROWS]
        S = PHT[_POSE_ROWS] + R
        K = PHT @ np.linalg.inv(S)
        # x = x + Ky
        kf.x = kf.x + K @ y
        # P = (I-KH)P(I-KH)' + KRK'      (Joseph form)
        I_KH = _EYE9.copy()
        I_KH[:, _POSE_ROWS] -= K
        kf.P = (I_KH @ kf.P) @ I_KH.T + (K @ R) @ K.T
        kf.x[IPHI, 0] = geo.wrap_angle(float(kf.x[IPHI, 0]))

    def predict_increment(self, stamp: float, d, cov_d) -> None:
        """Advance the pose to ``stamp`` by a measured body-frame displacement ``d = (dx, dy, dyaw)``
        (wheel odometry, :mod:`odometry`) with its 3x3 covariance ``cov_d``, instead of the
        constant-acceleration model::

            # (x, y, phi) <- (x, y, phi) ⊕ d
            # P_pose <- J_p P_pose J_p^T + J_d cov_d J_d^T     (J: the composition's Jacobians)

        The velocities become odometry's (``d / dt`` turned into the map frame; accelerations 0):
        they are what the output twist and the constant-acceleration model use when odometry stops.
        Their covariance follows the constant-acceleration model over ``dt``, uncorrelated with the
        pose (the pose no longer integrates them). A stamp not after the filter's is ignored.
        """
        if self.stamp is None or self.check_time(stamp):
            return
        dt = float(stamp) - self.stamp
        if dt <= 0.0:
            return
        x = self.kf.x.ravel().copy()
        pose = np.array([x[IX], x[IY], x[IPHI]])
        d = np.asarray(d, dtype=np.float64).reshape(3)
        Jp, Jd = se2_compose_jacobians(pose, d)
        new = se2_compose(pose, d)
        idx = np.array([IX, IY, IPHI])
        rest = np.array([IVX, IVY, IAX, IAY, IW, IALPHA])
        P = self.kf.P
        F = transition_matrix(min(dt, self.params.max_dt))
        Q = process_noise(min(dt, self.params.max_dt), self.params.jerk_noise_xy, self.params.jerk_noise_yaw)
        Pn = np.zeros((9, 9))
        Pn[np.ix_(idx, idx)] = Jp @ P[np.ix_(idx, idx)] @ Jp.T + Jd @ np.asarray(cov_d, dtype=np.float64) @ Jd.T
        Fr = F[np.ix_(rest, rest)]
        Pn[np.ix_(rest, rest)] = Fr @ P[np.ix_(rest, rest)] @ Fr.T + Q[np.ix_(rest, rest)]
        Pn = 0.5 * (Pn + Pn.T)
        c, s = np.cos(new[2]), np.sin(new[2])
        x[IX], x[IY], x[IPHI] = new
        x[IVX] = (c * d[0] - s * d[1]) / dt
        x[IVY] = (s * d[0] + c * d[1]) / dt
        x[IW] = d[2] / dt
        x[IAX] = x[IAY] = x[IALPHA] = 0.0
        self.kf.x = x.reshape(9, 1)
        self.kf.P = Pn
        self.stamp = float(stamp)
