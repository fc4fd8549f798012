"""Instructions per ring frame of the localization core: a measure the host's speed does not move.

A tool beside ``bench_localization.py`` (not a section of ``bench/run.py``). On this shared machine
the CPU time of the same code moves by half within minutes (docs/benchmarks.md, Localization), so
two versions of the core a few per cent apart cannot be told apart by ``loc_ms_median``, however
often they are alternated. The number of instructions the CPU executes for the same frames hardly
moves (0.2 % between runs here): it says whether a change does less work, though not how much time
that saves (cache misses and branch mispredictions are not counted), so a cut it shows is then
confirmed with the timed benchmark.

What is counted: the configuration of ``loc_ms_median`` (bench_localization: the kind lab's test
poses, corners mode at 0.3 px, the ring-file extrinsics, the 10-marker map, joint fusion, the
node's defaults, one BLAS and one OpenCV thread, the track started at each test pose), the first
``--frames`` of its 600 latency frames after 10 warm-up frames, through
``pipeline.feed_ring_frame``. The frames are simulated in this process and handed to a child
process run under valgrind's callgrind, which counts only inside the loop over the frames (the loop
is started through ``PyRun_SimpleString``, the function callgrind toggles its collection on:
imports and set-up are not counted). Hash randomisation is off in the child
(``PYTHONHASHSEED=0``), so that set and dict orders repeat.

Printed (JSON): ``core_instructions_per_ring_frame`` (thousands), the frames, the frames the
moved-marker check ran on (about half: ``marker_check/rate`` 5 Hz on the 10 Hz frames), and the
valgrind version. With ``--callgrind-out PATH`` the profile is kept (``callgrind_annotate PATH``:
per C function, numpy's and the interpreter's).

Run: ``source .ws/env.sh; python bench/core_instructions.py --frames 300`` (about 80 s for 300
frames; valgrind: ``apt-get install valgrind``). Compare two checkouts by running each one's copy.
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import re
import shutil
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

#: the C function the child runs the loop in: callgrind collects only while inside it
TOGGLE = "PyRun_SimpleStringFlags"


def _frames(path: str) -> None:
    """The latency frames and the 10-marker map of ``loc_ms_median``, pickled to ``path``."""
    import bench_localization as bl
    from aruco_ring_localization.ring import CameraRing
    from aruco_ring_localization.simulation.params import lab_config
    from aruco_ring_localization.simulation.ring_sim import perturb_ring
    from aruco_ring_localization.simulation.scene import Scene, resolve_scene_file

    ring = CameraRing.load(bl.RING_FILE)
    true_ring = perturb_ring(ring, seed=bl.RIG_SEED)
    # (bench_localization.run: the map grown from the harsh lab's truth, the frames from the kind lab)
    truth = Scene.load(resolve_scene_file(lab_config("harsh").scene.file)).truth_map()
    frames = bl._latency_frames(Scene.default(), true_ring, 600)
    with open(path, "wb") as handle:
        pickle.dump((bl._grown_map(truth, 10), frames), handle)


def _child(path: str, n: int) -> None:
    """Under callgrind: the pipeline over the first ``n`` frames, the loop alone counted."""
    import ctypes
    import logging

    import cv2
    from threadpoolctl import threadpool_limits

    import bench_localization as bl
    from aruco_ring_localization.pipeline import feed_ring_frame
    from aruco_ring_localization.ring import CameraRing

    cv2.setNumThreads(1)
    limits = threadpool_limits(limits=1)
    logging.disable(logging.WARNING)   # the track restarts at each pose: its warning is expected
    with open(path, "rb") as handle:
        marker_map, frames = pickle.load(handle)
    p = bl._pipeline(CameraRing.load(bl.RING_FILE), marker_map, fusion="joint")
    for _, T, f in frames[:10]:   # warm-up, as the timed benchmark's
        p.on_initial_pose(T, f.stamp)
        feed_ring_frame(p, f)
    p.reset()
    check = p.marker_check
    before = 0 if check is None else check.frames_checked
    state = {"pose": None}

    def loop() -> None:
        for i, T, f in frames[:n]:
            if i != state["pose"]:
                p.on_initial_pose(T, f.stamp)
                state["pose"] = i
            feed_ring_frame(p, f)

    sys.modules["__main__"].__dict__["_core_loop"] = loop
    # PyRun_SimpleString (the ABI's) calls PyRun_SimpleStringFlags, whose entry callgrind sees.
    if ctypes.pythonapi.PyRun_SimpleString(b"_core_loop()") != 0:
        raise SystemExit("the loop over the frames raised (its traceback is above)")
    print(json.dumps({"checked": 0 if check is None else check.frames_checked - before}))
    del limits


def _total(out_file: str) -> int:
    """The instructions recorded in a callgrind output file (its ``summary:`` or ``totals:`` line)."""
    with open(out_file, encoding="utf-8", errors="replace") as handle:
        for line in handle:
            if line.startswith(("summary:", "totals:")):
                return int(line.split()[1])
    raise SystemExit(f"{out_file}: no instruction count in the callgrind output")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="latency frames counted (of 600; default 300)")
    ap.add_argument("--callgrind-out", default="", help="keep callgrind's profile at this path")
    ap.add_argument("--child", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        _child(args.child, args.frames)
        return
    if not 1 <= args.frames <= 590:
        ap.error(f"--frames: expected 1 to 590, got {args.frames}")
    valgrind = shutil.which("valgrind")
    if valgrind is None:
        raise SystemExit("core_instructions: valgrind is not installed (apt-get install valgrind)")
    version = subprocess.run([valgrind, "--version"], capture_output=True, text=True, check=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="core_instructions_") as tmp:
        frames = os.path.join(tmp, "frames.pkl")
        _frames(frames)
        out_file = args.callgrind_out or os.path.join(tmp, "callgrind.out")
        env = dict(os.environ, PYTHONHASHSEED="0")
        run = subprocess.run([valgrind, "--tool=callgrind", "--collect-atstart=no", f"--toggle-collect={TOGGLE}",
                              f"--callgrind-out-file={out_file}", sys.executable, os.path.abspath(__file__),
                              "--child", frames, "--frames", str(args.frames)],
                             capture_output=True, text=True, env=env)
        if run.returncode != 0:
            sys.stderr.write(run.stderr[-4000:])
            raise SystemExit(f"core_instructions: the child under valgrind exited {run.returncode}")
        found = re.findall(r"^\{.*\}$", run.stdout, flags=re.M)
        if not found:
            raise SystemExit(f"core_instructions: no result from the child: {run.stdout[-2000:]}")
        checked = json.loads(found[-1])["checked"]
        total = _total(out_file)
    if total == 0:
        raise SystemExit(f"core_instructions: callgrind counted nothing (it did not see {TOGGLE} entered)")
    print(json.dumps({"core_instructions_per_ring_frame": round(total / args.frames / 1000.0, 1),
                      "unit": "thousands", "frames": args.frames, "frames_checked": checked,
                      "valgrind": version}))


if __name__ == "__main__":
    main()
