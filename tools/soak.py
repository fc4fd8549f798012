#!/usr/bin/env python3
"""`make soak`: run the localizer on the simulated lab for a long simulated time and record
memory (RSS of each node over time), dropped frames and the position error.

The simulator node (owning ``/clock``, paced at ``--speed`` simulated seconds per wall second,
driving the paper's 23 poses again and again, holding each 3 s; its parameters are written to
``--out``/simulator.yaml) feeds the localizer; the error compares ``localizer/pose`` with
``sim/ground_truth`` at the same stamp (the map is the scene's truth). The lab is the simulator's
default (its schema's: the demo's and the benchmarks' lab), or the one of ``--simulator-config FILE``
(config/simulator.yaml format: a harsher or a kinder lab, another scene); the soak sets only the
mode, rate, route, loop, hold time and clock on top. Modes (``--mode``):

* ``images`` — the simulator renders images for 8 detector nodes (lockstep: the clock waits for
  them, so no frame is lost and the real-time ratio says how fast the chain runs);
* ``corners`` — the simulator publishes the detections itself (pixel noise, a miscalibrated true
  rig): the localizer alone, at ``--speed``;
* ``auto`` (default) — ``images`` when the detector node exists, else ``corners`` (said on stdout).

The nodes run under their own master on a free port (no clash with a running roscore), with
``use_sim_time``. Every ``--sample`` simulated seconds it records, per node, VmRSS from
/proc/<pid>/status (pids from the master), and the localizer's poses, errors and diagnostics.
Output: results/soak/soak.json and a markdown section printed to stdout (copied into
docs/reliability.md). Memory is called flat when the RSS growth after warm-up (the first half
of the run) is below 5 MB per simulated hour, extrapolated.
``--report results/soak/soak.json`` rewrites the summary of a finished run.

Usage: tools/soak.py [--minutes 30] [--rate 10] [--speed 1.0] [--sample 30] [--mode auto]
                     [--simulator-config FILE]
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import xmlrpc.client
from typing import Dict, List, Optional

import numpy as np

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.join(REPO, "src"))

#: The first part of the run counted as warm-up (Python allocator pools, tf and connection
#: buffers fill up over minutes); memory must be flat after it.
WARMUP_FRACTION = 0.5
#: Flat: the localizer's RSS grows less than this after warm-up (MB per simulated hour, fit).
FLAT_MB_PER_H = 5.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def rss_mb(pid: int) -> Optional[float]:
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def node_pids(master_uri: str) -> Dict[str, int]:
    """name -> pid of every node registered with the master (through each node's getPid)."""
    master = xmlrpc.client.ServerProxy(master_uri)
    _, _, state = master.getSystemState("/soak")
    names = sorted({n for group in state for _, nodes in group for n in nodes})
    out = {}
    for name in names:
        try:
            _, _, uri = master.lookupNode("/soak", name)
            _, _, pid = xmlrpc.client.ServerProxy(uri).getPid("/soak")
            out[name] = int(pid)
        except (OSError, xmlrpc.client.Error, ValueError):
            continue
    return out


def simulator_config(mode: str, speed: float, rate: float, base_file: Optional[str] = None):
    """The simulator's parameters for the soak: the lab of ``base_file`` (or the default lab), the
    paper's 23 poses in a loop, 3 s each."""
    from aruco_ring_localization.config import load_yaml_config, with_overrides
    from aruco_ring_localization.simulation.params import SimulatorConfig

    base = load_yaml_config(SimulatorConfig, base_file) if base_file else SimulatorConfig()
    return with_overrides(base, {"mode": mode, "rate": rate, "robot.waypoints": "paper", "robot.plan": [],
                                 "robot.loop": True, "robot.hold_time": 3.0, "clock.publish": True,
                                 "clock.speed": speed})


def write_truth_map(config, path: str) -> str:
    """The true map of the configured scene (what the localizer localizes against), at ``path``."""
    from aruco_ring_localization.simulation.scene import Scene, resolve_scene_file

    scene = Scene.load(resolve_scene_file(config.scene.file)) if config.scene.file else Scene.default()
    scene.truth_map().save(path, backups=0)
    return path


def launch_text(mode: str, sim_config: str, truth_map: str) -> str:
    return f"""<launch>
  <include file="$(find aruco_ring_localization)/launch/simulation.launch">
    <arg name="config" value="{sim_config}"/>
    <arg name="detectors" value="{'true' if mode == 'images' else 'false'}"/>
    <arg name="use_sim_time" value="true"/>
  </include>
  <include file="$(find aruco_ring_localization)/launch/ring_tf.launch"/>
  <node pkg="aruco_ring_localization" type="localizer" name="localizer" output="log">
    <rosparam command="load" file="$(find aruco_ring_localization)/config/localization.yaml"/>
    <param name="map_file" value="{truth_map}"/>
  </node>
</launch>
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0, help="simulated minutes (default 30)")
    ap.add_argument("--rate", type=float, default=10.0, help="ring frames per simulated second (default 10)")
    ap.add_argument("--speed", type=float, default=1.0, help="simulated s per wall s, at most (default 1)")
    ap.add_argument("--sample", type=float, default=30.0, help="sampling period, simulated s (default 30)")
    ap.add_argument("--mode", choices=("auto", "corners", "images"), default="auto")
    ap.add_argument("--simulator-config", metavar="FILE", default=None,
                    help="the lab: simulator parameters (config/simulator.yaml format); default: the simulator's "
                         "default lab")
    ap.add_argument("--out", default=os.path.join(REPO, "results", "soak"))
    ap.add_argument("--report", metavar="SOAK_JSON", help="only summarise a finished run's soak.json")
    args = ap.parse_args(argv)
    if args.report:
        with open(args.report) as handle:
            run_data = json.load(handle)
        saved = argparse.Namespace(**run_data["args"])
        errors = run_data.get("errors_cm")
        errors = [e / 100.0 for e in errors] if errors else []
        return report(saved, run_data["mode"], run_data["samples"], errors, run_data["frames"], run_data["wall_s"])

    have_images = os.path.exists(os.path.join(REPO, "scripts", "detector"))
    mode = args.mode if args.mode != "auto" else ("images" if have_images else "corners")
    if mode == "images" and not have_images:
        print("soak: image mode needs scripts/detector")
        return 2
    if args.mode == "auto":
        print(f"soak: mode {mode} (image mode needs the detector node)")

    port = free_port()
    master_uri = f"http://localhost:{port}"
    os.environ["ROS_MASTER_URI"] = master_uri
    os.environ.setdefault("ROS_HOSTNAME", "localhost")
    tmp = tempfile.mkdtemp(prefix="soak_")
    os.makedirs(args.out, exist_ok=True)
    sim_config = os.path.join(args.out, "simulator.yaml")
    config = simulator_config(mode, args.speed, args.rate, args.simulator_config)
    with open(sim_config, "w") as handle:
        import yaml

        from aruco_ring_localization.config import to_dict
        yaml.safe_dump(to_dict(config), handle, sort_keys=False)
    truth_map = write_truth_map(config, os.path.join(args.out, "truth_map.yaml"))
    launch_file = os.path.join(tmp, "soak.launch")
    with open(launch_file, "w") as handle:
        handle.write(launch_text(mode, sim_config, truth_map))
    log = open(os.path.join(tmp, "roslaunch.log"), "w")
    proc = subprocess.Popen(["roslaunch", "-p", str(port), launch_file], stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        return run(args, mode, master_uri, proc)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGINT)
            proc.wait(timeout=20)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        log.close()
        shutil.rmtree(tmp, ignore_errors=True)


def run(args, mode: str, master_uri: str, proc: subprocess.Popen) -> int:
    """The simulator (owning /clock) [+ 8 detectors] + the localizer; this process only records."""
    import threading

    for _ in range(100):
        try:
            xmlrpc.client.ServerProxy(master_uri).getPid("/soak")
            break
        except OSError:
            time.sleep(0.2)
    import rospy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped

    rospy.init_node("soak", disable_signals=True)
    lock = threading.Lock()
    truth: Dict[int, tuple] = {}
    poses: List[tuple] = []
    diag: Dict[str, str] = {}

    def on_truth(msg):
        with lock:
            truth[int(round(msg.header.stamp.to_sec() * 1000))] = (msg.pose.position.x, msg.pose.position.y)

    def on_pose(msg):
        with lock:
            poses.append((int(round(msg.header.stamp.to_sec() * 1000)), msg.pose.pose.position.x,
                          msg.pose.pose.position.y))

    def on_diag(msg):
        for st in msg.status:
            if "filter" in st.name:
                with lock:
                    diag.update({v.key: v.value for v in st.values})

    rospy.Subscriber("sim/ground_truth", PoseStamped, on_truth, queue_size=50)
    rospy.Subscriber("localizer/pose", PoseWithCovarianceStamped, on_pose, queue_size=50)
    rospy.Subscriber("/diagnostics", DiagnosticArray, on_diag, queue_size=10)
    duration = args.minutes * 60.0
    t_wall0 = time.time()
    samples: List[dict] = []
    errors: List[float] = []
    frames_total = 0
    print(f"soak: {mode} mode, {args.minutes:g} simulated min at {args.rate:g} Hz, simulator speed {args.speed:g}, "
          f"sampled every {args.sample:g} s", flush=True)
    t0 = None
    next_sample = args.sample
    while True:
        rospy.rostime.wallsleep(1.0)
        if proc.poll() is not None:
            print("soak: roslaunch exited early")
            break
        now = rospy.get_time()
        if now <= 0:
            continue
        t0 = now if t0 is None else t0
        if now - t0 < next_sample and now - t0 < duration:
            continue
        with lock:
            got, poses[:] = list(poses), []
            keys = sorted(truth)
            frames_total += len(keys)
            errs = [float(np.hypot(x - truth[k][0], y - truth[k][1])) for k, x, y in got if k in truth]
            for k in keys[:-20]:  # keep the last frames: their poses may still be on the way
                del truth[k]
            frames_total -= min(20, len(keys))
            d = dict(diag)
        errors += errs
        rss = {name: rss_mb(pid) for name, pid in node_pids(master_uri).items()}
        sample = {"t_sim_s": round(now - t0, 1), "t_wall_s": round(time.time() - t_wall0, 1), "poses": len(got),
                  "err_cm_median": round(100 * float(np.median(errs)), 2) if errs else None,
                  "err_cm_max": round(100 * max(errs), 2) if errs else None,
                  "rss_mb": {k: round(v, 1) for k, v in rss.items() if v is not None},
                  "load_average": round(os.getloadavg()[0], 2),
                  "frames": d.get("frames"), "dropped_stale": d.get("dropped_stale"),
                  "latency_ms_median": d.get("latency_ms_median")}
        samples.append(sample)
        print(json.dumps(sample), flush=True)
        next_sample += args.sample
        if now - t0 >= duration:
            break
    frames_total += 20
    return report(args, mode, samples, errors, frames_total, time.time() - t_wall0)


def error_line(err: np.ndarray, samples: List[dict]) -> str:
    if np.any(np.isfinite(err)):
        return (f"- position error over the run: median {100 * np.nanmedian(err):.2f} cm, p99 "
                f"{100 * np.nanpercentile(err, 99):.2f} cm, max {100 * np.nanmax(err):.2f} cm")
    med = [s["err_cm_median"] for s in samples if s.get("err_cm_median") is not None]
    mx = [s["err_cm_max"] for s in samples if s.get("err_cm_max") is not None]
    return (f"- position error over the run (from the per-sample figures): median of the sample medians "
            f"{np.median(med):.2f} cm, max {max(mx):.2f} cm" if med else "- position error: no poses")


def load_line(samples: List[dict]) -> str:
    """The machine's 1-minute load average over the run (the run's own nodes included)."""
    loads = [s["load_average"] for s in samples if s.get("load_average") is not None]
    if not loads:
        return "- load average: not recorded"
    return (f"- load average (1 min, this run's nodes included) over the samples: median {np.median(loads):.1f}, "
            f"min {min(loads):.1f}, max {max(loads):.1f}")


def report(args, mode, samples, errors, frames_total, wall) -> int:
    def node_series(name):
        return [(s["t_sim_s"], s["rss_mb"].get(name)) for s in samples if s["rss_mb"].get(name) is not None]

    nodes = sorted({n for s in samples for n in s["rss_mb"]})
    warm = WARMUP_FRACTION * samples[-1]["t_sim_s"] if samples else 0.0
    rows = ["| node | RSS after warm-up (MB) | RSS at end (MB) | growth after warm-up (MB/h, fit) |",
            "|---|---:|---:|---:|"]
    growth = {}
    for n in nodes:
        series = [(t, v) for t, v in node_series(n) if t >= warm]
        if len(series) >= 2:
            ts, vs = np.array(series).T
            slope = float(np.polyfit(ts / 3600.0, vs, 1)[0]) if np.ptp(ts) > 0 else 0.0
        else:
            slope = float("nan")
        growth[n] = slope
        first = series[0][1] if series else float("nan")
        last = series[-1][1] if series else float("nan")
        rows.append(f"| `{n}` | {first:.1f} | {last:.1f} | {slope:+.1f} |")
    received = sum(s["poses"] for s in samples)
    last = samples[-1] if samples else {}
    dropped = int(last.get("dropped_stale") or 0)
    err = np.array(errors) if errors else np.array([np.nan])
    sim_s = samples[-1]["t_sim_s"] if samples else 0.0
    flat = all(np.isfinite(g) and g < FLAT_MB_PER_H for n, g in growth.items() if n.endswith("localizer"))
    md = "\n".join([
        f"Soak run: mode `{mode}`, {sim_s / 60:.1f} simulated minutes at {args.rate:g} Hz "
        f"({frames_total} ring frames) in {wall / 60:.1f} wall minutes (real-time ratio {sim_s / max(wall, 1e-9):.2f}), "
        f"{datetime.datetime.utcnow():%Y-%m-%d}.",
        "",
        *rows,
        "",
        f"- poses received: {received} of {frames_total} frames ({100.0 * received / max(frames_total, 1):.1f}%); "
        f"localizer's own count of stale frames dropped: {dropped}; latency median "
        f"{last.get('latency_ms_median')} ms",
        error_line(err, samples),
        load_line(samples),
        f"- memory flat after warm-up (the first {100 * WARMUP_FRACTION:.0f}% of the run; localizer growth < "
        f"{FLAT_MB_PER_H:g} MB/h): {'yes' if flat else 'NO'}",
    ])
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "soak.json"), "w") as handle:
        json.dump({"mode": mode, "args": vars(args), "wall_s": wall, "frames": frames_total, "poses": received,
                   "errors_cm": [round(100 * e, 3) for e in errors],
                   "dropped_stale": dropped, "growth_mb_per_h": growth, "samples": samples, "markdown": md},
                  handle, indent=1)
    print(md)
    return 0 if flat else 1


if __name__ == "__main__":
    sys.exit(main())
