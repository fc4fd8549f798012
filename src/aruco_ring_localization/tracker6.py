"""A 6-DOF tracker for rigs that are not ground robots (``filter/model: 6dof``).

The paper's filter (:mod:`kalman`) tracks x, y and yaw of a robot on a flat floor. A handheld
rig, a drone or a camera head on an arm rolls and pitches as much as it yaws: its yaw alone is not
a state that evolves smoothly (a handheld rig pointing up has no meaningful yaw), and the
planar filter's output is then wrong by degrees. This tracker is the same idea on SE(3):

* **State**: the pose ``T_map_base`` (position ``p`` and rotation ``R``) and its velocity
  (linear ``v`` and angular ``w``, both in the map frame). The filter is an error-state Kalman
  filter: its 12-dim error ``(dp, dtheta, dv, dw)`` with ``R_true = exp(dtheta) R`` (a rotation
  vector in the map frame, the estimator's covariance convention) is estimated and folded back
  into the nominal state after every update.
* **Motion model**: constant velocity with white acceleration (spectral densities
  ``accel_noise``, ``angular_accel_noise``) and a velocity that relaxes towards rest with time
  constant ``velocity_time_constant`` (an Ornstein-Uhlenbeck velocity): a rig the filter has not
  seen for a while is extrapolated a little, not thrown along its last velocity::

      p <- p + v*tau*(1 - a),  R <- exp(w*tau*(1 - a)) R,  v <- a v,  w <- a w,  a = exp(-dt/tau)

* **Measurement**: the estimator's full pose with its 6x6 covariance (floored by
  ``min_measurement_std_pos`` / ``min_measurement_std_rot_deg``: it knows only the pixel noise).
* **Gate** (never a flipped estimate in): a measurement is compared with the prediction for its
  stamp; it enters only when its rotation differs by at most
  ``min(base_angle + 0.5*max_angular_acceleration*dt^2 + sigma_factor*sigma, max_angle)`` and
  its position by at most ``base_distance + 0.5*max_acceleration*dt^2 + sigma_factor*sigma``
  (``dt`` since the last accepted measurement, ``sigma`` of prediction + measurement). For a
  measurement from fewer than ``min_markers_uncapped`` markers (a single marker: the pose that
  flips, its mirrored IPPE solution passing the localizer's ambiguity test by noise) the rotation
  cap ``max_angle_deg`` holds whatever dt and the covariance: a flip turns the pose by more than
  that. A measurement from several markers has no such second solution; it is held to the motion
  bound alone, so a rig filmed at 2 Hz that turns 30 deg between frames is still followed.
  A measurement the localizer marks *ambiguous* never enters and never counts towards a recovery.
* **Recovery, no lock-out**: ``recovery_count`` consecutive rejected measurements that agree
  with each other (within ``recovery_distance`` / ``recovery_angle_deg`` plus the motion allowed
  in between) re-initialise the track.
* **Coasting, bounded**: between accepted measurements the output is the prediction, published
  only up to ``max_coast`` s after the last accepted one and only while ``sigma_factor`` times its
  position / rotation std stays below ``coast_max_distance`` / ``coast_max_angle_deg`` (the flip
  thresholds, 0.5 m and 10 deg), and never for a stamp where a measurement contradicted it
  (:meth:`Tracker6.publishable`): a rig turning while no camera gives a usable pose is
  extrapolated by degrees within half a second. Nothing is published instead. *Contradicted*: a
  measurement rejected as a jump (from several markers, or a single marker's pose the image
  resolved: a flip, or two mapped markers that disagree with each other -- on TagSLAM's test_9 two
  surveyed tags put the rig 0.9 m apart, and the prediction from the first was published while the
  second said otherwise), or an ambiguous one whose every pose lies outside the gate (whichever is
  true, the prediction is not).
* **Lost track**: after ``lost_after`` s without an accepted measurement the track is dropped
  (no output: nothing is extrapolated that far). A measurement from several markers starts it
  again; single-marker ones need ``init_count`` consecutive, mutually consistent ones (one lone
  single-marker pose after a gap could be a flip that no prediction can check).

Used by :class:`pipeline.LocalizationPipeline` when ``filter/model`` is ``6dof`` (``aruco_ring
localize --6dof``, the real-recordings benchmark for handheld rigs); robots keep the planar filter.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np

from . import geometry as geo
from .config import in_radians, param, require_positive
from .errors import ConfigError
from .gating import (ACCEPTED, INITIALIZED, REINITIALIZED, REJECTED_AMBIGUOUS, REJECTED_JUMP, GateDecision)

logger = logging.getLogger(__name__)

#: Waiting for ``init_count`` consistent measurements to (re)start a lost track.
PENDING = "pending"


@dataclass(frozen=True)
class Tracker6Params:
    """The 6-DOF tracker (``filter/model: 6dof``; the localizer's ``tracker6`` section)."""

    accel_noise: float = param(2.0, "spectral density of the white linear acceleration (constant-velocity "
                                    "model): larger follows a shaking rig faster, smaller smooths more",
                               unit="m^2/s^3")
    angular_accel_noise: float = param(2.0, "the same for the angular acceleration", unit="rad^2/s^3")
    velocity_time_constant: float = param(1.0, "the velocity relaxes towards rest with this time constant "
                                               "while nothing corrects it", unit="s")
    measurement_std_pos: float = param(0.02, "position measurement std when the estimator gives no covariance",
                                       unit="m")
    measurement_std_rot_deg: float = param(1.0, "rotation measurement std when the estimator gives none",
                                           unit="deg")
    min_measurement_std_pos: float = param(0.002, "floor added to the estimator's position covariance (map and "
                                                  "calibration errors)", unit="m")
    min_measurement_std_rot_deg: float = param(0.1, "the same for the rotation", unit="deg")
    initial_std_velocity: float = param(0.5, "initial std of the linear (m/s) and angular (rad/s) velocity")
    base_distance: float = param(0.15, "allowed position jump from the prediction at dt = 0", unit="m")
    base_angle_deg: float = param(5.0, "allowed rotation from the prediction at dt = 0", unit="deg")
    max_acceleration: float = param(5.0, "unknown linear acceleration allowed over dt (a hand moves faster "
                                         "than a robot)", unit="m/s^2")
    max_angular_acceleration: float = param(20.0, "unknown angular acceleration allowed over dt", unit="rad/s^2")
    sigma_factor: float = param(3.0, "both thresholds also grow by this many standard deviations of prediction "
                                     "+ measurement; 0 disables")
    max_angle_deg: float = param(8.0, "a single-marker measurement turned more than this from the prediction "
                                      "never enters (a flipped pose turns by more) unless the track's own rotation "
                                      "std times sigma_factor is larger (a long gap); only a recovery "
                                      "re-initialises", unit="deg")
    recovery_count: int = param(5, "this many consecutive rejected measurements that agree with each other "
                                   "re-initialise the track (never a lock-out)")
    recovery_distance: float = param(0.05, "how close consecutive rejected measurements must be (plus the "
                                           "motion allowed in between)", unit="m")
    recovery_angle_deg: float = param(3.0, "the same for their rotation", unit="deg")
    lost_after: float = param(1.0, "no accepted measurement for this long: the track is dropped (no output) and "
                                   "restarts from init_count consistent measurements", unit="s")
    init_count: int = param(2, "consecutive consistent, non-ambiguous single-marker measurements that start a "
                               "track (one from several markers starts it alone)")
    min_markers_uncapped: int = param(2, "a measurement from at least this many markers is held to the motion "
                                         "bound only, not to max_angle_deg (it has no mirrored solution)")
    max_coast: float = param(0.25, "the prediction is published at most this long after the last accepted "
                                   "measurement (coasting on a turning rig drifts by degrees within half a second); "
                                   "the track itself is kept until lost_after", unit="s")
    coast_max_distance: float = param(0.5, "and only while sigma_factor times its position std stays below this "
                                           "(the flip threshold: 0.5 m)", unit="m")
    coast_max_angle_deg: float = param(10.0, "the same for its rotation std (the flip threshold: 10 deg)",
                                       unit="deg")

    base_angle = in_radians("base_angle_deg")
    max_angle = in_radians("max_angle_deg")
    recovery_angle = in_radians("recovery_angle_deg")
    measurement_std_rot = in_radians("measurement_std_rot_deg")
    min_measurement_std_rot = in_radians("min_measurement_std_rot_deg")
    coast_max_angle = in_radians("coast_max_angle_deg")

    def __post_init__(self) -> None:
        require_positive(self, "accel_noise", "angular_accel_noise", "velocity_time_constant", "measurement_std_pos",
                         "measurement_std_rot_deg", "initial_std_velocity", "base_distance", "base_angle_deg",
                         "max_angle_deg", "recovery_distance", "recovery_angle_deg", "lost_after",
                         "coast_max_distance", "coast_max_angle_deg")
        for key in ("min_measurement_std_pos", "min_measurement_std_rot_deg", "max_acceleration",
                    "max_angular_acceleration", "sigma_factor", "max_coast"):
            if not getattr(self, key) >= 0:
                raise ConfigError(f"must be >= 0, got {getattr(self, key)!r}", key=key)
        for key in ("recovery_count", "init_count", "min_markers_uncapped"):
            if getattr(self, key) < 1:
                raise ConfigError(f"must be >= 1, got {getattr(self, key)!r}", key=key)


def _rot_diff(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Rotation vector ``d`` (map frame) with ``R_a = exp(d) R_b``."""
    return geo.rvec_from_rotation(R_a @ R_b.T).ravel()


def increment_jacobians(R: np.ndarray, D: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """``(F, G)``, both 6x6: how a pose's error ``(dp, dtheta)`` (map frame, ``R_true = exp(dtheta)
    R``) and an increment's error ``(n_t, n_r)`` (its own frame) reach the error of ``T · D``, for a
    pose of rotation ``R``: ``dp' = dp - [R t_D]x dtheta + R n_t``, ``dtheta' = dtheta + R n_r``."""
    F = np.eye(6)
    F[0:3, 3:6] = -geo.skew(R @ np.asarray(D, dtype=np.float64)[:3, 3])
    G = np.zeros((6, 6))
    G[0:3, 0:3] = R
    G[3:6, 3:6] = R
    return F, G


def move_pose(T: np.ndarray, covariance: Optional[np.ndarray], D: np.ndarray,
              cov_D: np.ndarray) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """A pose measurement ``T`` (4x4, with its 6x6 ``covariance`` over (x, y, z, map-frame rotation
    vector), or None) carried along an odometry increment ``D`` (4x4, in the pose's body frame, 6x6
    covariance ``cov_D`` over (translation, rotation vector) in that frame): ``T · D`` and its
    covariance (None stays None: the tracker's default measurement noise then applies)."""
    T = np.asarray(T, dtype=np.float64).reshape(4, 4)
    D = np.asarray(D, dtype=np.float64).reshape(4, 4)
    if covariance is None:
        return T @ D, None
    F, G = increment_jacobians(T[:3, :3], D)
    C = F @ np.asarray(covariance, dtype=np.float64).reshape(6, 6) @ F.T + G @ np.asarray(cov_D) @ G.T
    return T @ D, 0.5 * (C + C.T)


class Tracker6:
    """Error-state Kalman filter on SE(3) with its own gate (module docstring)."""

    def __init__(self, params: Optional[Tracker6Params] = None):
        self.params = params or Tracker6Params()
        self.reinitializations = 0
        self.rejected_total = 0
        self.withheld_total = 0
        self.reset()

    # --- state --------------------------------------------------------------------------------

    def reset(self, T_map_base: Optional[np.ndarray] = None, stamp: Optional[float] = None,
              covariance: Optional[np.ndarray] = None) -> None:
        """Forget the track, or start it at ``T_map_base`` (then ``stamp`` is required)."""
        self.p = np.zeros(3)
        self.R = np.eye(3)
        self.v = np.zeros(3)
        self.w = np.zeros(3)
        self.P = np.zeros((12, 12))
        self.stamp: Optional[float] = None
        self.last_accepted_stamp: Optional[float] = None
        self._rejected: List[Tuple[float, np.ndarray]] = []
        self._pending: List[Tuple[float, np.ndarray]] = []
        self._contradicted_at: Optional[float] = None
        if T_map_base is not None:
            self._start(np.asarray(T_map_base, dtype=np.float64), float(stamp), covariance)

    @property
    def initialized(self) -> bool:
        return self.stamp is not None

    @property
    def pose(self) -> np.ndarray:
        """(4, 4) filtered ``T_map_base``."""
        return geo.make_transform(self.R, self.p)

    @property
    def covariance(self) -> np.ndarray:
        """(6, 6) over (x, y, z, rx, ry, rz), rotation vector in the map frame."""
        return self.P[:6, :6].copy()

    @property
    def velocity(self) -> Tuple[np.ndarray, np.ndarray]:
        """(linear m/s, angular rad/s), map frame."""
        return self.v.copy(), self.w.copy()

    @property
    def velocity_covariance(self) -> np.ndarray:
        return self.P[6:, 6:].copy()

    def _start(self, T: np.ndarray, stamp: float, covariance: Optional[np.ndarray]) -> None:
        self.p = T[:3, 3].copy()
        self.R = T[:3, :3].copy()
        self.v = np.zeros(3)
        self.w = np.zeros(3)
        self.P = np.zeros((12, 12))
        self.P[:6, :6] = self._measurement_cov(covariance)
        self.P[6:, 6:] = np.eye(6) * self.params.initial_std_velocity ** 2
        self.stamp = float(stamp)
        self.last_accepted_stamp = float(stamp)
        self._rejected.clear()
        self._pending.clear()

    def _propagate(self, dt: float):
        """(p, R, v, w, F, Q) over ``dt`` from the current state, without changing it."""
        p = self.params
        tau = p.velocity_time_constant
        a = float(np.exp(-dt / tau))
        h = tau * (1.0 - a)                       # integral of a(t) over [0, dt]
        F = np.eye(12)
        F[0:3, 6:9] = np.eye(3) * h
        F[3:6, 9:12] = np.eye(3) * h
        F[6:, 6:] = np.eye(6) * a
        Q = np.zeros((12, 12))
        # White acceleration on each axis (filterpy's Q_continuous_white_noise, order 1).
        for q, (i, j) in ((p.accel_noise, (0, 6)), (p.angular_accel_noise, (3, 9))):
            I3 = np.eye(3)
            Q[i:i + 3, i:i + 3] = I3 * q * dt ** 3 / 3.0
            Q[i:i + 3, j:j + 3] = Q[j:j + 3, i:i + 3] = I3 * q * dt ** 2 / 2.0
            Q[j:j + 3, j:j + 3] = I3 * q * dt
        pn = self.p + self.v * h
        Rn = geo.so3_exp(self.w * h) @ self.R
        return pn, Rn, self.v * a, self.w * a, F, Q

    def predicted(self, stamp: float) -> Optional[np.ndarray]:
        """Predicted (4, 4) ``T_map_base`` at ``stamp`` (the state is not changed), or None."""
        if self.stamp is None:
            return None
        pn, Rn, _, _, _, _ = self._propagate(max(float(stamp) - self.stamp, 0.0))
        return geo.make_transform(Rn, pn)

    def predict(self, stamp: float) -> None:
        """Advance to ``stamp``; a stamp not after the filter's is ignored. A track without an
        accepted measurement for ``lost_after`` s is dropped."""
        if self.stamp is None:
            return
        stamp = float(stamp)
        if self.last_accepted_stamp is not None and stamp - self.last_accepted_stamp > self.params.lost_after:
            logger.info("6-DOF tracker: no accepted measurement for %.2f s: track dropped",
                        stamp - self.last_accepted_stamp)
            self.reset()
            return
        dt = stamp - self.stamp
        if dt <= 0.0:
            return
        self.p, self.R, self.v, self.w, F, Q = self._propagate(dt)
        self.P = F @ self.P @ F.T + Q
        self.P = 0.5 * (self.P + self.P.T)
        self.stamp = stamp

    def predict_increment(self, stamp: float, D: np.ndarray, cov: np.ndarray) -> None:
        """Advance to ``stamp`` along an odometry increment instead of the motion model:
        ``D`` (4x4) is the body's displacement since the filter's stamp in its frame there
        (``T(stamp) = T · D``), ``cov`` its 6x6 covariance over (translation, rotation vector) in
        that frame (:meth:`odometry.OdometryHistory6.increment`). With ``T_true = (p + dp,
        exp(dtheta) R)``: ``dp' = dp - [R t_D]x dtheta + R n_t``, ``dtheta' = dtheta + R n_r``; the
        velocity becomes the increment's mean velocity (map frame), its covariance relaxed and
        grown as in :meth:`predict`. A stamp not after the filter's is ignored; a track without
        an accepted measurement for ``lost_after`` s is dropped, as in :meth:`predict`."""
        if self.stamp is None:
            return
        stamp = float(stamp)
        if self.last_accepted_stamp is not None and stamp - self.last_accepted_stamp > self.params.lost_after:
            self.predict(stamp)   # drops the track, and says so
            return
        dt = stamp - self.stamp
        if dt <= 0.0:
            return
        D = np.asarray(D, dtype=np.float64).reshape(4, 4)
        Q6 = np.asarray(cov, dtype=np.float64).reshape(6, 6)
        _, _, _, _, F, Q = self._propagate(dt)
        F[0:6, 6:12] = 0.0                        # the pose follows the odometry, not the velocity
        F6, G6 = increment_jacobians(self.R, D)
        F[0:6, 0:6] = F6
        G = np.zeros((12, 6))
        G[0:6, :] = G6
        Q[0:6, :] = 0.0
        Q[:, 0:6] = 0.0
        self.P = F @ self.P @ F.T + Q + G @ Q6 @ G.T
        t_map = self.R @ D[:3, 3]
        self.P = 0.5 * (self.P + self.P.T)
        R_new = self.R @ D[:3, :3]
        self.w = geo.rvec_from_rotation(R_new @ self.R.T).ravel() / dt
        self.v = t_map / dt
        self.p = self.p + t_map
        self.R = R_new
        self.stamp = stamp

    def _measurement_cov(self, covariance: Optional[np.ndarray]) -> np.ndarray:
        p = self.params
        if covariance is None or not np.all(np.isfinite(covariance)):
            return np.diag([p.measurement_std_pos ** 2] * 3 + [p.measurement_std_rot ** 2] * 3)
        C = np.asarray(covariance, dtype=np.float64).reshape(6, 6)
        return 0.5 * (C + C.T) + np.diag([p.min_measurement_std_pos ** 2] * 3 + [p.min_measurement_std_rot ** 2] * 3)

    def _update(self, T: np.ndarray, Rm: np.ndarray) -> None:
        y = np.concatenate([T[:3, 3] - self.p, _rot_diff(T[:3, :3], self.R)])
        H = np.zeros((6, 12))
        H[:, :6] = np.eye(6)
        S = H @ self.P @ H.T + Rm
        K = np.linalg.solve(S, H @ self.P).T
        dx = K @ y
        IKH = np.eye(12) - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ Rm @ K.T      # Joseph form
        self.P = 0.5 * (self.P + self.P.T)
        self.p = self.p + dx[0:3]
        self.R = geo.so3_exp(dx[3:6]) @ self.R
        self.v = self.v + dx[6:9]
        self.w = self.w + dx[9:12]

    # --- gate + update ------------------------------------------------------------------------

    def thresholds(self, dt: float, covariance: Optional[np.ndarray] = None,
                   capped: bool = True) -> Tuple[float, float]:
        """(allowed distance m, allowed angle rad) ``dt`` s after the last accepted measurement;
        ``covariance``: 6x6 of (measurement - prediction); ``capped``: the angle at most ``max_angle``."""
        p = self.params
        dt = max(float(dt), 0.0)
        d = p.base_distance + 0.5 * p.max_acceleration * dt * dt
        a = p.base_angle + 0.5 * p.max_angular_acceleration * dt * dt
        if covariance is not None and p.sigma_factor > 0:
            C = np.asarray(covariance, dtype=np.float64)
            d += p.sigma_factor * float(np.sqrt(max(np.linalg.eigvalsh(C[:3, :3])[-1], 0.0)))
            a += p.sigma_factor * float(np.sqrt(max(np.linalg.eigvalsh(C[3:, 3:])[-1], 0.0)))
        return d, (min(a, p.max_angle) if capped else a)

    def _consistent(self, history: List[Tuple[float, np.ndarray]], stamp: float, T: np.ndarray,
                    capped: bool = True) -> bool:
        if not history:
            return True
        t_prev, T_prev = history[-1]
        d, a = self.thresholds(stamp - t_prev, capped=capped)
        p = self.params
        dist, ang = geo.pose_distance(T_prev, T)
        return dist <= p.recovery_distance + d - p.base_distance and ang <= p.recovery_angle + a - p.base_angle

    def _allowed(self, stamp: float, Rm: np.ndarray, capped: bool) -> Tuple[float, float]:
        """The gate's (distance m, angle rad) at ``stamp`` (the filter advanced there) for a
        measurement of covariance ``Rm`` (floored)."""
        p = self.params
        S = self.P[:6, :6] + Rm
        dt = stamp - (self.last_accepted_stamp if self.last_accepted_stamp is not None else stamp)
        allowed_d, allowed_a = self.thresholds(dt, S, capped)
        if capped and p.sigma_factor > 0:
            # The cap yields only to the track's own doubt: a prediction over a long gap (a rig
            # filmed at 2 Hz) is uncertain by more than max_angle, and a flip still has to land
            # within sigma_factor of its rotation std.
            sigma_pred = float(np.sqrt(max(np.linalg.eigvalsh(self.P[3:6, 3:6])[-1], 0.0)))
            allowed_a = max(allowed_a, min(p.sigma_factor * sigma_pred, self.thresholds(dt, S, False)[1]))
        return allowed_d, allowed_a

    def _jump(self, T: np.ndarray) -> Tuple[float, float]:
        """(m, rad) from the track's pose to ``T``."""
        return float(np.linalg.norm(T[:3, 3] - self.p)), float(np.linalg.norm(_rot_diff(T[:3, :3], self.R)))

    def _within_gate(self, T: np.ndarray, stamp: float, covariance: Optional[np.ndarray], capped: bool) -> bool:
        d, a = self._jump(T)
        allowed_d, allowed_a = self._allowed(stamp, self._measurement_cov(covariance), capped)
        return d <= allowed_d and a <= allowed_a

    def update(self, T_map_base: np.ndarray, stamp: float, covariance: Optional[np.ndarray] = None,
               ambiguous: bool = False, markers: int = 1,
               alternatives: Sequence[np.ndarray] = ()) -> GateDecision:
        """Gate and (if accepted) fuse the measurement ``T_map_base`` (4x4) at ``stamp`` (s) with its
        6x6 covariance over (x, y, z, rx, ry, rz), made from ``markers`` markers; the filter is
        advanced to ``stamp`` either way. ``alternatives``: the other poses the data admit as well
        (an ambiguous measurement's, 4x4 each): when neither it nor any of them is within the gate,
        the prediction is contradicted whichever is true, and it is not published at ``stamp``."""
        T = np.asarray(T_map_base, dtype=np.float64).reshape(4, 4)
        stamp = float(stamp)
        self.predict(stamp)
        p = self.params
        capped = markers < p.min_markers_uncapped
        if ambiguous:
            self.rejected_total += 1
            if self.stamp is not None and all(not self._within_gate(A, stamp, covariance, capped)
                                              for A in [T] + [np.asarray(a, dtype=np.float64) for a in alternatives]):
                self._contradicted_at = stamp
            return GateDecision(False, REJECTED_AMBIGUOUS)
        if self.stamp is None:
            # No track: one measurement from several markers starts it, single-marker ones need
            # init_count consecutive consistent ones.
            if not self._consistent(self._pending, stamp, T):
                self._pending.clear()
            self._pending.append((stamp, T))
            if capped and len(self._pending) < p.init_count:
                return GateDecision(False, PENDING)
            self._start(T, stamp, covariance)
            return GateDecision(True, INITIALIZED)
        Rm = self._measurement_cov(covariance)
        allowed_d, allowed_a = self._allowed(stamp, Rm, capped)
        dist, ang = self._jump(T)
        if dist <= allowed_d and ang <= allowed_a:
            self._update(T, Rm)
            self.last_accepted_stamp = stamp
            self._rejected.clear()
            return GateDecision(True, ACCEPTED, dist, ang, allowed_d, allowed_a)
        self.rejected_total += 1
        # The measurement disagrees with the prediction beyond the motion bound: one of the two is
        # wrong and nothing here says which (several markers have no mirrored solution; a single
        # marker the image resolved may still be a flip, or the map's markers disagree with each
        # other: a mis-surveyed tag puts the pose metres off, as in TagSLAM's test_9), so neither
        # is published at this stamp.
        self._contradicted_at = stamp
        if not self._consistent(self._rejected, stamp, T, capped):
            self._rejected.clear()
        self._rejected.append((stamp, T))
        if len(self._rejected) >= p.recovery_count:
            logger.warning("6-DOF tracker: %d consecutive consistent measurements disagree with the track by "
                           "%.2f m / %.1f deg: re-initialising", len(self._rejected), dist, np.degrees(ang))
            self.reinitializations += 1
            self._start(T, stamp, covariance)
            return GateDecision(True, REINITIALIZED, dist, ang, allowed_d, allowed_a)
        return GateDecision(False, REJECTED_JUMP, dist, ang, allowed_d, allowed_a)

    def publishable(self, stamp: float, count: bool = True) -> bool:
        """Whether the track's pose at ``stamp`` (the filter advanced there) may be published.

        Right after an accepted measurement, always. Otherwise it is a prediction (coasting): only
        up to ``max_coast`` s after the last accepted measurement, only while ``sigma_factor``
        (at least 1) times its position and rotation std stay below ``coast_max_distance`` and
        ``coast_max_angle_deg`` (a prediction that uncertain may be a flip's size off), and not
        when a measurement contradicted it at that stamp (rejected as a jump, or ambiguous with every
        pose it admits outside the gate: :meth:`update`). ``count``: a withheld pose counts in
        :attr:`withheld_total` (the odometry-rate outputs do not count)."""
        if self.stamp is None or self.last_accepted_stamp is None:
            return False
        stamp = float(stamp)
        if stamp <= self.last_accepted_stamp:
            return True
        p = self.params
        ok = stamp - self.last_accepted_stamp <= p.max_coast and self._contradicted_at != stamp
        if ok:
            k = max(p.sigma_factor, 1.0)
            s_pos = float(np.sqrt(max(np.linalg.eigvalsh(self.P[:3, :3])[-1], 0.0)))
            s_rot = float(np.sqrt(max(np.linalg.eigvalsh(self.P[3:6, 3:6])[-1], 0.0)))
            ok = k * s_pos <= p.coast_max_distance and k * s_rot <= p.coast_max_angle
        if not ok and count:
            self.withheld_total += 1
        return ok

    def body_twist(self) -> np.ndarray:
        """(v_forward, v_left, yaw rate) in the body frame (the planar filter's twist layout)."""
        vb = self.R.T @ self.v
        wb = self.R.T @ self.w
        return np.array([vb[0], vb[1], wb[2]])


__all__ = ["Tracker6", "Tracker6Params", "PENDING", "increment_jacobians", "move_pose"]
