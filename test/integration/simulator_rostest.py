#!/usr/bin/env python3
"""rostest node for simulator.test: the simulator node's outputs against the simulation core.

The simulator (corners mode, sim time, driving the test positions) publishes detections, ground
truth, odometry, scan and its waypoint index; this node rebuilds the same true rig from the seed
and checks, message by message, that each camera's FiducialArray holds exactly the markers
visible from the ground-truth pose of the same stamp with corners within the pixel noise, and the
other outputs against the scene. An image-mode simulator in namespace ``img`` (2 cameras) is
checked for well-formed mono8 images in which the package's detector finds the visible markers.
"""
from __future__ import annotations

import os
import threading
import time
import unittest

import numpy as np
import rospkg
import rospy
import rostest
import tf2_ros
from fiducial_msgs.msg import FiducialArray
from geometry_msgs.msg import Pose2D, PoseArray, PoseStamped, Twist
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, Image, LaserScan
from std_msgs.msg import Int32

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.detection import Detector
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.ros.conversions import (fiducial_array_to_observations, msg_to_transform,
                                                      pose_msg_to_transform, stamp_to_sec)
from aruco_ring_localization.simulation.laser import LaserScanner
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene

PKG = "aruco_ring_localization"
IMG_CAMERAS = ("cam2", "cam6")
PIXEL_NOISE = 0.3


class SimulatorTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("simulator_rostest")
        root = rospkg.RosPack().get_path(PKG)
        cls.scene = Scene.load(os.path.join(root, "config", "lab_scene.yaml"))
        cls.ring = CameraRing.load(os.path.join(root, "config", "ring.yaml"))
        cls.seed = int(rospy.get_param("~seed", 5))
        cls.rate = float(rospy.get_param("~rate", 10.0))
        cls.sim = RingSimulator(cls.scene, perturb_ring(cls.ring, seed=cls.seed), seed=cls.seed)
        cls.lock = threading.Lock()
        cls.msgs = {}
        cls.tf_buffer = tf2_ros.Buffer(cache_time=rospy.Duration(600.0))
        cls.tf_listener = tf2_ros.TransformListener(cls.tf_buffer)
        for cam in cls.ring.cameras:
            rospy.Subscriber(f"{cam.namespace}/fiducial_vertices", FiducialArray, cls._keep, callback_args=cam.name)
            rospy.Subscriber(f"{cam.namespace}/camera_info", CameraInfo, cls._keep, callback_args=cam.name + "/info")
        for name in IMG_CAMERAS:
            ns = cls.ring[name].namespace
            rospy.Subscriber(f"img/{ns}/image_raw", Image, cls._keep, callback_args=name + "/image",
                             queue_size=2, buff_size=2 ** 24)
            rospy.Subscriber(f"img/{ns}/camera_info", CameraInfo, cls._keep, callback_args=name + "/img_info")
        for topic, typ in (("sim/ground_truth", PoseStamped), ("sim/at_waypoint", Int32), ("odom", Odometry),
                           ("scan", LaserScan), ("cmd_vel", Twist), ("img/sim/ground_truth", PoseStamped),
                           ("sim/waypoints", PoseArray)):
            rospy.Subscriber(topic, typ, cls._keep, callback_args=topic)

    @classmethod
    def _keep(cls, msg, key):
        with cls.lock:
            cls.msgs.setdefault(key, []).append(msg)
            if key == "sim/at_waypoint":
                # The simulator publishes the ground truth just before the waypoint index of the
                # same step; while a pose is held the robot is at rest, so the latest truth is it.
                gts = cls.msgs.get("sim/ground_truth")
                cls.msgs.setdefault("held", []).append((msg.data, gts[-1] if gts else None))

    def _get(self, key):
        with self.lock:
            return list(self.msgs.get(key, []))

    def _wait_for(self, condition, what: str, timeout: float = 60.0):
        """Wait (wall time: the simulated clock may run at any speed) until ``condition()`` is true."""
        end = time.monotonic() + timeout
        while not rospy.is_shutdown() and time.monotonic() < end:
            if condition():
                return
            time.sleep(0.05)
        with self.lock:
            counts = {k: len(v) for k, v in self.msgs.items()}
        why = "rospy shut down" if rospy.is_shutdown() else f"timed out after {timeout:.0f} s"
        self.fail(f"{why} waiting for {what}; messages so far: {counts}")

    def _truth_by_stamp(self):
        return {round(stamp_to_sec(m.header.stamp), 6): pose_msg_to_transform(m.pose)
                for m in self._get("sim/ground_truth")}

    # --- corners mode ------------------------------------------------------------------------------

    def test_1_fiducial_arrays_are_the_visible_markers_at_the_true_pose(self):
        names = self.ring.names
        self._wait_for(lambda: all(len(self._get(n)) >= 30 for n in names), "30 FiducialArrays per camera")
        truth = self._truth_by_stamp()
        errors, checked, seen_ids = [], 0, set()
        for name in names:
            for msg in self._get(name)[:60]:
                self.assertEqual(msg.header.frame_id, self.ring[name].frame_id)
                t = round(stamp_to_sec(msg.header.stamp), 6)
                if t not in truth:      # published before our ground-truth subscription connected
                    continue
                expected = dict(self.sim.visible_camera(truth[t], name))
                found = {o.marker_id: o.corners for o in fiducial_array_to_observations(msg)}
                self.assertEqual(sorted(found), sorted(expected), f"{name} at t={t}: published ids vs visible")
                for i, c in expected.items():
                    errors.append(found[i] - c)
                    seen_ids.add(i)
                checked += 1
        self.assertGreater(checked, 100, f"only {checked} arrays had a ground truth with the same stamp")
        e = np.concatenate(errors).ravel()
        self.assertGreater(len(seen_ids), 6, f"only markers {sorted(seen_ids)} seen over {checked} arrays")
        std, worst = float(np.std(e)), float(np.abs(e).max())
        self.assertTrue(0.6 * PIXEL_NOISE < std < 1.4 * PIXEL_NOISE,
                        f"corner noise std {std:.3f} px over {e.size} coordinates (expected {PIXEL_NOISE})")
        self.assertLess(worst, 6 * PIXEL_NOISE, f"worst corner offset {worst:.2f} px")
        self.assertLess(abs(float(np.mean(e))), 0.05, f"corner noise mean {np.mean(e):+.3f} px")

    def test_2_camera_info_is_the_ring_calibration(self):
        self._wait_for(lambda: all(self._get(n + "/info") for n in self.ring.names), "camera_info of every camera")
        for cam in self.ring.cameras:
            info = self._get(cam.name + "/info")[-1]
            self.assertEqual(info.header.frame_id, cam.frame_id)
            self.assertEqual((info.width, info.height), (cam.model.width, cam.model.height))
            self.assertTrue(np.allclose(np.reshape(info.K, (3, 3)), cam.model.K), f"{cam.name}: K")
            self.assertTrue(np.allclose(np.ravel(info.D), np.ravel(cam.model.D)), f"{cam.name}: D")

    def test_3_no_frame_is_dropped_on_the_simulated_clock(self):
        self._wait_for(lambda: len(self._get("cam0")) >= 30, "30 arrays on cam0")
        stamps = np.array([stamp_to_sec(m.header.stamp) for m in self._get("cam0")])
        steps = np.diff(stamps) * self.rate          # in frames
        # The clock advances by exactly one frame per step; a message may still be lost in transport
        # on a loaded machine (then a step of 2 frames), but never a fraction of a frame.
        self.assertTrue(np.allclose(steps, np.round(steps), atol=1e-4) and steps.min() >= 1 - 1e-4,
                        f"stamp steps {np.unique(np.round(steps, 4))} frames of {1.0 / self.rate} s")
        one = float(np.mean(np.isclose(steps, 1.0, atol=1e-4)))
        self.assertGreater(one, 0.9, f"only {one:.0%} of consecutive arrays are one frame apart")

    def test_4_drives_to_the_test_positions_and_holds_them(self):
        self._wait_for(lambda: any(k >= 1 for k, _ in self._get("held")), "holding test position 2",
                       timeout=90.0)
        held = self._get("held")
        self.assertIn(-1, [k for k, _ in held], "never moving between waypoints")
        self.assertTrue(self._get("cmd_vel"), "no cmd_vel while the waypoint driver drove")
        for k, gt in held:
            if k < 0 or gt is None:
                continue
            x, y, _ = geo.se2_from_transform(pose_msg_to_transform(gt.pose))
            goal = self.scene.test_positions[k]
            err = float(np.hypot(x - goal[0], y - goal[1]))
            self.assertLess(err, 0.01, f"holding waypoint {k} {err * 100:.2f} cm from test position {k + 1}")

    def test_4b_odometry_drifts_a_little_from_the_truth(self):
        self._wait_for(lambda: len(self._get("odom")) >= 100, "100 odometry messages", timeout=90.0)
        truth = self._truth_by_stamp()
        start = self.scene.T_world_base(self.scene.mapping_pose)
        worst, travelled = 0.0, 0.0
        for odom in self._get("odom"):
            t = round(stamp_to_sec(odom.header.stamp), 6)
            if t not in truth:
                continue
            self.assertEqual((odom.header.frame_id, odom.child_frame_id), ("odom", "base_link"))
            T_true = geo.inverse(start) @ truth[t]          # odom starts at the start pose
            T_odom = pose_msg_to_transform(odom.pose.pose)
            worst = max(worst, float(np.linalg.norm(T_odom[:2, 3] - T_true[:2, 3])))
            travelled = max(travelled, float(np.linalg.norm(T_true[:2, 3])))
        self.assertGreater(travelled, 0.3, f"the robot moved only {travelled:.2f} m")
        self.assertLess(worst, 0.02 + 0.05 * travelled,
                        f"odometry {worst * 100:.1f} cm from the truth after up to {travelled:.2f} m")

    def test_5_tf_tree_matches_the_topics(self):
        self._wait_for(lambda: len(self._get("sim/ground_truth")) >= 20, "20 ground-truth poses")
        gt = self._get("sim/ground_truth")[-10]
        self.assertEqual(gt.header.frame_id, "world")
        try:
            tfm = self.tf_buffer.lookup_transform("world", "sim_ground_truth", gt.header.stamp, rospy.Duration(5.0))
            odom_tf = self.tf_buffer.lookup_transform("odom", "base_link", gt.header.stamp, rospy.Duration(5.0))
        except (tf2_ros.LookupException, tf2_ros.ExtrapolationException, tf2_ros.ConnectivityException) as exc:
            self.fail(f"tf lookup failed: {exc}")
        dt, dr = geo.pose_distance(msg_to_transform(tfm.transform), pose_msg_to_transform(gt.pose))
        self.assertLess(dt, 1e-6, f"tf world -> sim_ground_truth {dt} m from sim/ground_truth")
        self.assertLess(dr, 1e-6)
        self.assertTrue(np.isfinite(msg_to_transform(odom_tf.transform)).all())

    def test_6_scan_sees_the_walls_from_the_true_pose(self):
        self._wait_for(lambda: len(self._get("scan")) >= 5, "5 scans")
        truth = self._truth_by_stamp()
        scan = self._get("scan")[-3]
        t = round(stamp_to_sec(scan.header.stamp), 6)
        self.assertIn(t, truth)
        r = np.asarray(scan.ranges)
        laser = LaserScanner(self.scene.obstacle_segments(), beams=r.size, noise_std=0.0)
        self.assertAlmostEqual(scan.angle_min, laser.angle_min, places=6)
        self.assertAlmostEqual(scan.angle_increment, laser.angle_increment, places=6)
        expected = laser.scan(geo.se2_from_transform(truth[t]))
        diff = np.abs(r - expected)
        self.assertTrue(np.all(np.isfinite(r)), "the closed room returns every beam")
        self.assertLess(float(np.median(diff)), 0.03, f"scan vs walls: median difference {np.median(diff):.3f} m")
        self.assertTrue(np.all((r > scan.range_min) & (r < scan.range_max)))

    # --- image mode (2 cameras) --------------------------------------------------------------------

    def test_7_image_mode_publishes_mono8_images_with_the_visible_markers(self):
        keys = [n + "/image" for n in IMG_CAMERAS] + [n + "/img_info" for n in IMG_CAMERAS]
        self._wait_for(lambda: all(self._get(k) for k in keys), f"images and camera_info on {IMG_CAMERAS}",
                       timeout=90.0)
        self.assertFalse(self._get("img/ring/cam0/image_raw"), "a camera outside ~cameras published")
        T = self.scene.T_world_base(self.scene.mapping_pose)
        detector = Detector()
        for name in IMG_CAMERAS:
            cam = self.ring[name]
            msg = self._get(name + "/image")[-1]
            self.assertEqual((msg.encoding, msg.height, msg.width, msg.step),
                             ("mono8", cam.model.height, cam.model.width, cam.model.width))
            self.assertEqual(msg.header.frame_id, cam.frame_id)
            img = np.frombuffer(msg.data, dtype=np.uint8).reshape(msg.height, msg.width)
            found = {o.marker_id: o.corners for o in detector.detect(img)}
            expected = dict(self.sim.visible_camera(T, name))
            self.assertTrue(expected, f"{name} should see markers from the mapping pose")
            self.assertEqual(sorted(found), sorted(expected), f"{name}: detected vs visible")
            err = max(float(np.abs(found[i] - c).max()) for i, c in expected.items())
            self.assertLess(err, 1.0, f"{name}: worst detected corner {err:.2f} px from the true projection")
            info = self._get(name + "/img_info")[-1]
            self.assertTrue(np.allclose(np.reshape(info.K, (3, 3)), cam.model.K))

    def test_8_waypoint_list_and_teleport(self):
        self._wait_for(lambda: self._get("sim/waypoints"), "the latched sim/waypoints")
        poses = [geo.se2_from_transform(pose_msg_to_transform(p)) for p in self._get("sim/waypoints")[-1].poses]
        self.assertTrue(np.allclose(poses, self.scene.test_positions, atol=1e-9), "sim/waypoints vs test_positions")
        param = rospy.get_param("sim/waypoint_poses")
        self.assertTrue(np.allclose(param, self.scene.test_positions), "sim/waypoint_poses vs test_positions")
        # Kidnap the image-mode robot (holding the mapping pose) and see its ground truth follow.
        pub = rospy.Publisher("img/sim/teleport", Pose2D, queue_size=1, latch=True)
        pub.publish(Pose2D(x=4.3, y=3.8, theta=1.0))

        def moved():
            gts = self._get("img/sim/ground_truth")
            return gts and np.allclose(geo.se2_from_transform(pose_msg_to_transform(gts[-1].pose)),
                                       [4.3, 3.8, 1.0], atol=1e-6)
        self._wait_for(moved, "the image-mode robot at the teleported pose", timeout=30.0)


if __name__ == "__main__":
    rostest.rosrun(PKG, "simulator_outputs", SimulatorTest)
