"""Plays the simulated ring (corners mode) into a running localizer with faults injected.

Used by the fault-injection rostests (test/integration/faults_*_rostest.py) and tools/soak.py.
It owns ``/clock`` (``use_sim_time``) and publishes per camera ``<ns>/camera_info`` and
``<ns>/fiducial_vertices`` from :class:`RingSimulator` (true rig = the ring file with a seeded
2 mm / 0.2 deg calibration error) at ``rate_hz`` frames per simulated second, paced in wall time
(the ring assembler's timeout is wall time). The faults of a :class:`faults.FaultSchedule` are
applied frame by frame. It records what the localizer says: ``~pose`` (with the truth at the
same stamp), ``/diagnostics`` and ``/rosout`` lines of the localizer.
"""
from __future__ import annotations

import os
import sys
import threading
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import rospy
from diagnostic_msgs.msg import DiagnosticArray
from fiducial_msgs.msg import FiducialArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from rosgraph_msgs.msg import Clock, Log
from sensor_msgs.msg import CameraInfo

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.ring import CameraRing  # noqa: E402
from aruco_ring_localization.ros.conversions import model_to_camera_info, observations_to_fiducials  # noqa: E402
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring  # noqa: E402
from aruco_ring_localization.simulation.scene import Scene  # noqa: E402

from faults import FaultSchedule, Phase, corrupt, silence  # noqa: E402


@dataclass
class PoseRecord:
    """One ~pose message: sim stamp, the phase, (x, y, yaw), the truth, std x/y (m) and yaw (rad)."""

    stamp: float
    phase: str
    t: float
    pose: np.ndarray
    truth: Optional[np.ndarray]
    std_xy: float
    std_yaw: float

    @property
    def error(self) -> float:
        return float("nan") if self.truth is None else float(np.hypot(*(self.pose[:2] - self.truth[:2])))


@dataclass
class DiagRecord:
    t: float          # player time (s from the start) when received
    phase: str
    silent: List[str]  # cameras the diagnostics call not alive
    values: Dict[str, str]


class FaultPlayer:
    """See module docstring. ``path(t)`` gives the robot's true (x, y, yaw) at player time t."""

    def __init__(self, path: Callable[[float], np.ndarray], schedule: FaultSchedule, ring_file: str,
                 t0: float = 100.0, rate_hz: float = 10.0, seed: int = 0, node: str = "/localizer",
                 pixel_noise: float = 0.3):
        self.scene = Scene.default()
        self.ring = CameraRing.load(ring_file)
        self.sim = RingSimulator(self.scene, perturb_ring(self.ring, seed=seed), pixel_noise=pixel_noise, seed=seed + 1)
        self.mapped = self.scene.marker_ids
        self.sizes = {m.marker_id: m.size for m in self.scene.markers}
        self.path = path
        self.schedule = schedule
        self.t0 = t0
        self.rate_hz = rate_hz
        self.rng = np.random.default_rng(seed + 2)
        self.node = node
        self.lock = threading.Lock()
        self.truth: Dict[int, np.ndarray] = {}
        self.stamp_phase: Dict[int, Tuple[str, float]] = {}
        self.poses: List[PoseRecord] = []
        self.diags: List[DiagRecord] = []
        self.logs: List[Tuple[float, int, str]] = []
        self.injected: Dict[str, int] = {}
        self.t_now = 0.0
        self.phase_now = ""
        self.clock_pub = rospy.Publisher("/clock", Clock, queue_size=10)
        self.fv_pubs = {c.name: rospy.Publisher(f"{c.namespace}/fiducial_vertices", FiducialArray, queue_size=10)
                        for c in self.ring.cameras}
        self.ci_pubs = {c.name: rospy.Publisher(f"{c.namespace}/camera_info", CameraInfo, queue_size=2)
                        for c in self.ring.cameras}
        rospy.Subscriber(f"{node}/pose", PoseWithCovarianceStamped, self._on_pose, queue_size=100)
        rospy.Subscriber("/diagnostics", DiagnosticArray, self._on_diag, queue_size=20)
        rospy.Subscriber("/rosout", Log, self._on_log, queue_size=200)

    # --- recording ---------------------------------------------------------------------------

    @staticmethod
    def _key(stamp: float) -> int:
        return int(round(stamp * 1000))

    def _on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        q = msg.pose.pose.orientation
        yaw = np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        stamp = msg.header.stamp.to_sec()
        cov = msg.pose.covariance
        with self.lock:
            k = self._key(stamp)
            phase, t = self.stamp_phase.get(k, (self.phase_now, self.t_now))
            self.poses.append(PoseRecord(stamp, phase, t, np.array([msg.pose.pose.position.x,
                                                                  msg.pose.pose.position.y, yaw]),
                                         self.truth.get(k), float(np.sqrt(max(cov[0], cov[7]))),
                                         float(np.sqrt(cov[35]))))

    def _on_diag(self, msg: DiagnosticArray) -> None:
        silent, values = [], {}
        for s in msg.status:
            if "camera" in s.name and s.hardware_id:
                kv = {v.key: v.value for v in s.values}
                if kv.get("alive") == "False":
                    silent.append(s.hardware_id)
            elif "filter" in s.name:
                values = {v.key: v.value for v in s.values}
                values["_message"] = s.message
                values["_level"] = str(s.level)
        if not values and not silent:
            return
        with self.lock:
            self.diags.append(DiagRecord(self.t_now, self.phase_now, sorted(silent), values))

    def _on_log(self, msg: Log) -> None:
        if msg.name.rstrip("/").endswith(self.node.strip("/")):
            with self.lock:
                self.logs.append((self.t_now, int(msg.level), msg.msg))

    # --- playing -----------------------------------------------------------------------------

    def wait_for_subscribers(self, timeout: float = 20.0) -> bool:
        for _ in range(int(timeout * 10)):
            if all(p.get_num_connections() > 0 for p in self.fv_pubs.values()):
                return True
            rospy.rostime.wallsleep(0.1)
        return False

    def true_pose(self, t: float, phase: Phase) -> np.ndarray:
        p = np.array(self.path(t), dtype=float)
        if phase.teleport is not None:
            p = p + np.asarray(phase.teleport)
            p[2] = geo.wrap_angle(p[2])
        return p

    def play(self, t_start: float = 0.0, t_end: Optional[float] = None, speed: float = 1.0) -> None:
        """Publish frames for player times [t_start, t_end) (default: the whole schedule).

        ``speed``: simulated seconds per wall second (the pacing; the stamps are unchanged).
        """
        t_end = self.schedule.duration if t_end is None else t_end
        n = int(round((t_end - t_start) * self.rate_hz))
        for k in range(n):
            t = t_start + k / self.rate_hz
            phase = self.schedule.at(t)
            stamp = self.t0 + t + phase.time_offset
            pose = self.true_pose(t, phase)
            with self.lock:
                self.t_now, self.phase_now = t, phase.name
                self.truth[self._key(stamp)] = pose
                self.stamp_phase[self._key(stamp)] = (phase.name, t)
            ros_stamp = rospy.Time.from_sec(stamp)
            self.clock_pub.publish(Clock(clock=ros_stamp))
            frame = self.sim.observe(self.scene.T_world_base(pose), stamp)
            if phase.corrupt_rate > 0:
                frame, counts = corrupt(frame, self.ring, self.mapped, self.sizes, phase.corrupt_rate, self.rng)
                for kind, c in counts.items():
                    self.injected[kind] = self.injected.get(kind, 0) + c
            frame = silence(frame, phase.silent)
            for name, cf in frame.cameras.items():
                cam = self.ring[name]
                if name not in phase.no_camera_info:
                    info = model_to_camera_info(cam.model, cam.frame_id)
                    info.header.stamp = ros_stamp
                    self.ci_pubs[name].publish(info)
                msg = FiducialArray()
                msg.header.stamp = ros_stamp
                msg.header.frame_id = f"{cam.frame_id}_unknown" if name in phase.wrong_frame else cam.frame_id
                msg.fiducials = observations_to_fiducials(cf.observations)
                self.fv_pubs[name].publish(msg)
            rospy.rostime.wallsleep(1.0 / (self.rate_hz * speed))

    # --- queries ---------------------------------------------------------------------------------

    def poses_in(self, phase: str, after: float = 0.0) -> List[PoseRecord]:
        """Poses of a phase whose stamp lies at least ``after`` s into it."""
        p = next(x for x in self.schedule.phases if x.name == phase)
        with self.lock:
            return [r for r in self.poses if r.phase == phase and r.t >= p.start + after]

    def diags_in(self, phase: str, after: float = 0.0) -> List[DiagRecord]:
        p = next(x for x in self.schedule.phases if x.name == phase)
        with self.lock:
            return [d for d in self.diags if p.start + after <= d.t < p.end]

    def summary(self) -> Dict[str, object]:
        """Per phase: poses, max/median position error (cm), std x/y at start and end (m); injected faults."""
        out: Dict[str, object] = {"injected": dict(self.injected), "phases": {}}
        for ph in self.schedule.phases:
            poses = self.poses_in(ph.name)
            errs = [r.error for r in poses if np.isfinite(r.error)]
            out["phases"][ph.name] = {  # type: ignore[index]
                "duration_s": ph.duration, "poses": len(poses),
                "max_err_cm": round(100 * max(errs), 2) if errs else None,
                "median_err_cm": round(100 * float(np.median(errs)), 2) if errs else None,
                "std_xy_first_m": round(poses[0].std_xy, 4) if poses else None,
                "std_xy_last_m": round(poses[-1].std_xy, 4) if poses else None,
                "silent_in_diagnostics": self.diags_in(ph.name)[-1].silent if self.diags_in(ph.name) else None}
        if self.diags:
            out["last_filter_diagnostics"] = self.diags[-1].values
        return out

    def write_summary(self, path: str, extra: Optional[Dict[str, object]] = None) -> None:
        import json

        data = self.summary()
        data.update(extra or {})
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as handle:
            json.dump(data, handle, indent=1, default=str)

    def logs_matching(self, text: str, t_from: float = -1e9, t_to: float = 1e9) -> List[Tuple[float, int, str]]:
        with self.lock:
            return [x for x in self.logs if text in x[2] and t_from <= x[0] < t_to]
