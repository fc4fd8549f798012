"""Outlier gate on fused pose measurements (paper Algorithm 1, step 4).

A measurement (x, y, yaw) is compared with the pose predicted for its stamp (the filter's
prediction, which carries the previous poses, or the last accepted pose moved by the motion
command). It is rejected when it lies farther than what the robot could have moved:

    allowed_distance = base_distance + speed_margin * |v| * dt + 0.5 * max_acceleration * dt^2
    allowed_angle    = base_angle + speed_margin * |w| * dt + 0.5 * max_angular_acceleration * dt^2

with ``v`` and ``w`` the commanded (``cmd_vel``) or measured (odometry twist) speeds, whichever is
larger, and ``dt`` the time since the last accepted measurement: the thresholds grow with the
elapsed time and the speed. When the covariances of the prediction (the filter's) and of the
measurement (the estimator's) are given, both thresholds also grow by ``sigma_factor`` standard
deviations of their sum (largest eigenvalue for the position): an uncertain track, e.g. after a
stretch with one camera, does not reject good measurements.

No lock-out: after ``recovery_count`` consecutive rejected measurements that agree with each other
(each within ``recovery_distance`` / ``recovery_angle`` of the previous one, plus the motion
allowed in between), the gate accepts the last one as a re-initialisation (a kidnapped robot, a bad
initial pose, a long outage) and logs it.

Flips (a single marker's two IPPE poses, or two minima of the joint problem): the gate also
checks the measurement's full rotation when it is given -- its up axis (roll and pitch) may differ
from the track's, the last accepted measurement's, by at most ``max_tilt_change_deg`` (a ground robot
does not tilt by degrees between two frames, a flipped pose usually does) -- and it treats a
measurement the localizer marks *ambiguous* (the data admit another, distinct pose about as well)
as no measurement: it never enters the filter (the localizer chose it by the prediction, so it
cannot confirm the track; after a kidnap the prediction is wrong and would pick the flip every
frame) and never counts towards a recovery (``ambiguous``).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np

from . import geometry as geo
from .config import in_radians, param, require_positive
from .errors import ConfigError

logger = logging.getLogger(__name__)

ACCEPTED = "accepted"
INITIALIZED = "initialized"
REJECTED_JUMP = "jump"
REJECTED_TILT = "tilt"
REJECTED_AMBIGUOUS = "ambiguous"
REINITIALIZED = "reinitialized"


@dataclass(frozen=True)
class GateParams:
    """Thresholds of :class:`MotionGate` (the localizer's ``gate`` section, config/localization.yaml).

    A measurement farther from the prediction than
    ``base_distance + speed_margin*|v|*dt + 0.5*max_acceleration*dt^2`` (m), or turned more than
    ``base_angle_deg + speed_margin*|w|*dt + 0.5*max_angular_acceleration*dt^2`` (deg), with
    ``v, w`` from cmd_vel/odom and ``dt`` since the last accepted one, is rejected.
    """

    enabled: bool = param(True, "false accepts every measurement")
    base_distance: float = param(0.15, "allowed position jump at dt = 0 and rest (measurement noise, latency)",
                                 unit="m")
    base_angle_deg: float = param(10.0, "allowed yaw jump at dt = 0 and rest", unit="deg")
    speed_margin: float = param(1.5, "factor on the speed x dt term (commands are not followed exactly)")
    max_acceleration: float = param(1.0, "unknown linear acceleration allowed over dt", unit="m/s^2")
    max_angular_acceleration: float = param(2.0, "unknown angular acceleration allowed over dt", unit="rad/s^2")
    recovery_count: int = param(5, "this many consecutive rejected measurements that agree with each other "
                                   "re-initialise the track (kidnapped robot, wrong initial pose): never a lock-out")
    recovery_distance: float = param(0.10, "how close consecutive rejected measurements must be (plus the motion "
                                           "allowed in between) to count as agreeing", unit="m")
    recovery_angle_deg: float = param(5.0, "the same for their yaw", unit="deg")
    sigma_factor: float = param(3.0, "both thresholds also grow by this many standard deviations of the prediction "
                                     "and the measurement (filter + estimator covariance): after a stretch of poor "
                                     "measurements (one camera left) good ones are not rejected; 0 disables")
    max_tilt_change_deg: float = param(5.0, "a measurement whose up axis (roll, pitch) differs from the last accepted "
                                            "one's by more is rejected: a flipped pose tilts, a ground robot does "
                                            "not; no covariance widens it; 0 disables", unit="deg")

    base_angle = in_radians("base_angle_deg")
    recovery_angle = in_radians("recovery_angle_deg")
    max_tilt_change = in_radians("max_tilt_change_deg")

    def __post_init__(self) -> None:
        require_positive(self, "base_distance", "base_angle_deg", "recovery_distance", "recovery_angle_deg")
        if self.recovery_count < 1:
            raise ConfigError(f"must be >= 1, got {self.recovery_count!r}", key="recovery_count")
        if not self.max_tilt_change_deg >= 0:
            raise ConfigError(f"must be >= 0, got {self.max_tilt_change_deg!r}", key="max_tilt_change_deg")


@dataclass
class GateDecision:
    """Outcome of :meth:`MotionGate.check`.

    Attributes:
        accepted: use the measurement (True also for INITIALIZED and REINITIALIZED).
        reason: ACCEPTED, INITIALIZED, REJECTED_JUMP, REJECTED_TILT, REJECTED_AMBIGUOUS or
            REINITIALIZED.
        distance, angle: the jump from the prediction, m and rad.
        allowed_distance, allowed_angle: the thresholds in force.
        tilt: change of the up axis against the track's, rad (0 when not checked).
    """

    accepted: bool
    reason: str
    distance: float = 0.0
    angle: float = 0.0
    allowed_distance: float = float("inf")
    allowed_angle: float = float("inf")
    tilt: float = 0.0

    @property
    def reinitialize(self) -> bool:
        return self.reason in (INITIALIZED, REINITIALIZED)


class MotionGate:
    """Reject pose measurements inconsistent with the previous poses and the motion command."""

    def __init__(self, params: Optional[GateParams] = None):
        self.params = params or GateParams()
        self.last_accepted_stamp: Optional[float] = None
        self._rejected: List[Tuple[float, np.ndarray, Optional[np.ndarray]]] = []
        self._up: Optional[np.ndarray] = None  # up axis (map frame) of the last accepted measurement
        self.rejected_total = 0
        self.reinitializations = 0

    def reset(self) -> None:
        """Forget the history: the next measurement is accepted as an initialisation."""
        self.last_accepted_stamp = None
        self._rejected.clear()
        self._up = None

    def thresholds(self, dt: float, speed: float = 0.0, yaw_rate: float = 0.0) -> Tuple[float, float]:
        """(allowed distance m, allowed angle rad) after ``dt`` s at the given speeds."""
        p = self.params
        dt = max(float(dt), 0.0)
        d = p.base_distance + p.speed_margin * abs(speed) * dt + 0.5 * p.max_acceleration * dt * dt
        a = p.base_angle + p.speed_margin * abs(yaw_rate) * dt + 0.5 * p.max_angular_acceleration * dt * dt
        return d, a

    def check(self, z, stamp: float, predicted=None, speed: float = 0.0, yaw_rate: float = 0.0,
              covariance: Optional[np.ndarray] = None, rotation: Optional[np.ndarray] = None,
              ambiguous: bool = False) -> GateDecision:
        """Decide on measurement ``z = (x, y, yaw)`` at ``stamp`` (s).

        Args:
            predicted: (x, y, yaw) expected at ``stamp``, or None when there is no track yet.
            speed: |linear speed| from cmd_vel or odometry, m/s; yaw_rate: rad/s.
            covariance: optional 3x3 covariance of (z - predicted) over (x, y, yaw): the
                prediction's plus the measurement's.
            rotation: optional (3, 3) full rotation of the measurement (``R_map_base``): its tilt
                against the track's is checked (``max_tilt_change``).
            ambiguous: the localizer found another pose that fits the data about as well: the
                measurement is rejected (``REJECTED_AMBIGUOUS``) and does not count towards a
                recovery; it does not interrupt one either.
        """
        z = np.asarray(z, dtype=np.float64).reshape(3)
        up = None if rotation is None else np.asarray(rotation, dtype=np.float64).reshape(3, 3)[:, 2].copy()
        if predicted is None or self.last_accepted_stamp is None:
            if ambiguous:
                self.rejected_total += 1
                return GateDecision(False, REJECTED_AMBIGUOUS)
            self._accept(stamp, up)
            return GateDecision(True, INITIALIZED)
        if not self.params.enabled:
            self._accept(stamp, up)
            return GateDecision(True, ACCEPTED)
        pred = np.asarray(predicted, dtype=np.float64).reshape(3)
        dt = stamp - self.last_accepted_stamp
        allowed_d, allowed_a = self.thresholds(dt, speed, yaw_rate)
        if covariance is not None and self.params.sigma_factor > 0:
            C = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
            allowed_d += self.params.sigma_factor * math.sqrt(max(_largest_eigenvalue_2x2(C), 0.0))
            allowed_a += self.params.sigma_factor * math.sqrt(max(C[2, 2], 0.0))
        dist, ang, tilt, ok = self._fits(z, up, pred, allowed_d, allowed_a)
        if ambiguous:
            # Never into the filter: the localizer chose it by the prediction, so it cannot confirm
            # the track (a wrong prediction, e.g. after a kidnap, would pick and keep the flip),
            # and a far face-on marker's two poses are both decimetres off, biased the same way.
            # Nor evidence for a new truth: an ambiguous pose may be a flip, chosen consistently.
            self.rejected_total += 1
            return GateDecision(False, REJECTED_AMBIGUOUS, dist, ang, allowed_d, allowed_a, tilt)
        if ok:
            self._accept(stamp, up)
            return GateDecision(True, ACCEPTED, dist, ang, allowed_d, allowed_a, tilt)
        self.rejected_total += 1
        reason = REJECTED_TILT if dist <= allowed_d and ang <= allowed_a else REJECTED_JUMP
        # Rejected: does it agree with the previous rejected ones (a consistent new truth)?
        if self._rejected:
            t_prev, z_prev, up_prev = self._rejected[-1]
            step_d, step_a = self.thresholds(stamp - t_prev, speed, yaw_rate)
            consistent = (np.hypot(*(z[:2] - z_prev[:2])) <= self.params.recovery_distance + step_d - self.params.base_distance
                          and abs(geo.angle_diff(z[2], z_prev[2])) <= self.params.recovery_angle + step_a - self.params.base_angle
                          and (up is None or up_prev is None or _angle_between(up, up_prev) <= self.params.recovery_angle))
            if not consistent:
                self._rejected.clear()
        self._rejected.append((float(stamp), z, up))
        if len(self._rejected) >= self.params.recovery_count:
            logger.warning("%d consecutive consistent measurements disagree with the track by %.2f m / %.1f deg: "
                           "re-initialising at (%.2f, %.2f, %.1f deg)", len(self._rejected), dist, np.degrees(ang),
                           z[0], z[1], np.degrees(z[2]))
            self.reinitializations += 1
            self._accept(stamp, up)
            return GateDecision(True, REINITIALIZED, dist, ang, allowed_d, allowed_a, tilt)
        return GateDecision(False, reason, dist, ang, allowed_d, allowed_a, tilt)

    def _fits(self, z: np.ndarray, up: Optional[np.ndarray], pred: np.ndarray, allowed_d: float,
              allowed_a: float) -> Tuple[float, float, float, bool]:
        """(distance, yaw jump, tilt change, within all thresholds) of a candidate pose."""
        dist = float(np.hypot(z[0] - pred[0], z[1] - pred[1]))
        ang = abs(float(geo.angle_diff(z[2], pred[2])))
        tilt = 0.0 if up is None or self._up is None else _angle_between(up, self._up)
        tilt_ok = self.params.max_tilt_change <= 0 or tilt <= self.params.max_tilt_change
        return dist, ang, tilt, dist <= allowed_d and ang <= allowed_a and tilt_ok

    def _accept(self, stamp: float, up: Optional[np.ndarray] = None) -> None:
        self.last_accepted_stamp = float(stamp)
        self._rejected.clear()
        if up is not None:
            self._up = up


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two unit vectors, rad (on Python floats: np.cross costs ~15 us a call)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    return math.atan2(math.sqrt(c0 * c0 + c1 * c1 + c2 * c2), a0 * b0 + a1 * b1 + a2 * b2)


def _largest_eigenvalue_2x2(C: np.ndarray) -> float:
    """The larger eigenvalue of the symmetric 2x2 block ``C[:2, :2]`` (its lower triangle, as
    ``eigvalsh`` reads it), in closed form."""
    a, b, d = float(C[0, 0]), float(C[1, 0]), float(C[1, 1])
    h = 0.5 * (a - d)
    return 0.5 * (a + d) + math.hypot(h, b)
