"""The localizer node against its core on the same ring frames: what the node costs beyond the pipeline.

A tool beside ``bench_nodes.py`` (not a section of ``bench/run.py``): a master, the stock
``localization.launch`` (with ``ring_tf``) on test/data/lab_truth_map.yaml under ``use_sim_time``,
and a lockstep player that publishes, per ring frame, /clock, the 8 camera_info and the 8
``fiducial_vertices`` of corners-mode detections (the simulated lab, the trajectory of
``bench_nodes.py``), then waits for ``localizer/pose`` of that stamp. No detector nodes: a run of
300 frames takes about a minute and the figure is not diluted by 8 image-processing processes.

Printed (JSON): ``node_ms`` = the localizer process's CPU per ring frame (utime + stime from
/proc/<pid>/stat, between publishing a frame and receiving its pose), ``node_total_ms`` = the same
over the whole measured span (what the node does after its pose went out, tf and the queued
publications, and between frames, included), ``node_sched_ms`` = the same
from every thread's /proc/<pid>/task/<tid>/schedstat (nanoseconds, so not quantised to clock
ticks), ``node_sys_ms`` its system share, and ``core_ms_mean`` / ``core_ms_median`` =
:class:`pipeline.LocalizationPipeline` in this process (one BLAS thread; CPU of its thread) on the same detections
through the same message conversion, ring-file extrinsics and intrinsics (what the node gets from
tf and camera_info), CPU per ring frame. With ``--py-spy PATH`` the node is sampled while it
runs (only the thread holding the GIL: ``--gil``; ``--py-spy-idle``: every thread, idle ones too,
with thread ids: ``--idle --threads``) and the top functions are printed.

``threads_ms`` (always): each thread's CPU per ring frame over the measured frames (schedstat),
named by the Python frame ``py-spy dump`` shows it in (with ``--py-spy``), largest first.
With ``--gc`` the node runs with a ``sitecustomize`` that counts its garbage collections
(``gc.callbacks``: per generation, and their CPU time) and writes them on SIGUSR1; ``gc`` gives
the collections and their ms per ring frame over the measured frames.

Run: ``source .ws/env.sh; python bench/localizer_node_split.py --frames 300`` (state the load:
the figures follow it; alternate two checkouts in one load window to compare them).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import shutil
import subprocess
import sys
import tempfile
import time
from typing import List, Optional

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(ROOT, "src"))

import bench_nodes as bn  # noqa: E402


def schedstat_seconds(pid: int) -> float:
    """CPU time of every thread of ``pid`` (first field of /proc/<pid>/task/<tid>/schedstat, ns), s."""
    total = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat", encoding="ascii") as handle:
                total += int(handle.read().split()[0])
        except OSError:  # a thread that ended
            pass
    return 1e-9 * total


def schedstat_per_thread(pid: int) -> dict:
    """tid -> CPU s of each thread of ``pid`` (schedstat)."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat", encoding="ascii") as handle:
                out[int(tid)] = 1e-9 * int(handle.read().split()[0])
        except OSError:
            pass
    return out


def context_switches(pid: int) -> tuple:
    """(voluntary, involuntary) context switches summed over the threads of ``pid`` (a voluntary one:
    the thread blocked, on a socket, a lock, the GIL; an involuntary one: the kernel preempted it)."""
    vol = inv = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/status", encoding="ascii") as handle:
                for line in handle:
                    if line.startswith("voluntary_ctxt_switches:"):
                        vol += int(line.split()[1])
                    elif line.startswith("nonvoluntary_ctxt_switches:"):
                        inv += int(line.split()[1])
        except OSError:
            pass
    return vol, inv


def thread_places(py_spy: str, pid: int) -> dict:
    """tid -> 'thread name: innermost frames' of each Python thread (``py-spy dump``)."""
    if not py_spy:
        return {}
    dump = subprocess.run([py_spy, "dump", "--pid", str(pid)], capture_output=True, text=True).stdout
    places: dict = {}
    tid = None
    frames: List[str] = []

    def close() -> None:
        if tid is not None:
            places[tid] = " < ".join(frames[:3])

    for line in dump.splitlines():
        if line.startswith("Thread "):
            close()
            parts = line.split()
            tid, frames = None, [line.split(":", 1)[-1].strip()]
            for part in parts[1:3]:
                word = part.strip("():,")
                if word.isdigit():
                    tid = int(word)
                elif word.lower().startswith("0x"):
                    tid = int(word, 16)
        elif line.strip() and tid is not None:
            frames.append(line.strip().split(" (")[0])
    close()
    return places


#: sitecustomize of a node run with --gc: counts collections per generation and their CPU time.
GC_SITECUSTOMIZE = """
import gc, os, signal, sys, time
try:
    import apport_python_hook
    apport_python_hook.install()
except ImportError:
    pass
if any(a.endswith("localizer") for a in sys.argv[:1]):
    _stats = {"collections": [0, 0, 0], "cpu_s": [0.0, 0.0, 0.0], "collected": 0}
    _t0 = [0.0]

    def _on_gc(phase, info):
        if phase == "start":
            _t0[0] = time.thread_time()
        else:
            g = info["generation"]
            _stats["collections"][g] += 1
            _stats["cpu_s"][g] += time.thread_time() - _t0[0]
            _stats["collected"] += info["collected"]

    gc.callbacks.append(_on_gc)

    _probes = {}

    def _probe(cls, name):
        fn = getattr(cls, name)
        acc = _probes.setdefault(cls.__name__ + "." + name, [0, 0.0])

        def wrapper(*args, **kwargs):
            t0 = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                acc[0] += 1
                acc[1] += time.thread_time() - t0
        setattr(cls, name, wrapper)

    def _install_probes():
        from aruco_ring_localization.pipeline import LocalizationPipeline
        from aruco_ring_localization.ros import localizer, ring_input, tf_output
        import tf2_ros
        for cls, name in [(LocalizationPipeline, "on_detections"), (LocalizationPipeline, "poll"),
                          (LocalizationPipeline, "diagnostics"),
                          (ring_input.RingSubscriber, "_on_fiducials_raw"),
                          (ring_input.RingSubscriber, "_on_camera_info_raw"),
                          (ring_input.RingSubscriber, "_on_timer"), (ring_input.RingSubscriber, "_drain"),
                          (localizer.LocalizerNode, "_publish"), (localizer.LocalizerNode, "publish_tf"),
                          (localizer.LocalizerNode, "check_tf_authority"),
                          (localizer.LocalizerNode, "publish_markers"),
                          (tf_output.MapTransform, "compute"),
                          (tf2_ros.TransformListener, "callback")]:
            if hasattr(cls, name):
                _probe(cls, name)

    def _install_when_imported():
        # before the node subscribes (rospy keeps the bound methods it was given)
        import threading
        def wait():
            while "aruco_ring_localization.ros.localizer" not in sys.modules or \\
                    not hasattr(sys.modules["aruco_ring_localization.ros.localizer"], "LocalizerNode"):
                time.sleep(0.002)
            _install_probes()
        threading.Thread(target=wait, daemon=True).start()

    _install_when_imported()

    def _dump(_sig, _frame):
        import json
        _probes_copy = {k: list(v) for k, v in _probes.items()}
        with open(os.environ["GC_STATS_FILE"], "a") as handle:
            handle.write(json.dumps(dict(_stats, threshold=gc.get_threshold(), frozen=gc.get_freeze_count(),
                                         probes=_probes_copy)) + "\\n")

    signal.signal(signal.SIGUSR1, _dump)
"""


def _gc_read(path: str) -> List[dict]:
    bn._wait(lambda: os.path.exists(path), 10, "the node's gc statistics")
    with open(path, encoding="utf-8") as handle:
        return [json.loads(line) for line in handle if line.strip()]


def _frames(n: int):
    import numpy as np

    from aruco_ring_localization.ring import CameraRing
    from aruco_ring_localization.simulation.ring_sim import RingSimulator
    from aruco_ring_localization.simulation.scene import Scene

    ring = CameraRing.load(os.path.join(ROOT, "config", "ring.yaml"))
    scene = Scene.default()
    sim = RingSimulator(scene, ring, seed=3)
    t0 = 100.0
    frames = [sim.observe(Scene.T_world_base(p), stamp=t0 + bn.DT * k, rng=np.random.default_rng(1000 + k))
              for k, p in enumerate(bn._trajectory(scene, n))]
    return ring, frames


def measure_node(ring, frames, warmup: int, workdir: str, py_spy: str = "", profile: str = "",
                 py_spy_idle: bool = False, gc_stats: bool = False) -> dict:
    import rospy
    from fiducial_msgs.msg import FiducialArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import CameraInfo

    from aruco_ring_localization.ros.conversions import model_to_camera_info, observations_to_fiducials

    env = dict(os.environ)
    gc_file = os.path.join(workdir, "gc.jsonl")
    if gc_stats:
        site = os.path.join(workdir, "site")
        os.makedirs(site, exist_ok=True)
        with open(os.path.join(site, "sitecustomize.py"), "w", encoding="utf-8") as handle:
            handle.write(GC_SITECUSTOMIZE)
        env["PYTHONPATH"] = site + os.pathsep + env.get("PYTHONPATH", "")
        env["GC_STATS_FILE"] = gc_file
    launch = bn._Launch([os.path.join(ROOT, "launch", "localization.launch"), f"map_file:={bn.MAP_FILE}"],
                        env, os.path.join(workdir, "launch.log"))
    rospy.set_param("/use_sim_time", True)
    rospy.init_node("bench_player", disable_signals=True)
    clock_pub = rospy.Publisher("/clock", Clock, queue_size=1)
    infos = {c: model_to_camera_info(ring[c].model, ring[c].frame_id) for c in bn.CAMERAS}
    info_pubs = {c: rospy.Publisher(f"/ring/{c}/camera_info", CameraInfo, queue_size=2) for c in bn.CAMERAS}
    det_pubs = {c: rospy.Publisher(f"/ring/{c}/fiducial_vertices", FiducialArray, queue_size=5) for c in bn.CAMERAS}
    got = {}

    def on_pose(msg) -> None:
        got[round(msg.header.stamp.to_sec(), 3)] = msg

    rospy.Subscriber("/localizer/pose", PoseWithCovarianceStamped, on_pose, queue_size=50)
    spy: Optional[subprocess.Popen] = None
    cpu = sys_cpu = sched = 0.0
    missing = 0
    try:
        pid = bn._node_pid("/localizer")
        bn._wait(lambda: all(p.get_num_connections() > 0 for p in det_pubs.values()), 120,
                 "the localizer's subscriptions")
        clock_pub.publish(Clock(clock=rospy.Time.from_sec(frames[0].stamp - 1.0)))
        time.sleep(2.0)  # ring_tf's static transforms reach the localizer's listener
        for k, frame in enumerate(frames):
            stamp = rospy.Time.from_sec(frame.stamp)
            key = round(frame.stamp, 3)
            msgs = {}
            for c in bn.CAMERAS:
                m = FiducialArray()
                m.header.stamp, m.header.frame_id, m.image_seq = stamp, ring[c].frame_id, k
                m.fiducials = observations_to_fiducials(frame.cameras[c].observations)
                msgs[c] = m
            if k == warmup:
                per_thread0 = schedstat_per_thread(pid)
                total0 = bn.cpu_seconds(pid)
                switches0 = context_switches(pid)
                if gc_stats:
                    os.kill(pid, signal.SIGUSR1)
            if k == warmup and py_spy:
                mode = ["--idle", "--threads"] if py_spy_idle else ["--gil"]
                spy = subprocess.Popen([py_spy, "record", "--pid", str(pid), "--rate", "1000"] + mode +
                                       ["--format", "raw", "--output", profile, "--nonblocking"],
                                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            before = (bn.cpu_seconds(pid), bn.system_seconds(pid), schedstat_seconds(pid))
            clock_pub.publish(Clock(clock=stamp))
            for c in bn.CAMERAS:
                infos[c].header.stamp = stamp
                info_pubs[c].publish(infos[c])
                det_pubs[c].publish(msgs[c])
            try:
                bn._wait(lambda: key in got, 10, f"the localizer's pose of frame {k}")
            except RuntimeError:
                missing += 1
            after = (bn.cpu_seconds(pid), bn.system_seconds(pid), schedstat_seconds(pid))
            if k >= warmup:
                cpu += after[0] - before[0]
                sys_cpu += after[1] - before[1]
                sched += after[2] - before[2]
        time.sleep(0.5)  # the last frame's tf and queued publications
        total1 = bn.cpu_seconds(pid)
        switches1 = context_switches(pid)
        threads = bn.threads(pid)
        per_thread1 = schedstat_per_thread(pid)
        if gc_stats:
            os.kill(pid, signal.SIGUSR1)
            bn._wait(lambda: len(_gc_read(gc_file)) >= 2, 10, "the node's gc statistics")
            gc_rows = _gc_read(gc_file)
        places = thread_places(py_spy, pid)
    finally:
        if spy is not None:
            spy.send_signal(signal.SIGINT)
            spy.wait(30)
        launch.stop()
        rospy.signal_shutdown("done")
    n = len(frames) - warmup
    per_thread = sorted(((1e3 * (c - per_thread0.get(t, 0.0)) / n, t) for t, c in per_thread1.items()), reverse=True)
    out = {"node_ms": 1e3 * cpu / n, "node_total_ms": 1e3 * (total1 - total0) / n, "node_sched_ms": 1e3 * sched / n, "node_sys_ms": 1e3 * sys_cpu / n,
           "missing_poses": missing, "threads": threads,
           "context_switches_per_frame": [(b - a) / n for a, b in zip(switches0, switches1)],
           "threads_ms": [f"{ms:.3f} {tid} {places.get(tid, '')}" for ms, tid in per_thread if ms > 0.0005]}
    if gc_stats:
        a, b = gc_rows[0], gc_rows[-1]
        out["gc"] = {"collections_per_frame": [(y - x) / n for x, y in zip(a["collections"], b["collections"])],
                     "ms_per_frame": [1e3 * (y - x) / n for x, y in zip(a["cpu_s"], b["cpu_s"])],
                     "collected_per_frame": (b["collected"] - a["collected"]) / n,
                     "threshold": b["threshold"], "frozen": b["frozen"]}
        # Inclusive CPU (thread time) per ring frame of the node's functions, and calls per frame
        # (the probes are installed at the first signal, so the second row holds the measured frames).
        pa = a.get("probes", {})
        delta = {k: (v[0] - pa.get(k, [0, 0.0])[0], v[1] - pa.get(k, [0, 0.0])[1]) for k, v in b.get("probes", {}).items()}
        out["probes_ms"] = {k: f"{1e3 * v[1] / n:.3f} ms, {v[0] / n:.2f} calls" for k, v in
                            sorted(delta.items(), key=lambda kv: -kv[1][1])}
    return out


def measure_core(ring, frames, warmup: int) -> dict:
    """The pipeline in process on the frames, through the node's conversion of the messages."""
    import numpy as np
    from fiducial_msgs.msg import FiducialArray
    from threadpoolctl import threadpool_limits

    from aruco_ring_localization.config import load_yaml_config
    from aruco_ring_localization.marker_map import MarkerMap
    from aruco_ring_localization.pipeline import LocalizationPipeline
    from aruco_ring_localization.ros.conversions import fiducial_array_to_observations, observations_to_fiducials
    from aruco_ring_localization.schemas import LocalizerConfig

    def through_message(obs):
        msg = FiducialArray()
        msg.fiducials = observations_to_fiducials(obs)
        return fiducial_array_to_observations(msg)

    per_frame = [{c: through_message(f.cameras[c].observations) for c in bn.CAMERAS} for f in frames]
    config = load_yaml_config(LocalizerConfig, os.path.join(ROOT, "config", "localization.yaml"),
                              {"input.use_tf": False, "input.camera_info_fallback": True, "map_file": bn.MAP_FILE})
    times: List[float] = []
    with threadpool_limits(limits=1):
        pipeline = LocalizationPipeline(config, ring, MarkerMap.load(bn.MAP_FILE))
        for k, frame in enumerate(frames):
            c0 = time.thread_time()
            for c in bn.CAMERAS:
                pipeline.on_detections(c, frame.stamp, per_frame[k][c], frame.stamp)
            if k >= warmup:
                times.append(time.thread_time() - c0)
    return {"core_ms_mean": 1e3 * float(np.mean(times)), "core_ms_median": 1e3 * float(np.median(times))}


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300, help="ring frames measured")
    parser.add_argument("--warmup", type=int, default=10, help="ring frames played first, not counted")
    parser.add_argument("--py-spy", default="", help="path of a py-spy executable: sample the node (GIL holder)")
    parser.add_argument("--py-spy-idle", action="store_true",
                        help="sample every thread, idle ones too, with thread ids (--idle --threads) instead of --gil")
    parser.add_argument("--gc", action="store_true", help="count the node's garbage collections and time its "
                        "inputs, pipeline calls and outputs (sitecustomize; the probes cost a few us per call)")
    parser.add_argument("--no-core", action="store_true", help="skip the in-process core measurement")
    parser.add_argument("--profile", default="results/bench/profiles/localizer_split.txt",
                        help="where py-spy's raw stacks go")
    args = parser.parse_args(argv)
    ring, frames = _frames(args.warmup + args.frames)
    # The core first: after the player's rospy session its threads share the process (and its
    # in-process figure read 30 % high against a run of its own).
    core = {} if args.no_core else measure_core(ring, frames, args.warmup)
    workdir = tempfile.mkdtemp(prefix="localizer_split_")
    if args.py_spy:
        os.makedirs(os.path.dirname(os.path.abspath(args.profile)), exist_ok=True)
    master, log = bn._start_master(workdir)
    load0 = os.getloadavg()[0]
    try:
        out = measure_node(ring, frames, args.warmup, workdir, args.py_spy, args.profile, args.py_spy_idle, args.gc)
    finally:
        bn._stop_master(master, log)
        shutil.rmtree(workdir, ignore_errors=True)
    out.update(core)
    out["frames"] = args.frames
    out["load"] = [load0, os.getloadavg()[0]]
    print(json.dumps(out, indent=2))
    if args.py_spy and os.path.exists(args.profile):
        print("\n".join(bn.top_functions(args.profile, 25)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
