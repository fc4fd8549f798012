"""Simulator motion, odometry, waypoint driver and laser scan."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.simulation.laser import LaserScanner
from aruco_ring_localization.simulation.motion import (HolonomicBase, MotionLimits, WaypointDriver,
                                                       WheelOdometry)
from aruco_ring_localization.simulation.scene import Scene


def test_base_respects_velocity_and_acceleration_limits():
    base = HolonomicBase((0, 0, 0), MotionLimits(max_speed=0.5, max_accel=0.5, max_yaw_rate=1.0))
    base.step((2.0, 0.0, 0.0), 0.1)
    assert np.isclose(base.velocity[0], 0.05), base.velocity       # accel limit: 0.5 m/s^2 * 0.1 s
    for _ in range(100):
        base.step((2.0, 0.0, 5.0), 0.1)
    assert np.isclose(np.hypot(*base.velocity[:2]), 0.5) and np.isclose(base.velocity[2], 1.0), base.velocity
    base.step((np.nan, 0, 0), 0.1)   # a NaN command is treated as stop
    assert np.all(np.isfinite(base.pose))


def test_straight_motion_and_rotation():
    base = HolonomicBase((1.0, 2.0, np.pi / 2), MotionLimits(max_accel=100.0, max_yaw_accel=100.0))
    for _ in range(10):
        base.step((0.2, 0.0, 0.0), 0.1)
    # First step accelerates from rest: mean speed 0.1 m/s, so 0.19 m in 1 s.
    assert np.allclose(base.pose, (1.0, 2.19, np.pi / 2), atol=1e-9), base.pose


def test_odometry_scale_error_is_exact_without_noise():
    """With the per-step noise off, odometry is the true motion times its (seeded) scale errors:
    10 m straight ahead reads 10 m x scale[0]; two turns on the spot read 4 pi x yaw_scale."""
    odo = WheelOdometry(seed=3, noise_std=0.0)
    for _ in range(100):
        odo.update((0.1, 0.0, 0.0), 0.1)
    assert odo.pose[0] == pytest.approx(10.0 * odo.scale[0], abs=1e-9), (odo.pose, odo.scale)
    assert abs(odo.pose[1]) < 1e-12 and abs(odo.pose[2]) < 1e-12
    turn = WheelOdometry(seed=3, noise_std=0.0)
    for _ in range(400):
        turn.update((0.0, 0.0, np.pi / 100), 0.1)
    total = 4 * np.pi * turn.yaw_scale
    assert geo.wrap_angle(turn.pose[2] - total) == pytest.approx(0.0, abs=1e-9)
    assert np.hypot(*turn.pose[:2]) < 1e-9
    assert WheelOdometry(seed=1).scale.tolist() == WheelOdometry(seed=1).scale.tolist() != \
        WheelOdometry(seed=2).scale.tolist()


def test_odometry_drift_has_the_documented_size():
    """Over 200 seeded robots, the error after 10 m straight ahead has the std the model's
    parameters give: scale_std x 10 m from the scale error, and noise_std x sqrt(per-step
    distance) per step from the noise (100 steps of 0.1 m). The tolerance, +-20 %, is 4 standard
    errors of a std estimated from 200 samples (1/sqrt(2 x 200) = 5 %)."""
    scale_std, noise_std, steps, step = 0.01, 0.005, 100, 0.1
    errs = []
    for seed in range(200):
        odo = WheelOdometry(seed=seed, scale_std=scale_std, noise_std=noise_std)
        for _ in range(steps):
            odo.update((step, 0.0, 0.0), 0.1)
        errs.append(odo.pose[0] - steps * step)
    expected = np.hypot(scale_std * steps * step, noise_std * np.sqrt(step) * np.sqrt(steps))
    assert np.std(errs) == pytest.approx(expected, rel=0.2), (np.std(errs), expected)
    assert abs(np.mean(errs)) < 4 * expected / np.sqrt(200), np.mean(errs)


def test_waypoint_driver_visits_and_holds():
    wps = [(1.0, 0.0, 0.0), (1.0, 0.5, np.pi / 2)]
    drv = WaypointDriver(wps, hold_time=1.0)
    base = HolonomicBase((0, 0, 0))
    held, t = [], 0.0
    for _ in range(1000):
        cmd = drv.command(base.pose, t)
        held.append(drv.holding)
        if drv.holding >= 0:
            goal = wps[drv.holding]
            assert np.hypot(base.pose[0] - goal[0], base.pose[1] - goal[1]) < 0.01
        base.step(cmd, 0.05)
        t += 0.05
        if drv.finished:
            break
    assert drv.finished, "did not finish the waypoints in 50 s"
    assert 0 in held and 1 in held and held[0] == -1
    assert sum(1 for h in held if h == 0) * 0.05 >= 0.95


def test_laser_sees_the_room_walls():
    scene = Scene.default()
    scanner = LaserScanner(scene.room.wall_segments(), beams=4, angle_min=0.0, angle_max=1.5 * np.pi, noise_std=0.0)
    r = scanner.scan((5.5, 4.5, 0.0))
    assert np.allclose(r, [5.5, 4.5, 5.5, 4.5]), r
    r = scanner.scan((5.5, 4.5, np.pi / 2))
    assert np.allclose(r, [4.5, 5.5, 4.5, 5.5]), r
    full = LaserScanner(scene.obstacle_segments(), noise_std=0.0).scan(scene.mapping_pose)
    assert np.all(np.isfinite(full)) and full.max() < np.hypot(11, 9)
    short = LaserScanner(scene.obstacle_segments(), range_max=4.0, noise_std=0.0).scan(scene.mapping_pose)
    assert np.isinf(short).any()


def test_sim_robot_follows_external_commands_and_times_out():
    from aruco_ring_localization.simulation.motion import SimRobot
    robot = SimRobot((0, 0, 0), limits=MotionLimits(max_accel=100.0))
    robot.set_command((0.2, 0, 0), 0.0)
    s = robot.step(0.1, 0.1)
    assert s.holding == -1 and s.cmd[0] == 0.2 and s.pose[0] > 0.0
    x = s.pose[0]
    s = robot.step(1.0, 0.1)      # command older than 0.5 s: stop
    assert s.cmd[0] == 0.0


def test_sim_robot_direct_waypoints_hold_exactly():
    from aruco_ring_localization.simulation.motion import SimRobot
    wps = [(1.0, 2.0, 0.3), (2.0, 2.0, -0.3)]
    robot = SimRobot((0, 0, 0), waypoints=wps, hold_time=0.5, direct=True)
    seen = {}
    t = 0.0
    for _ in range(40):
        t += 0.1
        s = robot.step(t, 0.1)
        if s.holding >= 0:
            seen.setdefault(s.holding, s.pose)
    assert set(seen) == {0, 1}
    for i, p in seen.items():
        assert np.allclose(p, wps[i], atol=1e-9), (i, p)


def test_the_published_command_is_the_one_followed_within_the_limits():
    # The waypoint driver's proportional command is far above the limits when the goal is far (it
    # gave 3.7 m/s on the paper's route, which the localizer drops as beyond limits/max_speed).
    from aruco_ring_localization.simulation.motion import SimRobot
    lim = MotionLimits(max_speed=0.3, max_yaw_rate=0.5)
    robot = SimRobot((0, 0, 0), limits=lim)
    robot.set_command((5.0, 5.0, 2.0), 0.0)
    s = robot.step(0.1, 0.1)
    assert np.hypot(s.cmd[0], s.cmd[1]) == pytest.approx(0.3) and s.cmd[2] == pytest.approx(0.5)
    assert s.cmd[0] == pytest.approx(s.cmd[1])   # the direction kept
    robot.set_command((float("nan"), 0.0, 0.0), 0.2)
    assert np.all(robot.step(0.3, 0.1).cmd == 0.0)
