"""``make demo``: the paper's experiment (§III) end to end on the simulated lab, with the real ROS nodes.

``python -m aruco_ring_localization.ros.demo [--fusion joint|paper] [--method refined|paper]
[--mode corners|images] [--gui] [--out results/demo]``

1. starts its own roscore (a free port, so it never disturbs a running ROS);
2. mapping: ``launch/demo.launch phase:=mapping`` (ring_tf + mapper); this process plays the
   simulated lab: the robot stands at the plate centre (the paper's single placement) and every
   camera's detections (``ring/camK/fiducial_vertices`` + ``camera_info``; in ``--mode images``
   rendered images on ``ring/camK/image_raw`` for the detector nodes) go out with the simulated
   clock; then ``/mapper/save_map`` writes the map;
3. localization: ``demo.launch phase:=localization`` (ring_tf + localizer on the saved map); the
   robot drives through the paper's 15 positions and 8 orientations (``cmd_vel`` published as it
   moves) and holds each stop for a few frames; the localizer's pose at each stop is recorded
   against the simulator's ground truth;
4. report: Table I (x, y, Euclidean error per position, cm), Table II (yaw error per
   orientation, deg), the map error, a one-line summary; under ``--out``: ``summary.json``,
   ``table1.md``/``.csv``, ``table2.md``/``.csv``, ``trajectory_estimate.tum``,
   ``trajectory_truth.tum``, ``map.yaml`` and the figures (``map.png``, ``fig8_positions.png``,
   ``fig9_camera_estimates.png``, ``fig10_orientations.png``).

The comparison is fair: the truth is expressed in the map frame through the TRUE pose of the
map's reference marker and the map's own frame definition
(:func:`evaluation.maps.truth_in_map_frame`); nothing is fitted that could hide an error. The
report itself (tables, summary.json, figures, the console summary) is :mod:`evaluation.report`.

The simulator runs in lockstep with the localizer (each frame waits for the pose it produces, up
to a timeout), so the result does not depend on the machine's speed, only the run time does.
"""
from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .. import geometry as geo
from ..errors import ArucoRingError
from ..evaluation.report import Progress, StopRecord, console_text, interpolate_motion, plan_stops, write_report
from ..marker_map import MarkerMap

logger = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[3]
PACKAGE = "aruco_ring_localization"


# --------------------------------------------------------------------------------------------
# Processes (roscore, roslaunch) owned by the demo
# --------------------------------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return int(s.getsockname()[1])


class RosSession:
    """A roscore on a free port and the roslaunch processes of the demo; stops all of them on exit."""

    def __init__(self, log_dir: Path, progress: Progress) -> None:
        self.log_dir = log_dir
        self.progress = progress
        self.port = _free_port()
        self.procs: List[subprocess.Popen] = []
        self.env = dict(os.environ)
        self.env["ROS_MASTER_URI"] = f"http://localhost:{self.port}"
        self.env["ROS_HOSTNAME"] = "localhost"
        self.env.pop("ROS_IP", None)
        self.env["ROS_LOG_DIR"] = str(log_dir)
        self.env["PYTHONUNBUFFERED"] = "1"

    def __enter__(self) -> "RosSession":
        self.log_dir.mkdir(parents=True, exist_ok=True)
        os.environ.update({k: self.env[k] for k in ("ROS_MASTER_URI", "ROS_HOSTNAME", "ROS_LOG_DIR")})
        os.environ.pop("ROS_IP", None)
        self.core = self.spawn(["roscore", "-p", str(self.port)], "roscore")
        import rosgraph

        deadline = time.monotonic() + 30
        while not rosgraph.Master("/aruco_ring_demo").is_online():
            if time.monotonic() > deadline or self.core.poll() is not None:
                raise RuntimeError(f"roscore did not start on port {self.port} (log: {self.log_dir}/roscore.log)")
            time.sleep(0.2)
        return self

    def spawn(self, cmd: List[str], name: str) -> subprocess.Popen:
        log = open(self.log_dir / f"{name}.log", "w")
        proc = subprocess.Popen(cmd, env=self.env, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
        log.close()
        self.procs.append(proc)
        return proc

    def launch(self, name: str, args: List[str]) -> subprocess.Popen:
        return self.spawn(["roslaunch", PACKAGE, "demo.launch"] + args, name)

    def stop(self, proc: subprocess.Popen, timeout: float = 15.0) -> None:
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGINT)
                proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5)
            except ProcessLookupError:
                pass
        if proc in self.procs:
            self.procs.remove(proc)

    def __exit__(self, *exc) -> None:
        for proc in reversed(list(self.procs)):
            self.stop(proc)


# --------------------------------------------------------------------------------------------
# The simulated lab, played by this process (ROS side)
# --------------------------------------------------------------------------------------------
class LabPlayer:
    """Publishes the simulated ring (corners or images), the truth, /clock and cmd_vel; records our pose."""

    def __init__(self, scene, ring, sim, mode: str, rate_hz: float, seed: int) -> None:
        import rospy
        import tf2_ros
        from fiducial_msgs.msg import FiducialArray
        from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped, Twist
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import CameraInfo, Image

        from .conversions import model_to_camera_info

        self.rospy = rospy
        self.scene, self.ring, self.sim, self.mode = scene, ring, sim, mode
        self.dt = 1.0 / rate_hz
        self.t = 1000.0  # simulated clock, s
        self.rng = np.random.default_rng(seed)
        self.clock = rospy.Publisher("/clock", Clock, queue_size=10)
        self.cmd = rospy.Publisher("/cmd_vel", Twist, queue_size=10)
        self.tf = tf2_ros.TransformBroadcaster()
        self.pubs: Dict[str, Tuple[Any, Any]] = {}
        self.infos = {}
        for cam in ring.cameras:
            data = (rospy.Publisher(f"{cam.namespace}/image_raw", Image, queue_size=2) if mode == "images"
                    else rospy.Publisher(f"{cam.namespace}/fiducial_vertices", FiducialArray, queue_size=10))
            info = rospy.Publisher(f"{cam.namespace}/camera_info", CameraInfo, queue_size=10)
            self.pubs[cam.name] = (data, info)
            self.infos[cam.name] = model_to_camera_info(cam.model, cam.frame_id)
        self._FiducialArray, self._Image, self._Clock, self._Twist = FiducialArray, Image, Clock, Twist
        self.lock = threading.Condition()
        self.poses: Dict[float, np.ndarray] = {}
        self.cam_estimates: Dict[float, np.ndarray] = {}
        self.detections: Dict[str, float] = {}
        rospy.Subscriber("/localizer/pose", PoseWithCovarianceStamped, self._on_pose, queue_size=100)
        rospy.Subscriber("/localizer/camera_estimates", PoseArray, self._on_cams, queue_size=100)
        if mode == "images":
            for cam in ring.cameras:
                rospy.Subscriber(f"{cam.namespace}/fiducial_vertices", FiducialArray, self._on_det,
                                 callback_args=cam.name, queue_size=10)
        self.publish_clock()

    # --- inputs from the nodes ------------------------------------------------------------------
    @staticmethod
    def _yaw(q) -> float:
        return float(np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)))

    def _on_pose(self, msg) -> None:
        p = msg.pose.pose
        with self.lock:
            self.poses[round(msg.header.stamp.to_sec(), 6)] = np.array([p.position.x, p.position.y, self._yaw(p.orientation)])
            self.lock.notify_all()

    def _on_cams(self, msg) -> None:
        arr = np.array([[p.position.x, p.position.y, self._yaw(p.orientation)] for p in msg.poses]).reshape(-1, 3)
        with self.lock:
            self.cam_estimates[round(msg.header.stamp.to_sec(), 6)] = arr

    def _on_det(self, msg, name) -> None:
        with self.lock:
            self.detections[name] = msg.header.stamp.to_sec()
            self.lock.notify_all()

    # --- outputs --------------------------------------------------------------------------------
    def publish_clock(self) -> None:
        self.clock.publish(self._Clock(clock=self.rospy.Time.from_sec(self.t)))

    def wait_for(self, topic_suffix_subscribers: str, timeout: float = 30.0) -> bool:
        """Wait until every camera's data topic has a subscriber (the nodes are up)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if all(p[0].get_num_connections() > 0 for p in self.pubs.values()):
                return True
            self.publish_clock()
            time.sleep(0.1)
        return False

    def step(self, pose_world: np.ndarray, cmd: Optional[np.ndarray] = None) -> float:
        """Advance the clock by one frame and publish everything for the robot at ``pose_world``."""
        from .conversions import make_transform_stamped, observations_to_fiducials

        rospy = self.rospy
        self.t = round(self.t + self.dt, 6)
        stamp = rospy.Time.from_sec(self.t)
        self.clock.publish(self._Clock(clock=stamp))
        T = geo.transform_from_se2(*pose_world)
        self.tf.sendTransform(make_transform_stamped(T, self.scene.world_frame, "sim_ground_truth", stamp))
        tw = self._Twist()
        if cmd is not None:
            tw.linear.x, tw.linear.y, tw.angular.z = (float(v) for v in cmd)
        self.cmd.publish(tw)
        if self.mode == "images":
            images = self.sim.render(T, rng=self.rng)
            for name, (pub, info_pub) in self.pubs.items():
                info = self.infos[name]
                info.header.stamp = stamp
                info_pub.publish(info)
                img = images[name]
                msg = self._Image()
                msg.header.stamp, msg.header.frame_id = stamp, info.header.frame_id
                msg.height, msg.width = int(img.shape[0]), int(img.shape[1])
                msg.encoding, msg.step = "mono8", int(img.shape[1])
                msg.data = np.ascontiguousarray(img, dtype=np.uint8).tobytes()
                pub.publish(msg)
        else:
            frame = self.sim.observe(T, self.t, rng=self.rng)
            for name, (pub, info_pub) in self.pubs.items():
                info = self.infos[name]
                info.header.stamp = stamp
                info_pub.publish(info)
                msg = self._FiducialArray()
                msg.header.stamp, msg.header.frame_id = stamp, info.header.frame_id
                msg.fiducials = observations_to_fiducials(frame.cameras[name].observations)
                pub.publish(msg)
        return self.t

    def wait_pose(self, stamp: float, timeout: float) -> Optional[np.ndarray]:
        """Our pose at ``stamp`` (waits up to ``timeout`` s wall time), or None."""
        key = round(stamp, 6)
        deadline = time.monotonic() + timeout
        tick = 0.0
        while True:
            with self.lock:
                if key in self.poses:
                    return self.poses[key]
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self.lock.wait(min(left, 0.05))
                if key in self.poses:
                    return self.poses[key]
            # Let the simulated clock creep forward (never reaching the next frame's stamp): the
            # nodes' ROS-time timers (e.g. the ring assembler's flush of incomplete frames) only
            # run while the clock moves, as they would on a robot.
            tick = min(tick + 0.002, 0.4 * self.dt)
            self.clock.publish(self._Clock(clock=self.rospy.Time.from_sec(self.t + tick)))

    def wait_detections(self, stamp: float, timeout: float) -> bool:
        """Image mode: wait until every detector has answered the frame at ``stamp``."""
        deadline = time.monotonic() + timeout
        with self.lock:
            while not all(self.detections.get(c.name, -1.0) >= stamp - 1e-6 for c in self.ring.cameras):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.lock.wait(left)
        return True


# --------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------
def _parse(argv: Optional[Sequence[str]]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m aruco_ring_localization.ros.demo",
                                description="The paper's experiment on the simulated lab with the real ROS nodes.")
    p.add_argument("--fusion", choices=("joint", "paper"), default="joint", help="localizer fusion (default joint)")
    p.add_argument("--method", choices=("refined", "paper"), default="refined", help="map method (default refined)")
    p.add_argument("--mode", choices=("images", "corners"), default=os.environ.get("DEMO_MODE", "auto"),
                   help="images: rendered images through the detector nodes; corners: simulated detections "
                        "(default: images when the detector node exists)")
    p.add_argument("--out", default=str(REPO / "results" / "demo"), help="output directory")
    p.add_argument("--gui", action="store_true", default=os.environ.get("GUI", "") not in ("", "0"),
                   help="also open rviz (needs DISPLAY); GUI=1 in the environment does the same")
    p.add_argument("--rate", type=float, default=5.0, help="simulated frames per simulated second")
    p.add_argument("--mapping-frames", type=int, default=30, help="frames at the mapping pose")
    p.add_argument("--hold-frames", type=int, default=10, help="frames held at each stop")
    p.add_argument("--use-last", type=int, default=4, help="last frames of each stop averaged (median)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.mode == "auto":
        args.mode = "images" if (REPO / "scripts" / "detector").exists() and \
            (REPO / "launch" / "detector.launch").exists() else "corners"
    if args.gui and not os.environ.get("DISPLAY"):
        sys.stdout.write("demo: GUI requested but DISPLAY is not set; running without rviz\n")
        args.gui = False
    return args


def run(args: argparse.Namespace) -> int:
    from ..ring import CameraRing
    from ..simulation.ring_sim import RingSimulator, perturb_ring
    from ..simulation.scene import Scene

    progress = Progress()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    map_file = out / "map.yaml"
    scene = Scene.default()
    ring = CameraRing.load(str(REPO / "config" / "ring.yaml"))
    true_ring = perturb_ring(ring, seed=args.seed)
    sim = RingSimulator(scene, true_ring, pixel_noise=0.3, seed=args.seed + 1)
    progress(f"simulated lab '{scene.name}': {len(scene.markers)} markers, plate {scene.plate.size[0]:.2f} x "
             f"{scene.plate.size[1]:.2f} m; true rig = ring.yaml + 2 mm / 0.2 deg calibration error; mode {args.mode}")
    if args.mode == "images":
        progress("warming up the renderer")
        sim.render(scene.T_world_base(scene.mapping_pose))
    records: List[StopRecord] = []
    traj_est: List[Tuple[float, np.ndarray]] = []
    traj_truth: List[Tuple[float, np.ndarray]] = []
    with RosSession(out / "logs", progress) as ros:
        progress(f"roscore on port {ros.port} (logs: {out / 'logs'})")
        import rospy

        rospy.init_node("aruco_ring_demo", disable_signals=True)
        player = LabPlayer(scene, ring, sim, args.mode, args.rate, args.seed + 2)
        common = [f"map_file:={map_file}", f"gui:={'true' if args.gui else 'false'}"]
        # --- mapping -----------------------------------------------------------------------------
        if args.mode == "images":
            _start_detectors(ros)
        mapping = ros.launch("mapping", ["phase:=mapping", f"method:={args.method}"] + common)
        if not player.wait_for("data", timeout=90):
            raise RuntimeError(f"the {'detectors' if args.mode == 'images' else 'mapper'} did not subscribe "
                               f"(logs: {out / 'logs'})")
        rospy.wait_for_service("/mapper/save_map", timeout=60)
        pose = np.asarray(scene.mapping_pose, dtype=float)
        progress(f"mapping from the plate centre ({pose[0]:.2f}, {pose[1]:.2f}) m: {args.mapping_frames} frames")
        time.sleep(1.0)
        for k in range(args.mapping_frames):
            t = player.step(pose)
            if args.mode == "images":
                player.wait_detections(t, timeout=5.0)
            time.sleep(0.1)
            progress(f"mapping: frame {k + 1}/{args.mapping_frames}", inline=True)
        time.sleep(1.0)
        progress("mapping: /mapper/save_map (bundle adjustment)" if args.method == "refined" else "mapping: /mapper/save_map")
        from std_srvs.srv import Trigger

        rospy.wait_for_service("/mapper/save_map", timeout=30)
        res = rospy.ServiceProxy("/mapper/save_map", Trigger)()
        if not res.success:
            raise RuntimeError(f"save_map failed: {res.message}")
        progress(f"mapping: {res.message}")
        ros.stop(mapping)
        est_map = MarkerMap.load(str(map_file))
        # --- localization --------------------------------------------------------------------------
        loc = ros.launch("localization", ["phase:=localization", f"fusion:={args.fusion}",
                                          f"comparison_dir:={out / 'comparison'}"] + common)
        if not player.wait_for("data", timeout=60):
            raise RuntimeError(f"the localizer did not subscribe (log: {out / 'logs'})")
        rospy.wait_for_service("/localizer/reset", timeout=60)
        time.sleep(1.0)
        stops = plan_stops(scene.test_positions, scene.test_orientations)
        progress(f"localization ({args.fusion} fusion): driving through {sum(s.kind == 'position' for s in stops)} "
                 f"positions and {sum(s.kind == 'orientation' for s in stops)} orientations")
        current = np.asarray(scene.mapping_pose, dtype=float)
        max_wait = 10.0 if args.mode == "images" else 3.0
        latencies: List[float] = []
        missed = 0

        def frame(p, cmd=None) -> float:
            # Lockstep with the localizer: wait for the pose of this frame, but not forever (a
            # dropped frame must not stall the drive); the wait adapts to the observed latency.
            nonlocal missed
            t = player.step(p, cmd)
            traj_truth.append((t, p.copy()))
            wait = min(max_wait, max(0.3, 3.0 * float(np.median(latencies[-20:])))) if latencies else max_wait
            t0 = time.monotonic()
            if player.wait_pose(t, wait) is None:
                missed += 1
            else:
                latencies.append(time.monotonic() - t0)
            return t

        for _ in range(5):  # initialise the filter where mapping left the robot
            frame(current)
        for k, stop in enumerate(stops):
            goal = np.asarray(stop.pose, dtype=float)
            for p, cmd in interpolate_motion(current, goal, player.dt):
                frame(p, cmd)
            rec = StopRecord(stop, goal.copy())
            hold = [frame(goal, np.zeros(3)) for _ in range(args.hold_frames)]
            player.wait_pose(hold[-1], max_wait)  # the stop's last pose, if it is late
            with player.lock:
                rec.estimates = [(t, player.poses[round(t, 6)]) for t in hold if round(t, 6) in player.poses]
                # the per-camera estimates (Fig. 9) of the latest hold frame that has them
                for t in reversed(hold):
                    cams = player.cam_estimates.get(round(t, 6))
                    if cams is not None and len(cams):
                        rec.camera_estimates = list(cams)
                        break
            records.append(rec)
            current = goal
            progress(f"{stop.kind} {stop.label:>2}: truth ({goal[0]:.2f}, {goal[1]:.2f}, {np.degrees(goal[2]):6.1f} deg), "
                     f"{len(rec.estimates)}/{len(hold)} poses [{k + 1}/{len(stops)}]")
        time.sleep(0.5)
        with player.lock:
            traj_est.extend((t, p) for t, p in sorted(player.poses.items()))
        try:  # the comparison node's own tables (live, fitted alignment): a cross-check
            from std_srvs.srv import Trigger as _Trigger

            rospy.wait_for_service("/comparison/write_tables", timeout=5)
            rospy.ServiceProxy("/comparison/write_tables", _Trigger)()
        except (rospy.ROSException, rospy.ServiceException) as exc:
            progress(f"note: no tables from the comparison node ({exc})")
        ros.stop(loc)
        if missed:
            progress(f"note: {missed} frames had no pose before the next frame (late or dropped by the localizer)")
        rospy.signal_shutdown("demo done")
    runtime = progress.elapsed()
    summary = write_report(out, records, est_map, scene.truth_map(), scene, traj_est, traj_truth, args.fusion,
                           args.method, args.mode, runtime)
    sys.stdout.write("\n" + console_text(summary, out))
    return 0


def _start_detectors(ros: RosSession) -> subprocess.Popen:
    """Image mode: the 8 detector nodes (launch/ring_detectors.launch), kept for both phases."""
    return ros.spawn(["roslaunch", PACKAGE, "ring_detectors.launch", "do_pose_estimation:=false"], "detectors")


def main(argv: Optional[Sequence[str]] = None) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    args = _parse(argv)

    def _terminate(signum, _frame):  # so that `timeout`/CI stopping us still stops our roscore and nodes
        raise KeyboardInterrupt(f"signal {signum}")

    signal.signal(signal.SIGTERM, _terminate)
    try:
        return run(args)
    except KeyboardInterrupt:
        sys.stderr.write("demo: interrupted\n")
        return 130
    except (RuntimeError, ArucoRingError) as exc:
        sys.stderr.write(f"demo: error: {exc}\n")
        return 1


if __name__ == "__main__":
    sys.exit(main())
