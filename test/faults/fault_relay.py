#!/usr/bin/env python3
"""Fault-injection relay for a live ring: ``<in_prefix>/camK/fiducial_vertices`` -> ``<out_prefix>/camK/...``.

Put it between the detectors (or the image-mode simulator + detectors, or a bag) and the
localizer/mapper to inject the faults of test/faults/faults.py on real traffic:

    rosrun aruco_ring_localization fault_relay.py _in_prefix:=ring_raw _out_prefix:=ring \\
        _silent:="cam0 cam3" _corrupt_rate:=0.1 _time_offset:=0.0 _seed:=0

Private parameters (read once at start):
    ring_file (str): ring YAML (default: the package's config/ring.yaml).
    in_prefix, out_prefix (str): topic prefixes replacing the ring's ``ring/`` namespace prefix.
    silent (str): cameras whose messages are dropped (space or comma separated).
    corrupt_rate (float): fraction of detections replaced by wrong ones (swapped id, flipped
        IPPE solution, random quad).
    time_offset (float): s added to every stamp (negative: a jump back).
    seed (int): random seed.
camera_info is relayed unchanged (except for silent cameras). Not used by ``make test``: the
rostests drive the same functions from :class:`fault_player.FaultPlayer` for exact timing.
"""
from __future__ import annotations

import os
import sys

import numpy as np
import rospy
from fiducial_msgs.msg import FiducialArray
from sensor_msgs.msg import CameraInfo

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from aruco_ring_localization.detections import CameraFrame, RingFrame  # noqa: E402
from aruco_ring_localization.ring import CameraRing  # noqa: E402
from aruco_ring_localization.ros.conversions import (camera_info_to_model,  # noqa: E402
                                                     fiducial_array_to_observations, observations_to_fiducials)

from faults import corrupt  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


def main() -> None:
    rospy.init_node("fault_relay")
    ring = CameraRing.load(rospy.get_param("~ring_file", os.path.join(REPO, "config", "ring.yaml")))
    in_prefix = rospy.get_param("~in_prefix", "ring_raw").strip("/")
    out_prefix = rospy.get_param("~out_prefix", "ring").strip("/")
    silent = set(str(rospy.get_param("~silent", "")).replace(",", " ").split())
    rate = float(rospy.get_param("~corrupt_rate", 0.0))
    offset = float(rospy.get_param("~time_offset", 0.0))
    rng = np.random.default_rng(int(rospy.get_param("~seed", 0)))
    mapped = list(range(0, 1000))
    models = {}

    def topic(prefix, cam, leaf):
        ns = cam.namespace.strip("/")
        ns = ns[len("ring/"):] if ns.startswith("ring/") else ns
        return f"{prefix}/{ns}/{leaf}" if prefix else f"{ns}/{leaf}"

    for cam in ring.cameras:
        pub_fv = rospy.Publisher(topic(out_prefix, cam, "fiducial_vertices"), FiducialArray, queue_size=10)
        pub_ci = rospy.Publisher(topic(out_prefix, cam, "camera_info"), CameraInfo, queue_size=2)

        def on_fv(msg, cam=cam, pub=pub_fv):
            if cam.name in silent:
                return
            stamp = msg.header.stamp.to_sec() + offset
            frame = RingFrame(stamp, {cam.name: CameraFrame(cam.name, stamp, fiducial_array_to_observations(msg),
                                                            models.get(cam.name))})
            if rate > 0:
                frame, _ = corrupt(frame, ring, mapped, {}, rate, rng)
            msg.header.stamp = rospy.Time.from_sec(max(stamp, 0.0))
            msg.fiducials = observations_to_fiducials(frame.cameras[cam.name].observations)
            pub.publish(msg)

        def on_ci(msg, cam=cam, pub=pub_ci):
            if cam.name in silent:
                return
            try:
                models[cam.name] = camera_info_to_model(msg, cam.name)
            except Exception:  # noqa: BLE001 - relay it anyway: the consumer must cope
                pass
            pub.publish(msg)

        rospy.Subscriber(topic(in_prefix, cam, "fiducial_vertices"), FiducialArray, on_fv, queue_size=10)
        rospy.Subscriber(topic(in_prefix, cam, "camera_info"), CameraInfo, on_ci, queue_size=2)
    rospy.loginfo("fault_relay: %s -> %s, silent %s, corrupt %.0f%%, time offset %.1f s", in_prefix, out_prefix,
                  sorted(silent) or "none", 100 * rate, offset)
    rospy.spin()


if __name__ == "__main__":
    main()
