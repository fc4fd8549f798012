#!/usr/bin/env python3
"""rostest node of hostile_load.test: a flood and a paused process (issue 14, F3, F4).

* ``flood``: 3,000 random quads (ids 0..2999, so that none is dropped as a duplicate, the
  mapped ones among them) per message on ring/cam0 at 10 Hz for 10 s,
  beside the simulator's own cam0 messages (the issue: output fell to 1.3 Hz, messages backed up
  14 s, late frames reset the filter, poses jumped 57-78 cm).
* ``pause``: ``kill -STOP`` of the localizer process for 10 s while the robot drives, then
  ``kill -CONT`` (the issue: predicted poses 11 cm off, then a 12 cm jump).

Checks per window: no pose more than 10 cm off the ground truth, no step beyond the robot's
motion, the tf listener started before resolves ``map -> base_link`` at now afterwards, the
warning said and throttled; for the flood, the pose rate and latency hold while it lasts; for the
pause, nothing is published from the stale state and the first pose after it comes within
RECOVERY_S. Named ``*_rostest.py`` so pytest does not collect it.
"""
from __future__ import annotations

import os
import signal
import sys
import unittest

import numpy as np
import rospy
import rostest
import tf2_ros
from fiducial_msgs.msg import Fiducial, FiducialArray

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "faults"))

from hostile_session import HostileSession  # noqa: E402

PKG = "aruco_ring_localization"
FLOOD_S = 10.0
PAUSE_S = 10.0
SETTLE = 3.0
#: After SIGCONT the localizer reads its backlog (dropped as stale) and the next ring frame: the
#: first pose came 0.1-0.4 s after SIGCONT in our runs (load 5-15); 2 s leaves room for a loaded CI.
RECOVERY_S = 2.0
#: While the flood lasts, against the clean window just before it (same run): at least half its
#: posed fraction (of the simulator's ring frames, the fraction that got a pose: the simulator's own
#: pace on a loaded machine is not the localizer's doing), and the 95th percentile of the latency
#: (arrival - stamp) at most 0.7 s above its own (the issue: 1.3 of 10 Hz, 14 s behind; a backlog
#: makes every frame stale, fraction 0). Measured at load 12-20 on the 2 shared cores: 0.61-1.07 of
#: the clean window's fraction, +0.01-0.33 s of latency (docs/reliability.md, "Hostile input"); the
#: bounds are the issue's regression with a wide margin (it gave 0.13 and +14 s), not a busy machine:
#: half the clean fraction, and twice the largest extra latency measured.
FLOOD_MIN_RATE_RATIO = 0.5
FLOOD_MAX_EXTRA_LATENCY_S = 0.7
CLEAN_S = 8.0


def flood_message(n: int = 3000, seed: int = 5) -> FiducialArray:
    rng = np.random.default_rng(seed)
    msg = FiducialArray()
    msg.header.frame_id = "cam0_optical_frame"
    for fid, (x, y) in zip(rng.permutation(n), rng.uniform(0, 1200, (n, 2))):
        f = Fiducial()
        f.fiducial_id = int(fid)
        f.x0, f.y0, f.x1, f.y1, f.x2, f.y2, f.x3, f.y3 = x, y, x + 20, y, x + 20, y + 20, x, y + 20
        msg.fiducials.append(f)
    return msg


class HostileLoad(unittest.TestCase):
    windows = {}
    tf_after = {}

    @classmethod
    def setUpClass(cls):
        rospy.init_node("hostile")
        cls.s = HostileSession()
        cls.cam0 = rospy.Publisher("ring/cam0/fiducial_vertices", FiducialArray, queue_size=2)
        cls.s.sleep(1.0)
        cls.clean_t = (cls.s.wait_tracking(), None)
        cls.s.sleep(CLEAN_S)
        cls.clean_t = (cls.clean_t[0], rospy.get_time())
        for name, fault in (("flood", cls._flood), ("pause", cls._pause)):
            t0 = rospy.get_time()
            fault()
            cls.s.sleep(SETTLE)
            cls.windows[name] = (t0, rospy.get_time())
            try:
                cls.s.lookup_now()
                cls.tf_after[name] = None
            except tf2_ros.TransformException as exc:
                cls.tf_after[name] = f"{type(exc).__name__}: {exc}"

    @classmethod
    def tearDownClass(cls):
        extra = {"flood_rate_hz": cls.rate(*cls.flood_t), "flood_latency_p95_s": cls.latency(*cls.flood_t),
                 "clean_rate_hz": cls.rate(*cls.clean_t), "clean_latency_p95_s": cls.latency(*cls.clean_t),
                 "flood_posed_fraction": cls.posed(*cls.flood_t), "clean_posed_fraction": cls.posed(*cls.clean_t),
                 "flood_sim_frames_hz": cls.sim_rate(*cls.flood_t), "clean_sim_frames_hz": cls.sim_rate(*cls.clean_t),
                 "first_pose_after_pause_s": cls.first_after_pause(), "tf_after": cls.tf_after,
                 "warning_lines": {"flood": len(cls.s.lines("too many detections", *cls.windows["flood"])),
                                   "pause": len(cls.s.lines("timing/max_pause", *cls.windows["pause"]))}}
        cls.s.write_results("hostile_load", cls.windows, extra)

    @classmethod
    def _flood(cls):
        msg = flood_message()
        cls.flood_t = (rospy.get_time(), rospy.get_time() + FLOOD_S)
        rate = rospy.Rate(10.0)
        while rospy.get_time() < cls.flood_t[1]:
            msg.header.stamp = rospy.Time.now()
            cls.cam0.publish(msg)
            rate.sleep()

    @classmethod
    def _pause(cls):
        pid = cls.s.pid_of("/localizer")
        cls.s.wait_driving()
        cls.pause_t = [rospy.get_time(), None]
        os.kill(pid, signal.SIGSTOP)
        try:
            cls.s.sleep(PAUSE_S)
        finally:
            os.kill(pid, signal.SIGCONT)
            cls.pause_t[1] = rospy.get_time()

    @classmethod
    def rate(cls, t0: float, t1: float) -> float:
        """Poses per second stamped in [t0 + 1, t1)."""
        return round(len(cls.s.poses(t0 + 1.0, t1)) / (t1 - t0 - 1.0), 2)

    @classmethod
    def posed(cls, t0: float, t1: float) -> float:
        """Fraction of the simulator's ring frames stamped in [t0 + 1, t1) that got a pose."""
        return round(cls.s.posed_fraction(t0 + 1.0, t1), 3)

    @classmethod
    def sim_rate(cls, t0: float, t1: float) -> float:
        """Ring frames per second the simulator made, stamped in [t0 + 1, t1)."""
        return round(cls.s.frames(t0 + 1.0, t1) / (t1 - t0 - 1.0), 2)

    @classmethod
    def latency(cls, t0: float, t1: float) -> float:
        """95th percentile of arrival - stamp of the poses stamped in [t0, t1), s."""
        lat = [p.received - p.stamp for p in cls.s.poses(t0, t1)]
        return round(float(np.percentile(lat, 95)), 3) if lat else float("nan")

    @classmethod
    def first_after_pause(cls):
        after = [p.received for p in cls.s.poses(cls.pause_t[1] - 0.5) if p.received >= cls.pause_t[1]]
        return round(min(after) - cls.pause_t[1], 3) if after else None

    def test_1_no_pose_more_than_10cm_off_and_no_step_beyond_the_motion(self):
        self.s.check_windows(self.windows)

    def test_3_flood_keeps_the_rate_and_the_latency(self):
        clean, flood = self.posed(*self.clean_t), self.posed(*self.flood_t)
        self.assertGreaterEqual(flood, FLOOD_MIN_RATE_RATIO * clean,
                                f"{flood:.0%} of the simulator's frames posed during the flood, {clean:.0%} before "
                                f"({self.rate(*self.flood_t)} Hz, {self.rate(*self.clean_t)} Hz)")
        clean, flood = self.latency(*self.clean_t), self.latency(*self.flood_t)
        self.assertLess(flood, clean + FLOOD_MAX_EXTRA_LATENCY_S, f"latency p95 {flood} s, {clean} s before")

    def test_4_nothing_published_from_the_stale_state_and_a_pose_within_recovery(self):
        t_stop, t_cont = self.pause_t
        during = [p for p in self.s.poses(t_stop + 0.5) if p.received < t_cont]
        self.assertFalse(during, f"{len(during)} poses published while the localizer was stopped")
        first = self.first_after_pause()
        self.assertIsNotNone(first, "no pose after the pause")
        self.assertLess(first, RECOVERY_S, f"the first pose came {first:.2f} s after SIGCONT")
        predicted = [p for p in self.s.poses(t_stop, t_cont + 1.0) if p.received >= t_cont and p.std_xy > 0.1]
        self.assertFalse(predicted, f"poses predicted across the pause: {predicted[:2]}")

    def test_5_tf_resolves_map_to_base_link_at_now_afterwards(self):
        bad = {k: v for k, v in self.tf_after.items() if v is not None}
        self.assertFalse(bad, f"the tf listener started before the faults fails: {bad}")

    def test_6_said_and_throttled(self):
        for name, needle in (("flood", "too many detections"), ("pause", "timing/max_pause")):
            t0, t1 = self.windows[name]
            lines = self.s.lines(needle, t0, t1 + 0.5)
            self.assertGreaterEqual(len(lines), 1, f"{name}: nothing said ({needle!r})")
            self.assertLessEqual(len(lines), self.s.max_throttled_lines(t1 - t0), f"{name}: {lines[:3]}")

    def test_9_no_callback_raised(self):
        bad = self.s.lines("bad callback") + self.s.lines("Traceback")
        self.assertFalse(bad, f"a localizer callback raised: {bad[:2]}")


if __name__ == "__main__":
    rostest.rosrun(PKG, "hostile_load", HostileLoad)
