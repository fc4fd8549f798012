#!/usr/bin/env python3
"""Fault-injection relay: ``<in_ns>/<camera ns>/{fiducial_vertices,camera_info}`` -> ``<camera ns>/...``.

It sits between the simulator node (or the detectors, or a bag) and the localizer/mapper and
applies the message faults of test/faults/faults.py to the messages in flight: cameras silenced
(nothing relayed), a fraction of detections corrupted (swapped id, flipped IPPE solution, random
quad), camera_info withheld, a frame_id that has no tf. Which faults apply is decided per message
from its stamp, so every fault is exactly timed in simulated time.

* :class:`FaultRelay` — in a test node (the fault rostests): ``faults_at(stamp)`` returns the
  :class:`faults.Phase` in force; the relay counts what it injected.
* ``main()`` — a standalone node with fixed faults, for a live system::

    rosrun aruco_ring_localization fault_relay.py _in_ns:=raw _silent:="cam0 cam3" \\
        _corrupt_rate:=0.1 _no_camera_info:=cam7 _wrong_frame:=cam5 _seed:=0

  Private parameters (read once): ``ring_file`` (default: the package's config/ring.yaml),
  ``in_ns`` (default ``raw``), ``silent``, ``no_camera_info``, ``wrong_frame`` (camera names, space
  or comma separated), ``corrupt_rate`` (fraction), ``seed``.
"""
from __future__ import annotations

import os
import sys
import threading
from typing import Callable, Dict, Optional, Sequence

import numpy as np
import rospy
from fiducial_msgs.msg import FiducialArray
from sensor_msgs.msg import CameraInfo

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from aruco_ring_localization.detections import CameraFrame, RingFrame  # noqa: E402
from aruco_ring_localization.ring import CameraRing  # noqa: E402
from aruco_ring_localization.ros.conversions import (fiducial_array_to_observations,  # noqa: E402
                                                     observations_to_fiducials, stamp_to_sec)

from faults import Phase, corrupt  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


class FaultRelay:
    """Relays every camera of ``ring`` from ``<in_ns>/<ns>`` to ``<ns>``, with the faults in force.

    Args:
        ring: the ring file (camera names and namespaces; models for the IPPE flip).
        faults_at: stamp (s) -> the :class:`faults.Phase` whose faults apply to that message.
        in_ns: namespace the incoming topics are under.
        mapped_ids, sizes: marker ids a swapped id is drawn from; marker sizes (m) for the flip.
        seed: corruption seed; each (camera, stamp) draws from its own generator, so what is
            injected does not depend on the order the messages arrive in.
    """

    def __init__(self, ring: CameraRing, faults_at: Callable[[float], Phase], in_ns: str = "raw",
                 mapped_ids: Sequence[int] = tuple(range(1000)), sizes: Optional[Dict[int, float]] = None,
                 seed: int = 0):
        self.ring = ring
        self.faults_at = faults_at
        self.mapped = list(mapped_ids)
        self.sizes = dict(sizes or {})
        self.seed = int(seed)
        self.injected: Dict[str, int] = {}
        self._lock = threading.Lock()
        self._subs = []
        for k, cam in enumerate(ring.cameras):
            ns = cam.namespace.strip("/")
            pub_fv = rospy.Publisher(f"{ns}/fiducial_vertices", FiducialArray, queue_size=10)
            pub_ci = rospy.Publisher(f"{ns}/camera_info", CameraInfo, queue_size=5)
            self._subs.append(rospy.Subscriber(f"{in_ns}/{ns}/fiducial_vertices", FiducialArray, self._on_fiducials,
                                               callback_args=(k, cam.name, pub_fv), queue_size=10))
            self._subs.append(rospy.Subscriber(f"{in_ns}/{ns}/camera_info", CameraInfo, self._on_camera_info,
                                               callback_args=(cam.name, pub_ci), queue_size=5))

    def connected(self) -> bool:
        """True when every incoming topic has a publisher."""
        return all(s.get_num_connections() > 0 for s in self._subs)

    def _on_fiducials(self, msg: FiducialArray, args) -> None:
        index, name, pub = args
        stamp = stamp_to_sec(msg.header.stamp)
        phase = self.faults_at(stamp)
        if name in phase.silent:
            return
        if phase.corrupt_rate > 0:
            frame = RingFrame(stamp, {name: CameraFrame(name, stamp, fiducial_array_to_observations(msg))})
            rng = np.random.default_rng([self.seed, index, int(round(stamp * 1000))])
            frame, counts = corrupt(frame, self.ring, self.mapped, self.sizes, phase.corrupt_rate, rng)
            msg.fiducials = observations_to_fiducials(frame.cameras[name].observations)
            with self._lock:
                for kind, c in counts.items():
                    self.injected[kind] = self.injected.get(kind, 0) + c
        if name in phase.wrong_frame:
            msg.header.frame_id = f"{msg.header.frame_id}_unknown"
        pub.publish(msg)

    def _on_camera_info(self, msg: CameraInfo, args) -> None:
        name, pub = args
        phase = self.faults_at(stamp_to_sec(msg.header.stamp))
        if name in phase.silent or name in phase.no_camera_info:
            return
        pub.publish(msg)


def _names(value) -> tuple:
    return tuple(str(value).replace(",", " ").split())


def main() -> None:
    rospy.init_node("fault_relay")
    ring = CameraRing.load(rospy.get_param("~ring_file", os.path.join(REPO, "config", "ring.yaml")))
    faults = Phase("relay", 0.0, float("inf"), silent=_names(rospy.get_param("~silent", "")),
                   corrupt_rate=float(rospy.get_param("~corrupt_rate", 0.0)),
                   no_camera_info=_names(rospy.get_param("~no_camera_info", "")),
                   wrong_frame=_names(rospy.get_param("~wrong_frame", "")))
    in_ns = str(rospy.get_param("~in_ns", "raw")).strip("/")
    FaultRelay(ring, lambda _stamp: faults, in_ns=in_ns, seed=int(rospy.get_param("~seed", 0)))
    rospy.loginfo("fault_relay: %s/<camera> -> <camera>: silent %s, corrupt %.0f%%, no camera_info %s, "
                  "wrong frame_id %s", in_ns, list(faults.silent) or "none", 100 * faults.corrupt_rate,
                  list(faults.no_camera_info) or "none", list(faults.wrong_frame) or "none")
    rospy.spin()


if __name__ == "__main__":
    main()
