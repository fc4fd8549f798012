"""The mapper's save path (``MapBuilder.save_map``, what ``~save_map`` and ``save_on_shutdown``
call) SIGKILLed at seeded instants while it maps and saves again and again: the map file and its
``.bak`` always load whole, with every mapped marker. Same method as test_data_safety.py (which
covers ``MarkerMap.save`` alone on a big map): a forked child, killed within its first saves.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
import time

import numpy as np
import pytest

from aruco_ring_localization.mapping import MapBuilder
from aruco_ring_localization.marker_map import MarkerMap
from aruco_ring_localization.markers import MarkerSizes
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene

from helpers import RING_YAML

KILLS = 12


def _builder():
    ring = CameraRing.load(str(RING_YAML))
    scene = Scene.default()
    sim = RingSimulator(scene, perturb_ring(ring, seed=5), pixel_noise=0.3, seed=6)
    b = MapBuilder(ring, MarkerSizes(0.2), method="paper")
    poses = [Scene.T_world_base(p) for p in scene.mapping_stations[:2]]
    for k, T in enumerate(poses):
        b.add_frame(sim.observe(T, stamp=0.1 * k), station=k)
    return b, sim, poses


def _map_and_save_forever(b: MapBuilder, sim: RingSimulator, poses, path: str, saves) -> None:  # forked child
    k = 0
    while True:
        # The mapper keeps receiving frames between saves: each save writes a different map.
        b.add_frame(sim.observe(poses[k % len(poses)], stamp=1.0 + 0.1 * k), station=k % len(poses))
        b.save_map(path)
        k += 1
        saves.value = k


def _check_whole(path: str, ids) -> int:
    m = MarkerMap.load(path)
    assert sorted(m.ids) == sorted(ids), f"{path}: markers {sorted(m.ids)}, expected {sorted(ids)}"
    assert m.reference_marker in m, f"{path}: reference {m.reference_marker} not in the map"
    return sum(e.observations for e in m)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_sigkill_while_mapping_and_saving_leaves_a_loadable_map(tmp_path):
    path = str(tmp_path / "map.yaml")
    b, sim, poses = _builder()
    t0 = time.perf_counter()
    ids = b.save_map(path).ids
    cycle_s = time.perf_counter() - t0
    rng = np.random.default_rng(20261122)
    ctx = multiprocessing.get_context("fork")  # the child inherits the builder and its frames
    totals = [_check_whole(path, ids)]
    for k in range(KILLS):
        saves = ctx.Value("i", 0)
        child = ctx.Process(target=_map_and_save_forever, args=(b, sim, poses, path, saves))
        child.start()
        if k % 2:
            # Every other kill after the child's first complete save, so that on a loaded machine
            # (where forking alone can outlast a few saves) some kills still land on a new map.
            deadline = time.monotonic() + 60.0
            while saves.value < 1 and time.monotonic() < deadline and child.is_alive():
                time.sleep(0.001)
            assert saves.value >= 1, "the child saved nothing in 60 s"
        time.sleep(float(rng.uniform(0.0, 3.0 * cycle_s)))
        os.kill(child.pid, signal.SIGKILL)
        child.join(5.0)
        assert child.exitcode == -signal.SIGKILL, f"child exit code {child.exitcode}"
        totals.append(_check_whole(path, ids))
        if os.path.exists(path + ".bak"):
            _check_whole(path + ".bak", ids)
    assert sorted(f for f in os.listdir(tmp_path) if f.endswith((".yaml", ".bak"))) == ["map.yaml", "map.yaml.bak"]
    # Some kills landed after a save completed (a new map), some before: the test exercised saving.
    assert len(set(totals)) > 1, f"every kill left the first map (observations {totals[0]}): nothing was saved"
