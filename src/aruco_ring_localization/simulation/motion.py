"""Robot motion for the simulator: a holonomic base, drifting wheel odometry, a waypoint driver.

* :class:`MotionLimits` (in :mod:`.params`) — velocity and acceleration limits of the base.
* :class:`HolonomicBase` — the true SE(2) pose of base_link in the world; follows a velocity
  command (vx, vy in the base frame, m/s; wz, rad/s) within velocity and acceleration limits.
* :class:`WheelOdometry` — integrates the true body motion with seeded errors: a per-run scale
  error per axis (wheel radius, ~1 %), a yaw-rate scale error and Gaussian noise per step, so the
  odometry drifts like a real omnidirectional base (``odom -> base_link``, REP-105).
* :class:`WaypointDriver` — visits a list of poses (the paper's test positions/orientations),
  holds each for ``hold_time`` seconds, and reports the index being held (-1 while moving).

All poses are (x, y, yaw rad); all times in seconds.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np

from .. import geometry as geo
from .params import MotionLimits, RobotParams

__all__ = ["MotionLimits", "HolonomicBase", "WheelOdometry", "WaypointDriver", "RobotState", "SimRobot"]

logger = logging.getLogger(__name__)


class HolonomicBase:
    """True pose of an omnidirectional base following velocity commands."""

    def __init__(self, pose: Sequence[float], limits: MotionLimits = MotionLimits()):
        self.pose = np.array(pose, dtype=float).reshape(3)
        self.velocity = np.zeros(3)   # vx, vy (base frame), wz
        self.limits = limits

    def limited(self, cmd: Sequence[float]) -> np.ndarray:
        """The command (vx, vy, wz) the base follows: ``cmd`` within the speed limits (zero if not finite)."""
        lim = self.limits
        target = np.array(cmd, dtype=float).reshape(3)
        if not np.all(np.isfinite(target)):
            return np.zeros(3)
        speed = float(np.hypot(target[0], target[1]))
        if speed > lim.max_speed:
            target[:2] *= lim.max_speed / speed
        target[2] = float(np.clip(target[2], -lim.max_yaw_rate, lim.max_yaw_rate))
        return target

    def step(self, cmd: Sequence[float], dt: float) -> np.ndarray:
        """Advance by ``dt`` toward the commanded (vx, vy, wz); returns the body motion (dx, dy, dyaw)
        in the base frame at the start of the step."""
        if dt <= 0:
            return np.zeros(3)
        lim = self.limits
        target = self.limited(cmd)
        dv = target - self.velocity
        dlin = float(np.hypot(dv[0], dv[1]))
        if dlin > lim.max_accel * dt:
            dv[:2] *= lim.max_accel * dt / dlin
        dv[2] = float(np.clip(dv[2], -lim.max_yaw_accel * dt, lim.max_yaw_accel * dt))
        v_mid = self.velocity + 0.5 * dv
        self.velocity = self.velocity + dv
        body = v_mid * dt
        self.pose = compose_se2(self.pose, body)
        return body

    def teleport(self, pose: Sequence[float]) -> None:
        self.pose = np.array(pose, dtype=float).reshape(3)
        self.velocity = np.zeros(3)


def compose_se2(pose: Sequence[float], body: Sequence[float]) -> np.ndarray:
    """Apply a body-frame motion (dx, dy, dyaw) to an SE(2) pose (midpoint heading for the translation)."""
    x, y, th = pose
    dx, dy, dth = body
    mid = th + 0.5 * dth
    c, s = np.cos(mid), np.sin(mid)
    return np.array([x + c * dx - s * dy, y + s * dx + c * dy, geo.wrap_angle(th + dth)])


class WheelOdometry:
    """Drifting odometry: ``pose`` is base_link in the odom frame (starts at the origin).

    Args:
        seed: seed of the scale errors and the per-step noise.
        scale_std: 1-sigma scale error of x, y translation (fraction).
        yaw_scale_std: 1-sigma scale error of the yaw rate (fraction).
        noise_std: per-metre translation noise (m per sqrt(m)) and per-radian yaw noise.
    """

    def __init__(self, seed: int = 0, scale_std: float = 0.01, yaw_scale_std: float = 0.01,
                 noise_std: float = 0.005):
        self.rng = np.random.default_rng([int(seed), 0x0d0])
        self.scale = 1.0 + self.rng.normal(0.0, scale_std, 2)
        self.yaw_scale = 1.0 + float(self.rng.normal(0.0, yaw_scale_std))
        self.noise_std = float(noise_std)
        self.pose = np.zeros(3)
        self.velocity = np.zeros(3)

    def update(self, body: Sequence[float], dt: float) -> np.ndarray:
        """Integrate one true body motion; returns the odometry pose (x, y, yaw) in odom."""
        b = np.array(body, dtype=float).reshape(3)
        meas = np.array([b[0] * self.scale[0], b[1] * self.scale[1], b[2] * self.yaw_scale])
        mag = np.array([abs(b[0]), abs(b[1]), abs(b[2])])
        meas += self.rng.normal(0.0, 1.0, 3) * self.noise_std * np.sqrt(mag)
        self.pose = compose_se2(self.pose, meas)
        self.velocity = meas / dt if dt > 0 else np.zeros(3)
        return self.pose.copy()


class WaypointDriver:
    """Drive to each pose in turn and hold it.

    Args:
        waypoints: poses (x, y, yaw) in the world.
        hold_time: seconds to stay at each pose once reached.
        gain: proportional gain (1/s) of the position and heading controller.
        tolerance: (m, rad) within which a pose counts as reached.
        loop: start again after the last pose.
    """

    def __init__(self, waypoints: Sequence[Sequence[float]], hold_time: float = RobotParams.hold_time,
                 gain: float = 1.5,
                 tolerance: Tuple[float, float] = (0.005, np.radians(0.5)), loop: bool = False):
        self.waypoints: List[np.ndarray] = [np.array(w, dtype=float).reshape(3) for w in waypoints]
        self.hold_time = float(hold_time)
        self.gain = float(gain)
        self.tolerance = tolerance
        self.loop = loop
        self.index = 0
        self._held_since: Optional[float] = None
        self.finished = not self.waypoints

    @property
    def holding(self) -> int:
        """Index of the waypoint being held, or -1 while moving (or finished)."""
        return self.index if self._held_since is not None and not self.finished else -1

    def command(self, pose: Sequence[float], t: float, velocity: Optional[Sequence[float]] = None) -> np.ndarray:
        """Velocity command (vx, vy, wz) in the base frame for the robot at ``pose`` at time ``t``.

        ``velocity`` (vx, vy, wz), when given, must also be small (< 1 cm/s, < 0.6 deg/s) for a
        waypoint to count as reached, so the robot is at rest while it holds the pose."""
        if self.finished:
            return np.zeros(3)
        goal = self.waypoints[self.index]
        p = np.asarray(pose, dtype=float)
        d_world = goal[:2] - p[:2]
        dyaw = float(geo.angle_diff(goal[2], p[2]))
        reached = np.hypot(*d_world) < self.tolerance[0] and abs(dyaw) < self.tolerance[1]
        if velocity is not None:
            v = np.asarray(velocity, dtype=float)
            reached = reached and np.hypot(v[0], v[1]) < 0.01 and abs(v[2]) < 0.01
        if self._held_since is not None:
            if t - self._held_since >= self.hold_time:
                self._held_since = None
                self.index += 1
                if self.index >= len(self.waypoints):
                    if self.loop:
                        self.index = 0
                    else:
                        self.finished = True
                        return np.zeros(3)
                return self.command(pose, t, velocity)
            return np.zeros(3)
        if reached:
            self._held_since = t
            return np.zeros(3)
        c, s = np.cos(p[2]), np.sin(p[2])
        v_body = self.gain * np.array([c * d_world[0] + s * d_world[1], -s * d_world[0] + c * d_world[1]])
        return np.array([v_body[0], v_body[1], self.gain * dyaw])


@dataclass
class RobotState:
    """What the simulator publishes after one step.

    Attributes:
        pose: true (x, y, yaw) of base_link in the world.
        odom_pose: (x, y, yaw) of base_link in the odom frame (drifting).
        odom_velocity: measured body velocity (vx, vy, wz).
        cmd: the velocity command that was followed (vx, vy, wz).
        holding: index of the waypoint being held, -1 while moving (or without waypoints).
    """

    pose: np.ndarray
    odom_pose: np.ndarray
    odom_velocity: np.ndarray
    cmd: np.ndarray
    holding: int


class SimRobot:
    """The simulated robot: true base, odometry and (optionally) the waypoint driver.

    Args:
        start: initial true pose (x, y, yaw) in the world.
        waypoints: poses to visit (empty: follow external commands only).
        hold_time: seconds at each waypoint.
        direct: jump to each waypoint instead of driving there (no motion blur of the schedule).
        limits: base limits.
        seed: odometry seed.
        loop: revisit the waypoints forever.
    """

    def __init__(self, start: Sequence[float], waypoints: Sequence[Sequence[float]] = (),
                 hold_time: float = RobotParams.hold_time, direct: bool = False,
                 limits: MotionLimits = MotionLimits(), seed: int = 0, loop: bool = False):
        self.base = HolonomicBase(start, limits)
        self.odometry = WheelOdometry(seed=seed)
        self.driver = WaypointDriver(waypoints, hold_time=hold_time, loop=loop) if len(waypoints) else None
        self.direct = direct
        self._cmd_ext = np.zeros(3)
        self._cmd_time = -np.inf

    def set_command(self, cmd: Sequence[float], t: float) -> None:
        """An external velocity command (cmd_vel), used when no waypoint driver is active."""
        c = np.array(cmd, dtype=float).reshape(3)
        self._cmd_ext = c if np.all(np.isfinite(c)) else np.zeros(3)
        self._cmd_time = t

    @property
    def driving(self) -> bool:
        return self.driver is not None and not self.driver.finished

    def step(self, t: float, dt: float, cmd_timeout: float = 0.5) -> RobotState:
        """Advance the robot to time ``t`` (s) by ``dt`` (s)."""
        if self.driving:
            if self.direct and self.driver.holding < 0:
                # Jump onto the current goal; the driver then holds it.
                self.base.teleport(self.driver.waypoints[self.driver.index])
            cmd = self.driver.command(self.base.pose, t, None if self.direct else self.base.velocity)
        else:
            cmd = self._cmd_ext if t - self._cmd_time <= cmd_timeout else np.zeros(3)
        before = self.base.pose.copy()
        body = self.base.step(cmd, dt)
        if self.direct and self.driving:
            body = _body_motion(before, self.base.pose)
        self.odometry.update(body, dt)
        holding = self.driver.holding if self.driver is not None else -1
        # The command as followed (within the limits): what the simulator publishes on cmd_vel, as a
        # real driver does (the waypoint driver's proportional command is far above them when the
        # goal is far, and the localizer drops a cmd_vel beyond its limits/max_speed).
        return RobotState(self.base.pose.copy(), self.odometry.pose.copy(), self.odometry.velocity.copy(),
                          self.base.limited(cmd), holding)


def _body_motion(a: Sequence[float], b: Sequence[float]) -> np.ndarray:
    """Body-frame motion (dx, dy, dyaw) from pose a to pose b (approximate inverse of compose_se2)."""
    dth = float(geo.angle_diff(b[2], a[2]))
    mid = a[2] + 0.5 * dth
    c, s = np.cos(mid), np.sin(mid)
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, dth])
