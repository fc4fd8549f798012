"""Data safety of the map file (issue 7 §4).

* A process repeatedly saving a big map (``MarkerMap.save``, what the mapper's ``~save_map`` and
  ``save_on_shutdown`` call) is SIGKILLed at seeded random instants, 20 times: afterwards the map
  file always loads, is one whole version (never a mix of two saves), and so does its ``.bak``.
* Maps, rings and scenes of another format version fail with a message naming ``format_version``.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
import time

import numpy as np
import pytest
import yaml

from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.marker_map import MapSanityLimits, MAP_FORMAT_VERSION, MarkerEntry, MarkerMap
from aruco_ring_localization.ring import CameraRing

from helpers import CONFIG, RING_YAML

N_MARKERS = 300
KILLS = 20


def _big_map(version: int) -> MarkerMap:
    """N_MARKERS markers; every translation's x equals ``version`` so a mixed file is detectable."""
    entries = []
    for i in range(N_MARKERS):
        T = np.eye(4)
        T[:3, 3] = (float(version), i * 0.01, 1.0)
        entries.append(MarkerEntry(i, T, 0.2, np.full(3, 1e-3), np.full(3, 1e-3), 10 + version))
    return MarkerMap(entries, reference_marker=0, method=f"version {version}")


def _save_forever(path: str, start: int, saves) -> None:  # runs in the forked child
    version = start
    while True:
        # x counts the saves, beyond any hall: this test is about atomic writes, not the sanity checks.
        _big_map(version).save(path, MapSanityLimits(max_extent=1e12))
        version += 1
        saves.value = version - start


def _check_whole(path: str) -> int:
    m = MarkerMap.load(path)
    assert len(m) == N_MARKERS, f"{path}: {len(m)} markers, expected {N_MARKERS}"
    xs = {float(e.T_map_marker[0, 3]) for e in m}
    assert len(xs) == 1, f"{path} mixes saves: versions {sorted(xs)[:5]}"
    return int(xs.pop())


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_sigkill_during_repeated_saves_always_leaves_a_loadable_map(tmp_path):
    path = str(tmp_path / "map.yaml")
    t0 = time.perf_counter()
    _big_map(0).save(path)
    save_s = time.perf_counter() - t0
    rng = np.random.default_rng(20261122)
    ctx = multiprocessing.get_context("fork")  # the child inherits the imports: starts in ms
    versions = []
    for k in range(KILLS):
        saves = ctx.Value("i", 0)
        child = ctx.Process(target=_save_forever, args=(path, 1000 * (k + 1), saves))
        child.start()
        if k % 2:
            # Every other kill after the child's first complete save, so that on a loaded machine
            # (where forking alone can outlast a few saves) some kills still land on a new version.
            deadline = time.monotonic() + 60.0
            while saves.value < 1 and time.monotonic() < deadline and child.is_alive():
                time.sleep(0.001)
            assert saves.value >= 1, "the child saved nothing in 60 s"
        # Kill anywhere within the first few saves (a save takes save_s; the instant is seeded).
        time.sleep(float(rng.uniform(0.0, 2.5 * save_s)))
        os.kill(child.pid, signal.SIGKILL)
        child.join(5.0)
        assert child.exitcode == -signal.SIGKILL, f"child exit code {child.exitcode}"
        versions.append(_check_whole(path))
        if os.path.exists(path + ".bak"):
            _check_whole(path + ".bak")
    # Temporary files of interrupted saves are left beside the map (at most one per kill), never
    # mistaken for it; the map and its backup are the only *.yaml files.
    leftovers = [f for f in os.listdir(tmp_path) if f.endswith(".tmp")]
    assert len(leftovers) <= KILLS, leftovers
    assert sorted(f for f in os.listdir(tmp_path) if f.endswith((".yaml", ".bak"))) == ["map.yaml", "map.yaml.bak"]
    # The kills did land both between and inside saves: some runs left a new version, some not.
    assert len(set(versions)) > 1, f"every kill left version {versions[0]}: the test did not exercise saving"


def _map_text(version) -> str:
    d = _big_map(3).to_dict()
    d["markers"] = d["markers"][:2]
    d["format_version"] = version
    return yaml.safe_dump(d, sort_keys=False)


@pytest.mark.parametrize("version", [0, MAP_FORMAT_VERSION + 1, 99, "1", 1.5])
def test_map_of_another_format_version_fails_naming_format_version(tmp_path, version):
    path = tmp_path / "old_map.yaml"
    path.write_text(_map_text(version))
    with pytest.raises(ConfigError) as info:
        MarkerMap.load(str(path))
    msg = str(info.value)
    assert str(path) in msg and "format_version" in msg and repr(version) in msg, msg


def test_map_without_format_version_says_what_it_is(tmp_path):
    path = tmp_path / "map.yaml"
    d = yaml.safe_load(_map_text(1))
    del d["format_version"]
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(ConfigError, match="format_version") as info:
        MarkerMap.load(str(path))
    assert str(path) in str(info.value)


def test_current_format_version_round_trips(tmp_path):
    path = tmp_path / "map.yaml"
    path.write_text(_map_text(MAP_FORMAT_VERSION))
    assert len(MarkerMap.load(str(path))) == 2


def test_ring_and_scene_of_another_format_version(tmp_path):
    from aruco_ring_localization.simulation.scene import Scene

    ring = yaml.safe_load(RING_YAML.read_text())
    ring["format_version"] = 2
    for c in ring["cameras"]:
        c["camera_info"] = str(CONFIG / c["camera_info"])
    rpath = tmp_path / "ring.yaml"
    rpath.write_text(yaml.safe_dump(ring))
    scene = yaml.safe_load((CONFIG / "lab_scene.yaml").read_text())
    scene["format_version"] = 2
    spath = tmp_path / "scene.yaml"
    spath.write_text(yaml.safe_dump(scene))
    for path, loader in ((rpath, CameraRing.load), (spath, Scene.load)):
        with pytest.raises(ConfigError) as info:
            loader(str(path))
        msg = str(info.value)
        assert str(path) in msg and "format_version" in msg and "2" in msg, msg
