"""Map loading benchmark: ``MarkerMap.load`` of a 5,000-marker map (target <= 1 s).

A synthetic map of N markers (random poses in a 100 m hall, as the mapper writes them: YAML with
flow-style lists, 1.2 MB for 5,000 markers) is saved and loaded again. Reported: the CPU time
(process time: utime + stime of this process, more robust than wall time on a shared machine)
of the fastest of the repetitions, and, as the reference measured in the same run, the same file
through PyYAML's full safe loader (the C parser; the loader before issue 14) and the marker list
checked one marker at a time (the fallback that names a bad key).
"""
from __future__ import annotations

import os
import sys
import tempfile
import time

import numpy as np
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))

from aruco_ring_localization import marker_map as mm  # noqa: E402
from aruco_ring_localization.camera import _UniqueKeyLoader  # noqa: E402
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap  # noqa: E402

from aruco_ring_localization import geometry as geo  # noqa: E402


def synthetic_map(n: int, seed: int = 0) -> MarkerMap:
    rng = np.random.default_rng(seed)
    m = MarkerMap(frame_id="map", reference_marker=0, method="refined")
    for i in range(n):
        T = geo.make_transform(geo.matrix_from_rpy(*rng.uniform(-np.pi, np.pi, 3)), rng.uniform(0, 100, 3))
        m.add(MarkerEntry(i, T, 0.2, rng.uniform(0, 0.003, 3), rng.uniform(0, 0.003, 3), int(rng.integers(1, 500))))
    return m


def cpu(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def run(quick: bool = False) -> dict:
    repeat = 2 if quick else 5
    rows = []
    results = {}
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        for n in (1000, 5000):
            path = os.path.join(tmp, f"map{n}.yaml")
            synthetic_map(n).save(path)
            size_mb = os.path.getsize(path) / 1e6
            t_load = cpu(lambda: MarkerMap.load(path), repeat)
            with open(path, encoding="utf-8") as fh:
                text = fh.read()
            t_full = cpu(lambda: MarkerMap.from_dict(yaml.load(text, Loader=_UniqueKeyLoader)), repeat)
            vectorised = mm._add_all_vectorised
            mm._add_all_vectorised = lambda out, markers: False
            try:
                t_slow = cpu(lambda: MarkerMap.load(path), max(1, repeat // 2))
            finally:
                mm._add_all_vectorised = vectorised
            rows.append(f"| {n} | {size_mb:.2f} | {t_load:.3f} | {t_full:.3f} | {t_slow:.3f} |")
            results[f"map_load_s_{n}_markers"] = round(t_load, 4)
            results[f"map_load_s_{n}_markers_full_yaml_loader"] = round(t_full, 4)
    load1 = os.getloadavg()[0]
    md = "\n".join([
        "## Map loading",
        "",
        "`MarkerMap.load` of synthetic maps as the mapper writes them, CPU time of this process (best of "
        f"{repeat}), load average {load0:.1f} -> {load1:.1f} during the run. Reference in the same run: the "
        "same file through PyYAML's full safe loader (C parser; the loader before issue 14), and the fast "
        "YAML route with the marker list checked one marker at a time (the path that names a bad key).",
        "",
        "| markers | file (MB) | load (s CPU) | full PyYAML loader + checks (s CPU) | one marker at a time (s CPU) |",
        "|---:|---:|---:|---:|---:|",
        *rows,
        "",
        "Target: `map_load_s_5000_markers` <= 1 s.",
    ])
    return {"results": results, "markdown": md}


if __name__ == "__main__":
    out = run(quick="--quick" in sys.argv)
    print(out["markdown"])
