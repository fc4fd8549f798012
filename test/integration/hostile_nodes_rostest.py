#!/usr/bin/env python3
"""rostest node of hostile_nodes.test: a second localizer, bad map files (issue 14, F6, F7).

* ``second_localizer``: ``rosrun aruco_ring_localization localizer __name:=localizer_two`` on the
  same map (the issue: two localizers ran at once with no warning). Both must say that another
  node publishes their tf child (``map -> odom``), throttled; ours keeps tracking; once the second
  one is gone, the warnings stop.
* ``bad maps``: localizers started on a map with a marker at 1e308 m and on a file beyond the size
  limit exit with code 1 and one fatal line naming the file and the key (or the limit).

Named ``*_rostest.py`` so pytest does not collect it.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import unittest

import rospkg
import rospy
import rostest
import tf2_ros
import yaml
from geometry_msgs.msg import PoseWithCovarianceStamped

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "faults"))

from hostile_session import MAX_ERROR_M, STEP_NOISE_M, HostileSession  # noqa: E402

from aruco_ring_localization.marker_map import MAX_MAP_FILE_BYTES  # noqa: E402

PKG = "aruco_ring_localization"
TWO_S = 15.0          # both localizers run this long
#: The second publisher is said at its first map -> odom (the localizer checks the sender of every
#: /tf message), so within a ring frame of the second one's first pose; 1 s leaves room for load.
DETECT_S = 1.0
NEEDLE = "also publishes tf"


def _localizer(name: str, map_file: str) -> subprocess.Popen:
    """``rosrun aruco_ring_localization localizer __name:=NAME _map_file:=MAP`` (the package's script,
    run directly: rosrun itself is not installed everywhere)."""
    script = os.path.join(rospkg.RosPack().get_path(PKG), "scripts", "localizer")
    return subprocess.Popen([sys.executable, script, f"__name:={name}", f"_map_file:={map_file}"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, universal_newlines=True,
                            start_new_session=True)


class HostileNodes(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("hostile")
        cls.s = HostileSession()
        cls.root = rospkg.RosPack().get_path(PKG)
        cls.truth_map = os.path.join(cls.root, "test", "data", "lab_truth_map.yaml")
        cls.s.sleep(1.0)
        cls.s.wait_tracking()
        cls.t_two = rospy.get_time()
        cls.two_first_pose = None
        rospy.Subscriber("/localizer_two/pose", PoseWithCovarianceStamped, cls._on_two_pose, queue_size=5)
        two = _localizer("localizer_two", cls.truth_map)
        try:
            cls.s.sleep(TWO_S)
        finally:
            two.send_signal(signal.SIGINT)
            cls.two_output = two.communicate(timeout=30)[0]
        cls.t_one = rospy.get_time()
        cls.s.sleep(2 * 5.0 + 1.0)   # two throttle periods with our localizer alone
        cls.t_end = rospy.get_time()
        try:
            cls.s.lookup_now()
            cls.tf_after = None
        except tf2_ros.TransformException as exc:
            cls.tf_after = f"{type(exc).__name__}: {exc}"

    @classmethod
    def tearDownClass(cls):
        cls.s.write_results("hostile_nodes", {"second_localizer": (cls.t_two, cls.t_one), "alone": (cls.t_one, cls.t_end)},
                            {"first_warning_after_s": cls.first_warning(),
                             "warning_lines": len(cls.s.lines(NEEDLE, cls.t_two, cls.t_one + 1.0))})

    @classmethod
    def _on_two_pose(cls, _msg) -> None:
        if cls.two_first_pose is None:
            cls.two_first_pose = rospy.get_time()

    @classmethod
    def first_warning(cls):
        """Seconds from the second localizer's first pose to our localizer's first warning."""
        with cls.s.lock:
            times = [t for t, _, m in cls.s.logs if NEEDLE in m and t >= cls.t_two]
        if not times or cls.two_first_pose is None:
            return None
        return round(min(times) - cls.two_first_pose, 2)

    def test_1_a_second_localizer_on_our_frames_is_said_throttled_by_both(self):
        lines = self.s.lines(NEEDLE, self.t_two, self.t_one + 1.0)
        self.assertTrue(lines, "our localizer said nothing about a second publisher of map -> odom")
        self.assertIn("/localizer_two", lines[0])
        self.assertIsNotNone(self.two_first_pose, "the second localizer never published a pose")
        self.assertLess(self.first_warning(), DETECT_S)
        self.assertLessEqual(len(lines), self.s.max_throttled_lines(self.t_one - self.t_two))
        self.assertIn(NEEDLE, self.two_output, "the second localizer did not say it either:\n" + self.two_output[-2000:])

    def test_2_once_alone_the_warnings_stop(self):
        self.assertFalse(self.s.lines(NEEDLE, self.t_one + 6.0, self.t_end))

    def test_3_our_localizer_keeps_tracking_and_tf_resolves(self):
        for t0, t1 in ((self.t_two, self.t_one), (self.t_one, self.t_end)):
            worst = self.s.worst(t0, t1)
            self.assertLess(worst.error, MAX_ERROR_M, self.s.summary(t0, t1))
            self.assertLess(self.s.worst_step(t0, t1)[0], STEP_NOISE_M, self.s.summary(t0, t1))
        self.assertIsNone(self.tf_after)

    def _bad_map(self, text: str, size: int = 0):
        with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as fh:
            fh.write(text)
            if size:
                fh.truncate(size)   # sparse: no disk space, but the size a loader sees
            path = fh.name
        try:
            proc = _localizer("localizer_bad_map", path)
            out = proc.communicate(timeout=60)[0]
            return proc.returncode, out, path
        finally:
            os.unlink(path)

    def test_4_a_marker_at_absurd_coordinates_is_refused_naming_the_key(self):
        data = yaml.safe_load(open(self.truth_map))
        data["markers"][3]["translation"][0] = 1e308
        code, out, path = self._bad_map(yaml.safe_dump(data))
        self.assertEqual(code, 1, out[-2000:])
        fatal = [line for line in out.splitlines() if "FATAL" in line or "from the map origin" in line]
        self.assertTrue(fatal and path in fatal[0] and "markers[3].translation" in fatal[0], out[-2000:])

    def test_5_a_map_file_beyond_the_size_limit_is_refused(self):
        code, out, path = self._bad_map(open(self.truth_map).read(), size=MAX_MAP_FILE_BYTES + 1)
        self.assertEqual(code, 1, out[-2000:])
        self.assertTrue(any(path in line and "MiB" in line for line in out.splitlines()), out[-2000:])

    def test_9_no_callback_raised(self):
        bad = self.s.lines("bad callback") + self.s.lines("Traceback")
        self.assertFalse(bad, f"a localizer callback raised: {bad[:2]}")


if __name__ == "__main__":
    rostest.rosrun(PKG, "hostile_nodes", HostileNodes)
