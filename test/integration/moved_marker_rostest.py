#!/usr/bin/env python3
"""rostest node of moved_marker.test: the localizer drops a moved marker, names it, re-maps it.

Marker 17 moves 5 cm at simulated t = 20 s (a simulator scene event). The localizer's
``/diagnostics`` status ``localizer: markers`` must turn WARN naming 17 and how far it
moved (3-8 cm), rosout must carry the warning naming it, and ``~remap_marker`` (std_srvs/Trigger,
every marker declared moved) must re-map it (moved 3-8 cm) and bring the status back to OK.
Waits are on events (messages), with generous wall-clock timeouts for a loaded machine.

Named ``*_rostest.py`` so pytest does not collect it.
"""
from __future__ import annotations

import re
import threading
import unittest

import rospy
import rostest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from rosgraph_msgs.msg import Log
from std_srvs.srv import Trigger

PKG = "aruco_ring_localization"
MARKER = 17
EVENT_T = 20.0
STATUS = "localizer: markers"


class MovedMarkerTest(unittest.TestCase):
    def setUp(self):
        self.cond = threading.Condition()
        self.status = None          # latest markers status
        self.first_warn_t = None    # sim time of the first WARN naming the marker
        self.logs = []
        self.poses = 0
        rospy.Subscriber("/diagnostics", DiagnosticArray, self.on_diag, queue_size=20)
        rospy.Subscriber("/rosout", Log, self.on_log, queue_size=200)   # every node's, directly
        rospy.Subscriber("/localizer/pose", PoseWithCovarianceStamped, self.on_pose, queue_size=10)

    def on_diag(self, msg):
        for s in msg.status:
            if s.name == STATUS:
                with self.cond:
                    self.status = s
                    if s.level == DiagnosticStatus.WARN and f"{MARKER} by" in s.message and self.first_warn_t is None:
                        self.first_warn_t = msg.header.stamp.to_sec()
                    self.cond.notify_all()

    def on_log(self, msg):
        with self.cond:
            self.logs.append(msg.msg)
            self.cond.notify_all()

    def on_pose(self, _msg):
        with self.cond:
            self.poses += 1
            self.cond.notify_all()

    def wait(self, pred, timeout):
        with self.cond:
            return self.cond.wait_for(pred, timeout)

    def test_moved_marker_is_dropped_named_and_remapped(self):
        self.assertTrue(self.wait(lambda: self.poses > 5, 120.0), "the localizer published no pose")
        self.assertTrue(self.wait(lambda: self.status is not None, 60.0), f"no '{STATUS}' diagnostics")
        ok_before = self.status.level == DiagnosticStatus.OK
        self.assertTrue(ok_before or rospy.get_time() >= EVENT_T,
                        f"markers status before the move: {self.status.message}")
        self.assertTrue(self.wait(lambda: self.first_warn_t is not None, 180.0),
                        f"no WARN naming marker {MARKER} (last status: {self.status.message!r})")
        with self.cond:
            s = self.status
            values = {kv.key: kv.value for kv in s.values}
        self.assertEqual(values.get("moved_markers"), str(MARKER), s.message)
        moved_cm = float(values[f"marker_{MARKER}_moved_cm"])
        self.assertTrue(3.0 <= moved_cm <= 8.0, f"reported {moved_cm} cm for a 5 cm move")
        # The declaration names it, then a throttled reminder every 5 s ("... dropped from the pose: 17 (5.0 cm)").
        named = re.compile(rf"marker {MARKER} moved by|dropped from the pose: (.*, )?{MARKER} \(")
        self.assertTrue(self.wait(lambda: any(named.search(m) for m in self.logs), 30.0),
                        f"rosout never named the moved marker ({len(self.logs)} lines seen)")
        # The diagnostics come once a second: the move was seen within a few of them.
        self.assertLess(self.first_warn_t - EVENT_T, 5.0, f"declared at t={self.first_warn_t:.1f} s")
        # A few more frames of it from where it is now, then re-map it.
        t0 = rospy.get_time()
        self.assertTrue(self.wait(lambda: rospy.get_time() > t0 + 3.0, 60.0), "the clock stopped")
        rospy.wait_for_service("/localizer/remap_marker", 30.0)
        res = rospy.ServiceProxy("/localizer/remap_marker", Trigger)()
        self.assertTrue(res.success, res.message)
        m = re.search(rf"re-mapped {MARKER} \(moved ([0-9.]+) cm\)", res.message)
        self.assertIsNotNone(m, res.message)
        self.assertTrue(3.0 <= float(m.group(1)) <= 8.0, res.message)
        self.assertTrue(self.wait(lambda: self.status.level == DiagnosticStatus.OK, 30.0),
                        f"markers status after re-mapping: {self.status.message}")


if __name__ == "__main__":
    rospy.init_node("moved_marker_test")
    rostest.rosrun(PKG, "moved_marker", MovedMarkerTest)
