#!/usr/bin/env python3
"""rostest node for apriltag_relay.test: both AprilTag message types in, fiducial_vertices out.

The apriltag_msgs messages are the real ones of test_8 (their class built from the definition
stored in the bag, as the relay builds it from the publisher's: no apriltag package is
installed); the apriltag_ros one is made here from the message definition of apriltag_ros.
"""
from __future__ import annotations

import threading
import unittest

import numpy as np
import rosbag
import rospy
import rostest
from fiducial_msgs.msg import FiducialArray

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.markers import APRILTAG_TO_ARUCO, marker_corners
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros.apriltag import APRILTAG_ROS_TYPE, apriltag_ros_definition, message_class, message_classes

PKG = "aruco_ring_localization"
N_FRAMES = 20



class ApriltagRelayTest(unittest.TestCase):

    @classmethod
    def setUpClass(cls):
        rospy.init_node("apriltag_relay_rostest")
        cls.ring = CameraRing.load(rospy.get_param("~ring_file"))
        cls.received = {c.name: [] for c in cls.ring.cameras}
        cls.lock = threading.Lock()
        cls.subs = [rospy.Subscriber("/" + c.namespace + "/fiducial_vertices", FiducialArray, cls._store,
                                     callback_args=c.name) for c in cls.ring.cameras]
        with rosbag.Bag(rospy.get_param("~bag")) as bag:
            conn = next(iter(bag._connections.values()))
            cls.tag_class = message_class(conn.datatype, conn.msg_def)
            cls.messages = []
            for topic, msg, _ in bag.read_messages():
                cls.messages.append((topic, msg))
                if len(cls.messages) >= 4 * N_FRAMES:
                    break

    @classmethod
    def _store(cls, msg, camera):
        with cls.lock:
            cls.received[camera].append(msg)

    def _wait(self, camera, n, timeout=20.0):
        end = rospy.Time.now() + rospy.Duration(timeout)
        while rospy.Time.now() < end and not rospy.is_shutdown():
            with self.lock:
                if len(self.received[camera]) >= n:
                    return list(self.received[camera])
            rospy.sleep(0.05)
        with self.lock:
            return list(self.received[camera])

    def _publisher(self, topic, cls):
        pub = rospy.Publisher(topic, cls, queue_size=100)
        end = rospy.Time.now() + rospy.Duration(15.0)
        while pub.get_num_connections() == 0 and rospy.Time.now() < end:
            rospy.sleep(0.05)
        self.assertGreater(pub.get_num_connections(), 0, f"the relay does not subscribe to {topic}")
        return pub

    def test_1_apriltag_msgs_corners_are_relayed_in_aruco_order(self):
        topics = sorted({t for t, _ in self.messages})
        pubs = {t: self._publisher(t, self.tag_class) for t in topics}
        # Our fiducial_vertices subscriptions connected to the relay too, or its first messages are
        # published to nobody (CI 2026-12-03: cam2 19 of 20 relayed under load).
        end = rospy.Time.now() + rospy.Duration(15.0)
        while not all(sub.get_num_connections() for sub in self.subs) and rospy.Time.now() < end:
            rospy.sleep(0.05)
        self.assertTrue(all(sub.get_num_connections() for sub in self.subs), "not connected to the relay's outputs")
        for topic, msg in self.messages:
            pubs[topic].publish(msg)
            rospy.sleep(0.002)
        cam_of = {"/" + c.namespace + "/tags": c for c in self.ring.cameras}
        for topic in topics:
            cam = cam_of[topic]
            sent = [m for t, m in self.messages if t == topic]
            got = self._wait(cam.name, len(sent))
            self.assertEqual(len(got), len(sent), f"{cam.name}: {len(got)} of {len(sent)} relayed")
            for s, g in zip(sent, got):
                self.assertEqual(g.header.stamp, s.header.stamp)
                self.assertEqual(g.header.frame_id, cam.frame_id)
                want = {t.id: np.array([[c.x, c.y] for c in t.corners])[list(APRILTAG_TO_ARUCO)]
                        for t in s.apriltags if t.id != 30}               # 30 is in ignore_fiducials
                have = {f.fiducial_id: np.array([[f.x0, f.y0], [f.x1, f.y1], [f.x2, f.y2], [f.x3, f.y3]])
                        for f in g.fiducials}
                self.assertEqual(sorted(have), sorted(want))
                for i in want:
                    np.testing.assert_allclose(have[i], want[i], atol=1e-4)

    def test_2_apriltag_ros_poses_become_projected_corners(self):
        cam = self.ring["cam2"]
        classes = message_classes(APRILTAG_ROS_TYPE, apriltag_ros_definition())
        pub = self._publisher("/" + cam.namespace + "/tag_detections", classes["apriltag_ros/AprilTagDetectionArray"])
        msg = classes["apriltag_ros/AprilTagDetectionArray"]()
        msg.header.stamp = rospy.Time(1234, 5000)
        msg.header.frame_id = "whatever_the_camera_calls_itself"
        T = geo.make_transform(geo.rotation_from_rvec([np.pi, 0.0, 0.0]), [0.1, -0.05, 1.5])
        det = classes["apriltag_ros/AprilTagDetection"]()
        det.id, det.size = [17], [0.15]
        det.pose.header = msg.header
        p = det.pose.pose.pose
        p.position.x, p.position.y, p.position.z = (float(v) for v in T[:3, 3])
        p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (float(v) for v in
                                                                             geo.quaternion_from_matrix(T))
        msg.detections = [det]
        before = len(self._wait(cam.name, 0, timeout=0.1))
        pub.publish(msg)
        got = self._wait(cam.name, before + 1)
        self.assertEqual(len(got), before + 1, "the apriltag_ros message was not relayed")
        self.assertEqual(got[-1].header.frame_id, cam.frame_id)
        f = got[-1].fiducials
        self.assertEqual([x.fiducial_id for x in f], [17])
        corners = np.array([[f[0].x0, f[0].y0], [f[0].x1, f[0].y1], [f[0].x2, f[0].y2], [f[0].x3, f[0].y3]])
        want = cam.model.project(geo.transform_points(T, marker_corners(0.15)))   # the ring's intrinsics
        np.testing.assert_allclose(corners, want, atol=1e-3)

    def test_3_a_message_of_another_type_is_dropped_and_the_relay_lives_on(self):
        from std_msgs.msg import String

        cam = self.ring["cam1"]
        pub = self._publisher("/" + cam.namespace + "/tags", String)
        before = len(self._wait(cam.name, 0, timeout=0.1))
        pub.publish(String(data="not a detection"))
        rospy.sleep(1.0)
        self.assertEqual(len(self._wait(cam.name, 0, timeout=0.1)), before)
        pub.unregister()
        tags = self._publisher("/" + cam.namespace + "/tags", self.tag_class)
        topic, msg = next((t, m) for t, m in self.messages if t == "/" + cam.namespace + "/tags")
        tags.publish(msg)
        self.assertEqual(len(self._wait(cam.name, before + 1)), before + 1, "the relay stopped after a bad message")


if __name__ == "__main__":
    rostest.rosrun(PKG, "apriltag_relay", ApriltagRelayTest)
