#!/usr/bin/env python3
"""rostest node for faults_data.test: wrong detections, a kidnapped robot, time jumping back.

The simulator node (corners mode, namespace ``lab``) plays the lab; in setUpClass a
:class:`FaultSession` (test/faults/) drives the robot along :func:`path`, relays the simulator's
detections to the localizer corrupting 10 % of them in the ``corrupt`` phase, kidnaps the robot
(the simulator's ``sim/teleport``) and makes the clock jump back (``sim/time_jump``) when those
phases start, and records what the localizer publishes; then each test asserts one behaviour on
it. Named ``*_rostest.py`` so pytest does not collect it.
"""
from __future__ import annotations

import os
import sys
import unittest

import numpy as np
import rospkg
import rospy
import rostest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "faults"))

from fault_session import FaultSession  # noqa: E402
from faults import FaultSchedule  # noqa: E402

from aruco_ring_localization import geometry as geo  # noqa: E402

PKG = "aruco_ring_localization"
RATE = 10.0
T0 = 100.0            # the simulator's clock.start_time (faults_data.test)
TOL_M = 0.05
TOL_CORRUPT_M = 0.10   # issue 7: no position error above 10 cm with 10% wrong detections
KIDNAP = (2.4, 1.8, np.pi / 2)   # 3.0 m and 90 deg
RELOCALIZE_S = 2.0
JUMP_S = -30.0


def path(t: float) -> np.ndarray:
    """Robot pose at time t of the run: slow drift around (4.3, 3.8) on the plate (the simulator
    starts at path(0): robot/start_pose in faults_data.test; the kidnap offsets the rest)."""
    return np.array([4.3 + 0.2 * np.sin(0.2 * t), 3.8 + 0.15 * np.sin(0.15 * t), 0.2 + 0.03 * t])


def schedule() -> FaultSchedule:
    s = FaultSchedule()
    s.add("warmup", 2.0)
    s.add("corrupt", 8.0, corrupt_rate=0.10)
    s.add("clean", 1.5)
    s.add("kidnapped", 4.0, kidnap=KIDNAP)
    s.add("before_jump", 1.5)
    s.add("time_jump", 4.0, time_jump=JUMP_S)
    return s


class FaultsDataTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("faults_data_rostest")
        root = rospkg.RosPack().get_path(PKG)
        cls.p = FaultSession(path, schedule(), f"{root}/config/ring.yaml", t0=T0, rate_hz=RATE, seed=13)
        assert cls.p.wait_connected(), "the simulator's detections never reached the relay"
        cls.p.run()
        rospy.rostime.wallsleep(1.5)
        cls.root = root
        first = cls.p.truth[min(k for k in cls.p.truth if k >= 1000 * T0)]
        assert np.hypot(*(first[:2] - path(0)[:2])) < 0.01 and abs(first[2] - path(0)[2]) < 0.01, \
            f"the simulator started at {first}, not at path(0) = {path(0)}: robot/start_pose in the .test file"

    @classmethod
    def tearDownClass(cls):
        extra = cls.extra() if hasattr(cls, "extra") else {}
        cls.p.write_summary(os.path.join(cls.root, "results", "faults", "faults_data.json"), extra)

    @classmethod
    def extra(cls):
        """Time from the kidnap to the first pose of a run within 5 cm that stays within it."""
        ph = next(x for x in cls.p.schedule.phases if x.name == "kidnapped")
        poses = cls.p.poses_in("kidnapped")
        t_ok = None
        for i, r in enumerate(poses):
            if all(q.error < TOL_M for q in poses[i:]):
                t_ok = r.t - ph.start
                break
        return {"relocalized_after_s": t_ok}

    def _phase(self, name):
        return next(x for x in self.p.schedule.phases if x.name == name)

    def test_1_wrong_detections_never_move_the_pose_beyond_10cm(self):
        poses = self.p.poses_in("corrupt")
        self.assertGreater(len(poses), 0.3 * 8.0 * RATE, f"only {len(poses)} poses in the corrupt phase")
        injected = sum(self.p.injected.values())
        self.assertGreater(injected, 20, f"the test injected only {self.p.injected}")
        worst = max(poses, key=lambda r: r.error)
        self.assertLess(worst.error, TOL_CORRUPT_M,
                        f"position error {worst.error * 100:.1f} cm at t={worst.t:.1f} s with wrong detections "
                        f"(injected {self.p.injected})")

    def test_2_wrong_detections_are_counted_as_rejected(self):
        def rejected(diags):
            if not diags:
                return 0
            return sum(int(v) for k, v in diags[-1].values.items() if k.startswith("rejected_"))
        before = rejected(self.p.diags_in("warmup"))
        after = rejected(self.p.diags_in("clean") or self.p.diags_in("kidnapped"))
        self.assertGreater(after - before, 0.2 * sum(self.p.injected.values()),
                           f"diagnostics count {after - before} rejections for {self.p.injected} injected faults "
                           f"(last filter diagnostics: {self.p.diags[-1].values if self.p.diags else None})")

    def test_3_kidnapped_robot_relocalizes_within_2s_and_says_so(self):
        ph = self._phase("kidnapped")
        late = [r for r in self.p.poses_in("kidnapped") if r.t >= ph.start + RELOCALIZE_S]
        self.assertGreater(len(late), 5, f"only {len(late)} poses {RELOCALIZE_S} s after the kidnap")
        worst = max(late, key=lambda r: r.error)
        self.assertLess(worst.error, TOL_M, f"{RELOCALIZE_S} s after a 3 m / 90 deg kidnap the error is still "
                                            f"{worst.error * 100:.1f} cm (t={worst.t:.1f})")
        yaw_err = max(abs(geo.angle_diff(r.pose[2], r.truth[2])) for r in late)
        self.assertLess(yaw_err, np.radians(2.0), f"yaw error {np.degrees(yaw_err):.1f} deg after the kidnap")
        logs = [m for t, _, m in self.p.logs if ph.start <= t < ph.start + RELOCALIZE_S + 1.0]
        self.assertTrue(any("re-initialised" in m or "reinitial" in m or "relocali" in m for m in logs),
                        f"the kidnap was not said in the log: {logs[:6]}")

    def test_4_time_jump_back_resets_without_divergence(self):
        ph = self._phase("time_jump")
        poses = self.p.poses_in("time_jump", after=1.0)
        self.assertGreater(len(poses), 5, f"only {len(poses)} poses after the time jump")
        worst = max(poses, key=lambda r: r.error)
        self.assertLess(worst.error, TOL_M, f"after the time jump: error {worst.error * 100:.1f} cm")
        self.assertTrue(all(r.std_xy < 0.5 for r in poses), "covariance diverged after the time jump")
        logs = [m for t, _, m in self.p.logs if t >= ph.start]
        self.assertTrue(any("time jumped back" in m for m in logs), f"time jump not logged: {logs[:6]}")


    def test_9_no_callback_raised(self):
        """rospy logs 'bad callback' when a subscriber/timer callback raises: it must never happen."""
        bad = [m for _, _, m in self.p.logs if "bad callback" in m or "Traceback" in m]
        self.assertFalse(bad, f"a localizer callback raised: {bad[:2]}")

if __name__ == "__main__":
    rostest.rosrun(PKG, "faults_data", FaultsDataTest)
