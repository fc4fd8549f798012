#!/usr/bin/env python3
"""rostest node for simulator_lockstep.test: with ~lockstep no rendered frame is lost.

Records the stamps of both detectors' FiducialArrays and of /clock; once ``~frames`` frames have
been answered, every clock tick from the first answered frame on must have an answer from each
camera (the simulator asked for 20x real time, which the detectors cannot follow: without the
lockstep they drop images and the stamps show gaps). The cameras are free-running: a camera's
answer to the frame at t is stamped with its exposure time in (t - 1/rate, t], so a stamp s
belongs to the frame ceil(s * rate); the two cameras' stamps must differ (their own phases).
"""
from __future__ import annotations

import threading
import time
import unittest

import numpy as np
import rospy
import rostest
from fiducial_msgs.msg import FiducialArray

PKG = "aruco_ring_localization"
CAMERAS = ("cam1", "cam5")
RATE = 10.0


class LockstepTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("simulator_lockstep_rostest")
        cls.frames = int(rospy.get_param("~frames", 40))
        cls.lock = threading.Lock()
        cls.stamps = {c: [] for c in CAMERAS}
        cls.markers = {c: 0 for c in CAMERAS}
        for cam in CAMERAS:
            rospy.Subscriber(f"ring/{cam}/fiducial_vertices", FiducialArray, cls._keep, callback_args=cam,
                             queue_size=100)

    @classmethod
    def _keep(cls, msg, cam):
        with cls.lock:
            cls.stamps[cam].append(msg.header.stamp.to_sec())
            cls.markers[cam] += len(msg.fiducials)

    def test_every_frame_is_answered_by_every_detector(self):
        end = time.monotonic() + 100.0
        while time.monotonic() < end and not rospy.is_shutdown():
            with self.lock:
                if all(len(s) >= self.frames for s in self.stamps.values()):
                    break
            time.sleep(0.1)
        with self.lock:
            stamps = {c: np.array(s) for c, s in self.stamps.items()}
            markers = dict(self.markers)
        counts = {c: len(s) for c, s in stamps.items()}
        self.assertTrue(all(n >= self.frames for n in counts.values()), f"answers per camera after 100 s: {counts}")
        frames = {c: np.ceil(s * RATE - 1e-6).astype(int) for c, s in stamps.items()}
        first = max(f[0] for f in frames.values())
        last = min(f[-1] for f in frames.values())
        expected = np.arange(first, last + 1)
        common = set(np.round(stamps["cam1"], 6)) & set(np.round(stamps["cam5"], 6))
        self.assertLess(len(common), 3, f"free-running cameras share {len(common)} stamps")
        for cam, s in stamps.items():
            got = set(frames[cam])
            lost = sorted(set(expected) - got)
            self.assertFalse(lost, f"{cam}: {len(lost)} of {len(expected)} frames never answered "
                                   f"(first lost t={lost[0] / RATE if lost else 0:.1f} s)")
            self.assertGreater(markers[cam], 0, f"{cam}: no marker detected in {counts[cam]} frames")


if __name__ == "__main__":
    rostest.rosrun(PKG, "simulator_lockstep", LockstepTest)
