#!/usr/bin/env python3
"""rostest node for diagnostics_aggregator.test: /diagnostics_agg groups the localizer's statuses.

Named ``*_rostest.py`` so that pytest does not collect it (it needs rostest's master).
"""
from __future__ import annotations

import threading
import unittest

import rospkg
import rospy
import rostest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

from aruco_ring_localization.ring import CameraRing

PKG = "aruco_ring_localization"


class AggregatorTest(unittest.TestCase):
    def test_every_status_lands_in_its_group(self):
        rospy.init_node("diagnostics_aggregator_rostest")
        ring = CameraRing.load(f"{rospkg.RosPack().get_path(PKG)}/config/ring.yaml")
        expected = {f"/ArUco ring/Cameras/{n}" for n in ring.names} | {"/ArUco ring/Localizer/filter"}
        got = {}
        done = threading.Event()

        def on_agg(msg):
            statuses = {s.name: s for s in msg.status}
            # the filter ERROR (every camera silent) once the localizer has judged them silent
            f = statuses.get("/ArUco ring/Localizer/filter")
            if expected <= set(statuses) and f is not None and f.level == DiagnosticStatus.ERROR:
                got.update(statuses)
                done.set()

        rospy.Subscriber("/diagnostics_agg", DiagnosticArray, on_agg, queue_size=5)
        self.assertTrue(done.wait(90.0), f"/diagnostics_agg never held {sorted(expected)} with the filter in ERROR")
        other = sorted(n for n in got if n.startswith("/Other"))
        self.assertFalse(other, f"statuses no analyzer claims: {other}")
        for n in ring.names:
            s = got[f"/ArUco ring/Cameras/{n}"]
            self.assertEqual(s.level, DiagnosticStatus.WARN, f"{n}: {s.message}")
            self.assertEqual(s.hardware_id, n)
        self.assertEqual(got["/ArUco ring"].level, DiagnosticStatus.ERROR)


if __name__ == "__main__":
    rostest.rosrun(PKG, "diagnostics_aggregator", AggregatorTest)
