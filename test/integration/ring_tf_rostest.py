#!/usr/bin/env python3
"""rostest node for ring_tf.test: the ring's static extrinsics, seen by a late-joining listener.

Named ``*_rostest.py`` (not ``test_*.py``) so that pytest does not collect it: it needs the
master that rostest starts. test/integration/test_rostests.py runs it through rostest.
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import unittest

import numpy as np
import rospkg
import rospy
import rostest
import tf2_ros

from aruco_ring_localization.geometry import transform_from_translation_quaternion
from aruco_ring_localization.ring import CameraRing

PKG = "aruco_ring_localization"
TOL = 1e-6


def _package_path() -> str:
    return rospkg.RosPack().get_path(PKG)


class RingTfTest(unittest.TestCase):
    """ring_tf.launch is running (started by ring_tf.test)."""

    @classmethod
    def setUpClass(cls):
        rospy.init_node("ring_tf_rostest")
        ring_file = rospy.get_param("~ring_file", os.path.join(_package_path(), "config", "ring.yaml"))
        cls.ring = CameraRing.load(ring_file)
        # Join late: ring_tf sent its transforms once, long before this listener exists, so
        # they can only arrive through /tf_static's latching (all cameras in one message).
        rospy.sleep(1.0)
        cls.buffer = tf2_ros.Buffer()
        cls.listener = tf2_ros.TransformListener(cls.buffer)

    def test_all_cameras_resolve_with_ring_values(self):
        self.assertEqual(len(self.ring.cameras), 8, "the shipped ring has 8 cameras")
        for camera in self.ring.cameras:
            msg = self.buffer.lookup_transform(self.ring.base_frame, camera.frame_id, rospy.Time(0),
                                               rospy.Duration(10.0))
            t = msg.transform.translation
            q = msg.transform.rotation
            T = transform_from_translation_quaternion([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])
            err = float(np.max(np.abs(T - camera.T_base_cam)))
            self.assertLess(err, TOL, f"{self.ring.base_frame} -> {camera.frame_id}: max |T_tf - T_ring| = "
                                      f"{err:.3g} (tolerance {TOL:g})\ntf:\n{T}\nring.yaml:\n{camera.T_base_cam}")

    def test_markers_draw_every_cameras_field_of_view_and_the_robot(self):
        from visualization_msgs.msg import MarkerArray

        msg = rospy.wait_for_message("/ring_tf/markers", MarkerArray, timeout=10.0)   # latched
        frustums = {m.header.frame_id: m for m in msg.markers if m.ns == "frustums"}
        self.assertEqual(sorted(frustums), sorted(c.frame_id for c in self.ring.cameras))
        for camera in self.ring.cameras:
            m = frustums[camera.frame_id]
            self.assertTrue(m.frame_locked)
            # rviz places a marker with tf at its stamp: 0 (latest) shows it whenever the robot's
            # pose arrives; the launch time hid it (no map -> base_link that early)
            self.assertEqual(m.header.stamp, rospy.Time(0))
            self.assertEqual(len(m.points), 16)
            self.assertAlmostEqual(max(p.z for p in m.points), 1.0, places=6)   # frustum_depth's default
        robot = [m for m in msg.markers if m.ns == "robot"]
        self.assertEqual([m.header.frame_id for m in robot], [self.ring.base_frame] * 2)

    def test_bad_ring_file_exits_1_naming_file_and_key(self):
        script = os.path.join(_package_path(), "scripts", "ring_tf")
        with tempfile.TemporaryDirectory() as tmp:
            bad = os.path.join(tmp, "bad_ring.yaml")
            with open(bad, "w") as f:
                f.write("format_version: 1\nbase_frame: base_link\ncameras: []\n")
            proc = subprocess.run(
                [sys.executable, script, "__name:=ring_tf_bad", f"_ring_file:={bad}"],
                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, universal_newlines=True, timeout=60)
        self.assertEqual(proc.returncode, 1, f"exit code {proc.returncode}, output:\n{proc.stdout}")
        self.assertIn(bad, proc.stdout, f"the error must name the file; output:\n{proc.stdout}")
        self.assertIn("cameras", proc.stdout, f"the error must name the key; output:\n{proc.stdout}")


if __name__ == "__main__":
    rostest.rosrun(PKG, "ring_tf_rostest", RingTfTest)
