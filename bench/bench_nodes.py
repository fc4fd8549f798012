"""Whole-process benchmark: the real nodes through a real master, CPU time read from /proc.

What the in-process benchmarks (bench_detector, bench_localization) cannot see: message
(de)serialisation, rospy's threads, tf, timers, diagnostics and the BLAS/OpenCV thread pools of a
node process. This benchmark starts a master and the stock launch files, and plays rendered ring
frames of the simulated lab to them in lockstep:

* pass 1: ``ring_detectors.launch`` (8 ``detector`` nodes) + ``localization.launch`` (``localizer``
  on test/data/lab_truth_map.yaml) under ``use_sim_time``. For each ring frame the player
  publishes /clock, the 8 camera_info and the 8 mono8 1280x960 images, then waits for all 8
  ``fiducial_vertices`` and the ``localizer/pose`` of that stamp (so nothing is dropped, however
  loaded the machine is), reading ``utime + stime`` of every node process in /proc/<pid>/stat
  just before publishing and just after the last answer. The frame is rendered before that
  window, so the player's own work is not charged to the nodes (sim-time timers of the nodes fire
  inside the window, since /clock moves only there).
* pass 2: ``mapping.launch`` (``mapper``) fed the detections recorded in pass 1 (camera_info,
  /clock and the 8 FiducialArrays of each frame) at 10 ring frames per wall second, as live; its
  CPU over the whole pass (live preview timer, progress, tf included) per ring frame.

``--lab harsh`` plays pass 1 on config/lab_harsh.yaml's images instead (as bench/noise_budget.py draws
them: the tilted, bumpy plate, each camera shaken by the ring's vibration, the wandering gain that
saturates the white paper, the uneven light, the pillars; the truth through each camera as it
was); ``run`` (bench/run.py) measures both, the harsh lab right after the kind one, and reports its
detector and localizer figures as the ``_harsh`` keys beside the kind lab's of the same run.

Keys: ``detector_node_cpu_ms_per_image`` (mean over the 8 detectors and the frames),
``localizer_node_cpu_ms_per_ring_frame``, ``mapper_node_cpu_ms_per_ring_frame``, ``ring_10hz_cores``
= (8 x detector + localizer) x 10 Hz; also ``detector_node_detection_rate`` and
``detector_node_corner_err_px_median`` of what the nodes published, against the simulator's truth.
Run alone: ``python bench/bench_nodes.py --frames 30`` (prints the JSON).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from typing import Dict, List, Optional

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
MAP_FILE = os.path.join(ROOT, "test", "data", "lab_truth_map.yaml")
CAMERAS = [f"cam{k}" for k in range(8)]
DT = 0.1  # s of simulated time per ring frame (10 Hz)
TICK = os.sysconf("SC_CLK_TCK")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return int(s.getsockname()[1])


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process, s (fields 14 and 15 of /proc/<pid>/stat)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as handle:
        fields = handle.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


def system_seconds(pid: int) -> float:
    """stime of a process, s (the kernel's share: syscalls, page faults, thread wake-ups)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as handle:
        fields = handle.read().rsplit(")", 1)[1].split()
    return int(fields[12]) / TICK


def threads(pid: int) -> int:
    with open(f"/proc/{pid}/status", encoding="ascii") as handle:
        for line in handle:
            if line.startswith("Threads:"):
                return int(line.split()[1])
    return 0


def _trajectory(scene, n: int):
    """n poses (x, y, yaw) along the lab's test positions at about 0.3 m and 3 deg per frame."""
    import numpy as np

    pts = [np.asarray(p, dtype=float) for p in scene.test_positions]
    out = []
    seg = 0
    pose = pts[0].copy()
    while len(out) < n:
        out.append(pose.copy())
        target = pts[(seg + 1) % len(pts)]
        d = target[:2] - pose[:2]
        dyaw = (target[2] - pose[2] + np.pi) % (2 * np.pi) - np.pi
        dist = float(np.linalg.norm(d))
        step = 1.0
        if dist > 0:
            step = min(step, 0.03 / dist)
        if abs(dyaw) > 0:
            step = min(step, np.radians(3.0) / abs(dyaw))
        pose[:2] += step * d
        pose[2] += step * dyaw
        if step >= 1.0:
            seg += 1
    return out


class _Launch:
    """A roslaunch process (own process group), stopped with SIGINT."""

    def __init__(self, args: List[str], env: dict, log: str):
        self.log = open(log, "w", encoding="utf-8")
        self.proc = subprocess.Popen(["roslaunch", "--wait"] + args, env=env, stdout=self.log,
                                     stderr=subprocess.STDOUT, start_new_session=True)

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self.log.close()


def _node_pid(name: str, timeout: float = 120.0) -> int:
    import rosgraph
    import xmlrpc.client

    master = rosgraph.Master("/bench_player")
    deadline = time.monotonic() + timeout
    while True:
        try:
            uri = master.lookupNode(name)
            code, _msg, pid = xmlrpc.client.ServerProxy(uri).getPid("/bench_player")
            if code == 1:
                return int(pid)
        except Exception:  # noqa: BLE001 - not up yet
            pass
        if time.monotonic() > deadline:
            raise RuntimeError(f"node {name} did not come up within {timeout:.0f} s")
        time.sleep(0.5)


def _wait(cond, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.002)


class _Profiler:
    """``py-spy record`` (raw collapsed stacks) of some node processes, when ``py_spy`` is given."""

    def __init__(self, py_spy: str, out_dir: str):
        self.py_spy, self.out_dir = py_spy, out_dir
        self.procs: List[subprocess.Popen] = []

    def start(self, name: str, pid: int) -> None:
        if not self.py_spy:
            return
        os.makedirs(self.out_dir, exist_ok=True)
        out = os.path.join(self.out_dir, f"{name}.txt")
        self.procs.append(subprocess.Popen([self.py_spy, "record", "--pid", str(pid), "--rate", "250", "--format",
                                            "raw", "--output", out, "--nonblocking"], stdout=subprocess.DEVNULL,
                                           stderr=subprocess.DEVNULL))

    def stop(self) -> None:
        for proc in self.procs:
            proc.send_signal(signal.SIGINT)
        for proc in self.procs:
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
        self.procs = []


def _thread_report(py_spy: str, pid: int, name: str) -> None:
    """CPU seconds of each thread of a process with the Python frame py-spy shows it in (stderr)."""
    per_tid = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            per_tid[int(tid)] = cpu_seconds_task(pid, int(tid))
        except OSError:
            pass
    dump = subprocess.run([py_spy, "dump", "--pid", str(pid)], capture_output=True, text=True).stdout
    where: Dict[int, str] = {}
    tid = None
    for line in dump.splitlines():
        if line.startswith("Thread "):
            parts = line.split()
            try:
                tid = int(parts[1], 16) if parts[1].startswith("0x") else int(parts[1])
            except ValueError:
                tid = None
            # 'Thread 0x7F.. (active): "name"' - the native id is printed in parentheses by newer py-spy
            for p in parts:
                if p.strip("():,").isdigit():
                    tid = int(p.strip("():,"))
            where[tid] = line
        elif tid is not None and where.get(tid, "").startswith("Thread ") and line.strip():
            where[tid] = line.strip()
            tid = None
    sys.stderr.write(f"--- threads of {name} (pid {pid}): CPU s, frame\n")
    for t, c in sorted(per_tid.items(), key=lambda kv: -kv[1])[:15]:
        sys.stderr.write(f"  {t} {c:7.2f}  {where.get(t, '?')}\n")


def cpu_seconds_task(pid: int, tid: int) -> float:
    with open(f"/proc/{pid}/task/{tid}/stat", encoding="ascii") as handle:
        fields = handle.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


def top_functions(raw_file: str, n: int = 12) -> List[str]:
    """Lines 'inclusive % self % function (file:line)' of a py-spy raw (collapsed) profile."""
    inclusive: Dict[str, int] = {}
    own: Dict[str, int] = {}
    total = 0
    with open(raw_file, encoding="utf-8", errors="replace") as handle:
        for line in handle:
            stack, _, count = line.rstrip("\n").rpartition(" ")
            if not stack or not count.isdigit():
                continue
            c = int(count)
            total += c
            frames = stack.split(";")
            for f in set(frames):
                inclusive[f] = inclusive.get(f, 0) + c
            own[frames[-1]] = own.get(frames[-1], 0) + c
    rows = sorted(own.items(), key=lambda kv: -kv[1])[:n]
    return [f"{100.0 * c / max(1, total):5.1f} % self, {100.0 * inclusive[f] / max(1, total):5.1f} % incl  {f}"
            for f, c in rows]


def measure(frames: int, warmup: int, workdir: str, py_spy: str = "", profile_dir: str = "", lab: str = "kind",
            mapper: bool = True) -> dict:
    import numpy as np
    import rospy
    from fiducial_msgs.msg import FiducialArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import CameraInfo, Image

    sys.path.insert(0, os.path.join(ROOT, "src"))
    from aruco_ring_localization.ring import CameraRing
    from aruco_ring_localization.ros.conversions import model_to_camera_info
    from aruco_ring_localization.simulation.scene import Scene

    ring = CameraRing.load(os.path.join(ROOT, "config", "ring.yaml"))
    render = _lab_renderer(lab, ring)
    poses = _trajectory(Scene.default(), warmup + frames)
    saturated_images = 0

    # --- pass 1: detectors + localizer -------------------------------------------------------
    launch_file = os.path.join(workdir, "bench_nodes_pass1.launch")
    with open(launch_file, "w", encoding="utf-8") as handle:
        handle.write(f"""<launch>
  <param name="use_sim_time" value="true"/>
  <include file="$(find aruco_ring_localization)/launch/ring_detectors.launch"/>
  <include file="$(find aruco_ring_localization)/launch/localization.launch">
    <arg name="map_file" value="{MAP_FILE}"/>
  </include>
</launch>
""")
    env = dict(os.environ)
    launch = _Launch([launch_file], env, os.path.join(workdir, "pass1.log"))
    rospy.init_node("bench_player", anonymous=False, disable_signals=True)
    clock_pub = rospy.Publisher("/clock", Clock, queue_size=1)
    infos = {c: model_to_camera_info(ring[c].model, ring[c].frame_id) for c in CAMERAS}
    info_pubs = {c: rospy.Publisher(f"/ring/{c}/camera_info", CameraInfo, queue_size=2) for c in CAMERAS}
    img_pubs = {c: rospy.Publisher(f"/ring/{c}/image_raw", Image, queue_size=1) for c in CAMERAS}
    got: Dict[str, Dict[float, FiducialArray]] = {c: {} for c in CAMERAS}
    poses_got: Dict[float, PoseWithCovarianceStamped] = {}

    def on_vertices(msg, cam):
        got[cam][round(msg.header.stamp.to_sec(), 3)] = msg

    def on_pose(msg):
        poses_got[round(msg.header.stamp.to_sec(), 3)] = msg

    for c in CAMERAS:
        rospy.Subscriber(f"/ring/{c}/fiducial_vertices", FiducialArray, on_vertices, callback_args=c,
                         queue_size=50)
    rospy.Subscriber("/localizer/pose", PoseWithCovarianceStamped, on_pose, queue_size=50)
    profiler = _Profiler(py_spy, profile_dir)
    try:
        pids = {c: _node_pid(f"/ring/{c}/detector") for c in CAMERAS}
        pids["localizer"] = _node_pid("/localizer")
        _wait(lambda: all(p.get_num_connections() > 0 for p in img_pubs.values())
              and all(p.get_num_connections() > 0 for p in info_pubs.values()), 120, "the detectors' subscriptions")
        t0 = 100.0
        clock_pub.publish(Clock(clock=rospy.Time.from_sec(t0 - 1.0)))
        time.sleep(2.0)  # the localizer's tf listener gets ring_tf's static transforms
        cpu = {k: 0.0 for k in pids}
        sys_cpu = {k: 0.0 for k in pids}
        detections = 0
        visible_total = 0
        errors: List[float] = []
        recorded = []
        missing_poses = 0
        for k, pose in enumerate(poses):
            images, visible = render(pose, np.random.default_rng(1000 + k))
            if k >= warmup:
                saturated_images += sum(int(images[c].max() >= 255) for c in CAMERAS)
            t = t0 + DT * k
            stamp = rospy.Time.from_sec(t)
            key = round(t, 3)
            msgs = {}
            for c in CAMERAS:
                img = Image()
                img.header.stamp = stamp
                img.header.frame_id = ring[c].frame_id
                img.height, img.width = images[c].shape
                img.encoding = "mono8"
                img.step = img.width
                img.data = images[c].tobytes()
                msgs[c] = img
            before = {n: cpu_seconds(p) for n, p in pids.items()}
            sys_before = {n: system_seconds(p) for n, p in pids.items()}
            clock_pub.publish(Clock(clock=stamp))
            for c in CAMERAS:
                infos[c].header.stamp = stamp
                info_pubs[c].publish(infos[c])
                img_pubs[c].publish(msgs[c])
            _wait(lambda: all(key in got[c] for c in CAMERAS), 60, f"the detections of frame {k}")
            try:
                _wait(lambda: key in poses_got, 10, f"the localizer's pose of frame {k}")
            except RuntimeError:
                missing_poses += 1
            after = {n: cpu_seconds(p) for n, p in pids.items()}
            sys_after = {n: system_seconds(p) for n, p in pids.items()}
            recorded.append((t, {c: got[c][key] for c in CAMERAS}))
            if k == warmup - 1:
                profiler.start("detector_cam0", pids["cam0"])
                profiler.start("localizer", pids["localizer"])
            if k < warmup:
                continue
            for n in pids:
                cpu[n] += after[n] - before[n]
                sys_cpu[n] += sys_after[n] - sys_before[n]
            for c in CAMERAS:
                found = {f.fiducial_id: f for f in got[c][key].fiducials}
                for marker_id, corners in visible[c]:
                    visible_total += 1
                    f = found.get(marker_id)
                    if f is None:
                        continue
                    detections += 1
                    pts = np.array([[f.x0, f.y0], [f.x1, f.y1], [f.x2, f.y2], [f.x3, f.y3]])
                    errors.extend(np.linalg.norm(pts - corners, axis=1))
        thread_counts = {n: threads(p) for n, p in pids.items()}
        if py_spy:
            for name in ("localizer", "cam0"):
                _thread_report(py_spy, pids[name], name)
    finally:
        profiler.stop()
        launch.stop()

    # --- pass 2: mapper on the recorded detections -----------------------------------------------
    mapper_cpu, mapper_threads = float("nan"), 0
    if not mapper:
        rospy.signal_shutdown("done")
        return _summary(frames, warmup, cpu, sys_cpu, detections, visible_total, errors, missing_poses,
                        thread_counts, mapper_cpu, mapper_threads, saturated_images)
    map_out = os.path.join(workdir, "bench_map.yaml")
    launch = _Launch([os.path.join(ROOT, "launch", "mapping.launch"), f"map_file:={map_out}"], env,
                     os.path.join(workdir, "pass2.log"))
    det_pubs = {c: rospy.Publisher(f"/ring/{c}/fiducial_vertices", FiducialArray, queue_size=5) for c in CAMERAS}
    try:
        mapper_pid = _node_pid("/mapper")
        _wait(lambda: all(p.get_num_connections() > 0 for p in det_pubs.values()), 120, "the mapper's subscriptions")
        time.sleep(2.0)
        counted = recorded[warmup:]
        for t, msgs in recorded[:warmup]:
            clock_pub.publish(Clock(clock=rospy.Time.from_sec(t)))
            for c in CAMERAS:
                info_pubs[c].publish(infos[c])
                det_pubs[c].publish(msgs[c])
            time.sleep(DT)
        time.sleep(1.0)
        profiler.start("mapper", mapper_pid)
        m0 = cpu_seconds(mapper_pid)
        w0 = time.monotonic()
        for i, (t, msgs) in enumerate(counted):
            clock_pub.publish(Clock(clock=rospy.Time.from_sec(t)))
            for c in CAMERAS:
                infos[c].header.stamp = rospy.Time.from_sec(t)
                info_pubs[c].publish(infos[c])
                det_pubs[c].publish(msgs[c])
            delay = w0 + DT * (i + 1) - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        clock_pub.publish(Clock(clock=rospy.Time.from_sec(counted[-1][0] + DT)))
        time.sleep(1.0)
        mapper_cpu = cpu_seconds(mapper_pid) - m0
        mapper_threads = threads(mapper_pid)
    finally:
        profiler.stop()
        launch.stop()
    rospy.signal_shutdown("done")
    return _summary(frames, warmup, cpu, sys_cpu, detections, visible_total, errors, missing_poses,
                    thread_counts, mapper_cpu, mapper_threads, saturated_images)


def _lab_renderer(lab: str, ring):
    """``render(pose, rng) -> (images, visible)`` of one ring frame at ``pose`` (x, y, yaw) of the lab
    (kind: ``RingSimulator.render`` of the default scene, every camera at the pose; harsh:
    config/lab_harsh.yaml's conditions as bench/noise_budget.py draws them: the tilted, bumpy plate,
    each camera shaken by the ring's vibration, the wandering gain that saturates the white paper
    and the uneven light, the pillars; ``visible`` the true corners through each camera as it was)."""
    from aruco_ring_localization.simulation.ring_sim import RingSimulator
    from aruco_ring_localization.simulation.scene import Scene, resolve_scene_file

    if lab == "kind":
        sim = RingSimulator(Scene.default(), ring, seed=3)

        def render(pose, rng):
            T = Scene.T_world_base(pose)
            return sim.render(T, rng=rng), sim.visible(T)
        return render
    if lab != "harsh":
        raise ValueError(f"lab: expected kind or harsh, got {lab!r}")
    from aruco_ring_localization.simulation.conditions import LabConditions
    from aruco_ring_localization.simulation.params import lab_config

    config = lab_config("harsh")
    scene = Scene.load(resolve_scene_file(config.scene.file))
    sim = RingSimulator(scene, ring, seed=3)
    cond = LabConditions(config, scene, ring.names, seed=3)

    def render(pose, rng):
        T_world = cond.T_world_base(pose)
        light = cond.photometry.draw()
        views = cond.views(sim.ring, T_world)
        images = {c: sim.render_views([Tv], c, light.get(c), rng=rng) for c, Tv in views.items()}
        return images, {c: sim.visible_camera(Tv, c) for c, Tv in views.items()}
    return render


def _summary(frames, warmup, cpu, sys_cpu, detections, visible_total, errors, missing_poses, thread_counts,
             mapper_cpu, mapper_threads, saturated_images) -> dict:
    import numpy as np

    n = frames
    det_ms = [1e3 * cpu[c] / n for c in CAMERAS]
    det_mean = float(np.mean(det_ms))
    loc_ms = 1e3 * cpu["localizer"] / n
    return {
        "detector_node_cpu_ms_per_image": det_mean,
        "detector_node_cpu_ms_per_image_max": float(np.max(det_ms)),
        "localizer_node_cpu_ms_per_ring_frame": loc_ms,
        "mapper_node_cpu_ms_per_ring_frame": 1e3 * mapper_cpu / n,
        "ring_10hz_cores": (8 * det_mean + loc_ms) * 10.0 / 1000.0,
        "detector_node_detection_rate": detections / max(1, visible_total),
        "detector_node_corner_err_px_median": float(np.median(errors)) if errors else float("nan"),
        "_system_share": {"detectors": sum(sys_cpu[c] for c in CAMERAS) / max(1e-9, sum(cpu[c] for c in CAMERAS)),
                          "localizer": sys_cpu["localizer"] / max(1e-9, cpu["localizer"])},
        "_frames": n,
        "_warmup": warmup,
        "_visible": visible_total,
        "_missing_poses": missing_poses,
        "_threads": {**thread_counts, "mapper": mapper_threads},
        "_saturated_images": saturated_images,
    }


def _start_master(workdir: str):
    port = _free_port()
    os.environ["ROS_MASTER_URI"] = f"http://localhost:{port}"
    os.environ.setdefault("ROS_HOSTNAME", "localhost")
    os.environ["ROS_HOME"] = workdir
    log = open(os.path.join(workdir, "roscore.log"), "w", encoding="utf-8")
    proc = subprocess.Popen(["roscore", "-p", str(port)], stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True, env=dict(os.environ))
    import rosgraph

    _wait(lambda: rosgraph.is_master_online(), 60, "the master")
    return proc, log


def _stop_master(master: subprocess.Popen, log) -> None:
    """Stop what :func:`_start_master` started (SIGINT to its process group, SIGKILL after 20 s)."""
    os.killpg(master.pid, signal.SIGINT)
    try:
        master.wait(20)
    except subprocess.TimeoutExpired:
        os.killpg(master.pid, signal.SIGKILL)
    log.close()


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60, help="ring frames measured")
    parser.add_argument("--warmup", type=int, default=5, help="ring frames played first, not counted")
    parser.add_argument("--out", default="", help="write the JSON here (default: stdout)")
    parser.add_argument("--keep", action="store_true", help="keep the work folder (logs)")
    parser.add_argument("--py-spy", default="", help="path of a py-spy executable: profile cam0's detector, the "
                                                      "localizer and the mapper (raw stacks in --profile-dir)")
    parser.add_argument("--profile-dir", default="results/bench/profiles", help="where the profiles go")
    parser.add_argument("--lab", default="kind", choices=["kind", "harsh"],
                        help="the rendered lab (harsh: pass 1 only, the detectors and the localizer)")
    args = parser.parse_args(argv)
    workdir = tempfile.mkdtemp(prefix="bench_nodes_")
    master, log = _start_master(workdir)
    try:
        load0 = os.getloadavg()
        out = measure(args.frames, args.warmup, workdir, args.py_spy, args.profile_dir, lab=args.lab,
                      mapper=args.lab == "kind")
        load1 = os.getloadavg()
        out["_load"] = [load0[0], load1[0], load1[1]]
    finally:
        _stop_master(master, log)
        if not args.keep:
            shutil.rmtree(workdir, ignore_errors=True)
        else:
            sys.stderr.write(f"[bench_nodes] logs in {workdir}\n")
    if args.py_spy:
        for name in ("detector_cam0", "localizer", "mapper"):
            path = os.path.join(args.profile_dir, f"{name}.txt")
            if os.path.exists(path):
                sys.stderr.write(f"--- {name} (py-spy, {path})\n" + "\n".join(top_functions(path)) + "\n")
    text = json.dumps(out, indent=2)
    if args.out:
        with open(args.out, "w", encoding="utf-8") as handle:
            handle.write(text)
    else:
        print(text)
    return 0


def run(quick: bool = False) -> dict:
    """For bench/run.py: the measurement in a child process (rospy.init_node once per process)."""
    frames, warmup = (15, 3) if quick else (60, 5)

    def child(lab: str) -> dict:
        with tempfile.TemporaryDirectory() as tmp:
            out_file = os.path.join(tmp, "nodes.json")
            subprocess.run([sys.executable, os.path.abspath(__file__), "--frames", str(frames), "--warmup",
                            str(warmup), "--out", out_file, "--lab", lab], check=True)
            with open(out_file, encoding="utf-8") as handle:
                return json.load(handle)

    out = child("kind")
    harsh = child("harsh")
    keys = ["detector_node_cpu_ms_per_image", "localizer_node_cpu_ms_per_ring_frame",
            "mapper_node_cpu_ms_per_ring_frame", "ring_10hz_cores", "detector_node_detection_rate",
            "detector_node_corner_err_px_median", "detector_node_cpu_ms_per_image_max"]
    results = {k: out[k] for k in keys}
    harsh_keys = ["detector_node_cpu_ms_per_image", "detector_node_detection_rate", "detector_node_corner_err_px_median",
                  "localizer_node_cpu_ms_per_ring_frame"]
    results.update({k + "_harsh": harsh[k] for k in harsh_keys})
    th = out["_threads"]
    md = [
        "## nodes (whole processes through a real master)",
        "",
        f"The stock launch files (ring_detectors.launch + localization.launch on test/data/lab_truth_map.yaml; then "
        f"mapping.launch) driven by a lockstep player on {out['_frames']} rendered ring frames of the lab "
        f"(8 mono8 1280x960 images each, after {out['_warmup']} warm-up frames); CPU = utime + stime of each node "
        f"process from /proc/<pid>/stat. Load average (1 min) {out['_load'][0]:.1f} at the start, "
        f"{out['_load'][1]:.1f} at the end (5 min: {out['_load'][2]:.1f}). bench/bench_nodes.py.",
        "",
        "| key | value | target |",
        "|---|---|---|",
        f"| detector_node_cpu_ms_per_image (mean of 8; max {results['detector_node_cpu_ms_per_image_max']:.1f}) | "
        f"{results['detector_node_cpu_ms_per_image']:.1f} | <= 12 |",
        f"| detector_node_detection_rate (of {out['_visible']} visible markers) | "
        f"{100 * results['detector_node_detection_rate']:.2f} % | >= 99.9 % |",
        f"| detector_node_corner_err_px_median | {results['detector_node_corner_err_px_median']:.3f} | <= 0.15 |",
        f"| localizer_node_cpu_ms_per_ring_frame | {results['localizer_node_cpu_ms_per_ring_frame']:.1f} | <= 5 |",
        f"| mapper_node_cpu_ms_per_ring_frame (fed at 10 Hz) | {results['mapper_node_cpu_ms_per_ring_frame']:.1f} | - |",
        f"| ring_10hz_cores (8 detectors + localizer) | {results['ring_10hz_cores']:.2f} | <= 1.2 |",
        "",
        f"Threads per process at the end: detector {th['cam0']}, localizer {th['localizer']}, mapper {th['mapper']}. "
        f"Localizer poses missing (not an answer within 10 s): {out['_missing_poses']}.",
        "",
        f"**The harsh lab** (`--lab harsh`, the `_harsh` keys; pass 1 only, right after, load "
        f"{harsh['_load'][0]:.1f} at the start, {harsh['_load'][1]:.1f} at the end): the same drive and player on "
        "config/lab_harsh.yaml's images as bench/noise_budget.py draws them (the tilted, bumpy plate, each camera "
        "shaken by the ring's vibration, the wandering gain, the uneven light, the pillars), the truth through each "
        f"camera as it was; {harsh['_saturated_images']} of the {8 * harsh['_frames']} images have a pixel at full "
        "scale (saturated white paper: the detector's border-stripe path, docs/detector.md). The map file is the "
        "same room's.",
        "",
        "| key | value | kind lab (above) |",
        "|---|---|---|",
        f"| detector_node_cpu_ms_per_image_harsh (max {harsh['detector_node_cpu_ms_per_image_max']:.1f}) | "
        f"{harsh['detector_node_cpu_ms_per_image']:.1f} | {out['detector_node_cpu_ms_per_image']:.1f} |",
        f"| detector_node_detection_rate_harsh (of {harsh['_visible']} visible markers) | "
        f"{100 * harsh['detector_node_detection_rate']:.2f} % | {100 * out['detector_node_detection_rate']:.2f} % |",
        f"| detector_node_corner_err_px_median_harsh | {harsh['detector_node_corner_err_px_median']:.3f} | "
        f"{out['detector_node_corner_err_px_median']:.3f} |",
        f"| localizer_node_cpu_ms_per_ring_frame_harsh | {harsh['localizer_node_cpu_ms_per_ring_frame']:.1f} | "
        f"{out['localizer_node_cpu_ms_per_ring_frame']:.1f} |",
    ]
    return {"results": results, "markdown": "\n".join(md)}


if __name__ == "__main__":
    sys.exit(main())
