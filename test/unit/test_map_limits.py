"""Map files a hostile or broken writer could hand us (issue 14, F6, F7): a size limit, absurd
coordinates, the fast YAML route giving exactly the full loader's result, the vectorised marker
list giving exactly the one-by-one result, and N generations of backups."""
from __future__ import annotations

import math
import os
from dataclasses import replace

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from aruco_ring_localization import camera as camera_mod
from aruco_ring_localization import geometry as geo
from aruco_ring_localization import marker_map as mm
from aruco_ring_localization.camera import _UniqueKeyLoader, _fast_safe_load, _Unusual, load_yaml_file
from aruco_ring_localization.errors import ConfigError, MapSanityError
from aruco_ring_localization.fileio import atomic_write_text, backup_paths
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap

from fuzz_support import FUZZ
from helpers import REPO, random_transform


def _map(n: int, seed: int = 0) -> MarkerMap:
    rng = np.random.default_rng(seed)
    m = MarkerMap(frame_id="map", reference_marker=0)
    for i in range(n):
        m.add(MarkerEntry(i, random_transform(rng, 50.0), float(rng.uniform(0.05, 0.3)),
                          rng.uniform(0, 0.01, 3), rng.uniform(0, 0.01, 3), int(rng.integers(0, 500))))
    return m


def _same(a, b) -> bool:
    """Equal values and types, NaN equal to NaN, -0.0 not equal to 0.0, dict key order included."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return (math.isnan(a) and math.isnan(b)) or (a == b and math.copysign(1, a) == math.copysign(1, b))
    if isinstance(a, dict):
        return list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def _full(text):
    try:
        return "ok", yaml.load(text, Loader=_UniqueKeyLoader)
    except Exception as exc:  # noqa: BLE001 - compared by type
        return "error", type(exc)


def _fast(text):
    try:
        return "ok", _fast_safe_load(text)
    except _Unusual:
        return "full", _full(text)  # what load_yaml_file then does
    except Exception as exc:  # noqa: BLE001
        return "error", type(exc)


# --- the fast YAML route ----------------------------------------------------------------------------

def test_fast_route_gives_the_full_loaders_result_on_every_file_of_the_package(tmp_path):
    files = sorted(REPO.glob("config/**/*.yaml")) + sorted(REPO.glob("test/data/**/*.yaml"))
    path = tmp_path / "map.yaml"
    _map(50).save(str(path))
    files.append(path)
    assert len(files) > 10
    for f in files:
        text = f.read_text()
        kind, got = _fast(text)
        assert kind == "ok", f"{f}: the fast route gave up"
        assert _same(got, yaml.load(text, Loader=_UniqueKeyLoader)), f


EDGE_CASES = [
    "a: 1\nb: -0.0\nc: 1_000\nd: 012\ne: 0x1f\nf: 1:20\ng: .5\nh: .inf\ni: -.inf\nj: .nan\nk: yes\nl: ~\n"
    "m: ''\nn: '1.5'\no: 1e5\np: 1.e+5\nq: +7\nr: -0\ns: null\nt: [1, 2.5, x]\nw: |\n  text\n",
    "u: &A {x: 1}\nv: *A\n", "- 1\n- [2, [3]]\n", "a: 2026-11-22\n", "a: !!str 1\n", "<<: {a: 1}\n",
    "a: 1\na: 2\n", "---\na: 1\n---\nb: 2\n", "a: [1, 2", "? [1, 2]\n: 3\n", "1: a\n1.0: b\n", "", "# c\n",
    "~\n", "a: *nope\n", "a: !!binary aGVsbG8=\n", "a: !custom 1\n", "[" * 200 + "]" * 200,
    "a: b\n  c: d\n", "a: 0b101\nb: 1_0.5_0\nc: 09\nd: 190:20:30.15\n",
]


@pytest.mark.parametrize("text", EDGE_CASES)
def test_fast_route_matches_the_full_loader_or_hands_over(text):
    kind, got = _fast(text)
    ref = _full(text)
    if kind == "full":
        return  # the full loader decides, by construction the same
    assert kind == ref[0], (text, got, ref)
    if kind == "ok":
        assert _same(got, ref[1]), (got, ref[1])
    else:
        assert got is ref[1] or issubclass(got, yaml.YAMLError) and issubclass(ref[1], yaml.YAMLError)


def test_aliases_are_shared_as_the_full_loader_shares_them():
    data = _fast_safe_load("a: &x [1, 2]\nb: *x\n")
    assert data["a"] is data["b"]
    loop = _fast_safe_load("a: &x [1, *x]\n")["a"]   # a recursive list, as PyYAML builds it
    assert loop[1] is loop and yaml.load("a: &x [1, *x]\n", Loader=_UniqueKeyLoader)["a"][1] is not None


scalars = (st.integers(-10 ** 12, 10 ** 12) | st.floats(allow_nan=True, allow_infinity=True) | st.booleans()
           | st.none() | st.text(max_size=12))
documents = st.recursive(scalars, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6) | st.integers(),
                                                                                       c, max_size=4), max_leaves=25)


@settings(FUZZ)
@given(documents, st.sampled_from([None, True, False]), st.booleans())
def test_fuzz_fast_route_equals_full_loader(doc, flow, sort_keys):
    text = yaml.safe_dump(doc, default_flow_style=flow, sort_keys=sort_keys)
    kind, got = _fast(text)
    if kind == "ok":
        assert _same(got, yaml.load(text, Loader=_UniqueKeyLoader)), text


# --- limits -------------------------------------------------------------------------------------

def test_a_map_file_beyond_the_size_limit_is_refused_unread(tmp_path, monkeypatch):
    path = tmp_path / "big.yaml"
    _map(200).save(str(path))
    size = os.path.getsize(path)
    monkeypatch.setattr(mm, "MAX_MAP_FILE_BYTES", size - 1)
    calls = []
    monkeypatch.setattr(camera_mod, "_fast_safe_load", lambda text: calls.append(1))
    with pytest.raises(ConfigError, match="MiB") as info:
        MarkerMap.load(str(path))
    assert info.value.path == str(path) and not calls, "parsed although too large"
    monkeypatch.undo()
    monkeypatch.setattr(mm, "MAX_MAP_FILE_BYTES", size)
    assert len(MarkerMap.load(str(path))) == 200
    monkeypatch.undo()
    assert mm.MAX_MAP_FILE_BYTES > 10 * size / 200 * 5000, "a 5,000-marker map must fit, with a margin"


def test_other_yaml_files_have_their_own_limit(tmp_path):
    path = tmp_path / "ring.yaml"
    path.write_text("a: 1\n" + "#" * (camera_mod.MAX_YAML_FILE_BYTES + 1))
    with pytest.raises(ConfigError, match="more than the 4 MiB"):
        load_yaml_file(str(path))


@pytest.mark.parametrize("value", ["1e308", "-2.0e5", "1.0e+300", "inf"])
def test_a_marker_at_absurd_coordinates_is_refused_naming_the_key(tmp_path, value):
    path = tmp_path / "map.yaml"
    _map(5).save(str(path))
    data = yaml.safe_load(path.read_text())
    data["markers"][3]["translation"][1] = float(value)
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as info:
        MarkerMap.load(str(path))
    assert info.value.key in ("markers[3].translation", "markers[3]"), info.value
    # A map built in memory (a diverged adjustment) is refused when saved, by the sanity checks.
    far = _map(5)
    far.add(MarkerEntry(1, geo.make_transform(t=[0.0, 2e5, 0.0]), 0.2))
    with pytest.raises(MapSanityError, match="extent"):
        far.save(str(path))


def test_vectorised_marker_list_gives_exactly_the_one_by_one_map(tmp_path, monkeypatch):
    path = tmp_path / "map.yaml"
    m = _map(300, seed=4)
    for i in (3, 7):   # the optional keys the mapper writes
        m.add(replace(m[i], ambiguous=True, rms_px=0.1 * i))
    m.save(str(path))
    fast = MarkerMap.load(str(path))
    monkeypatch.setattr(mm, "_add_all_vectorised", lambda out, markers: False)
    slow = MarkerMap.load(str(path))
    assert fast.ids == slow.ids and len(fast) == 300
    for i in fast.ids:
        a, b = fast[i], slow[i]
        assert np.allclose(a.T_map_marker, b.T_map_marker, rtol=0, atol=1e-15)
        assert np.allclose(fast.corners(i), slow.corners(i), rtol=0, atol=1e-13)
        assert (a.size, a.observations, a.ambiguous, a.rms_px) == (b.size, b.observations, b.ambiguous, b.rms_px)
        assert np.array_equal(a.position_std, b.position_std) and np.array_equal(a.rotation_std, b.rotation_std)


def test_one_bad_marker_among_many_still_names_its_key(tmp_path):
    path = tmp_path / "map.yaml"
    _map(100).save(str(path))
    text = path.read_text().replace("size: ", "size: -", 1)
    path.write_text(text)
    with pytest.raises(ConfigError, match=r"markers\[0\]\.size"):
        MarkerMap.load(str(path))


# --- backups ------------------------------------------------------------------------------------

def test_n_generations_of_backups_newest_first(tmp_path):
    path = str(tmp_path / "map.yaml")
    for k in range(7):
        atomic_write_text(path, f"version {k}\n", backups=3)
    baks = backup_paths(path, 3)
    assert [os.path.basename(b) for b in baks] == ["map.yaml.bak", "map.yaml.bak.2", "map.yaml.bak.3"]
    assert [open(b).read() for b in [path] + baks] == [f"version {k}\n" for k in (6, 5, 4, 3)]
    assert not os.path.exists(path + ".bak.4")
    atomic_write_text(path, "version 7\n", backups=0)
    assert open(baks[0]).read() == "version 5\n", "backups=0 must leave the backups alone"


def test_a_smaller_map_saved_over_a_larger_one_leaves_the_larger_one_recoverable(tmp_path):
    path = str(tmp_path / "map.yaml")
    _map(10).save(path, backups=5)
    for _ in range(3):
        _map(9).save(path, backups=5)
    lengths = [len(MarkerMap.load(p)) for p in [path] + backup_paths(path, 5) if os.path.exists(p)]
    assert lengths == [9, 9, 9, 10], lengths


def test_backups_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        path = str(tmp_path / "map.yaml")
        for _ in range(3):
            _map(3).save(path, backups=2)
    finally:
        os.umask(old)
    modes = {p: os.stat(p).st_mode & 0o777 for p in [path] + backup_paths(path, 2)}
    assert set(modes.values()) == {0o644}, modes


# --- YAML bombs ---------------------------------------------------------------------------------

def _bomb(levels: int) -> str:
    lines = ["format_version: 1", "a0: &a0 [1.0, 1.0, 1.0]"]
    lines += [f"a{k}: &a{k} [*a{k - 1}, *a{k - 1}, *a{k - 1}]" for k in range(1, levels + 1)]
    return "\n".join(lines + ["markers:", f"- {{id: 1, size: 0.2, translation: *a{levels}, rotation: [0, 0, 0, 1]}}"])


@pytest.mark.parametrize("text,needle", [
    (_bomb(24), "YAML bomb"),                        # 3^25 values: numpy would ask for terabytes
    ("format_version: 1\nmarkers: &m [*m]\n", "recursive"),
    ("format_version: 1\nx: &x !!python/none [*x]\nmarkers: []\n", ""),   # the full loader's own error
])
def test_yaml_bombs_and_recursive_aliases_are_refused_naming_the_file(tmp_path, text, needle):
    path = tmp_path / "bomb.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=needle) as info:
        MarkerMap.load(str(path))
    assert info.value.path == str(path)


def test_shared_aliases_of_reasonable_size_still_load(tmp_path):
    path = tmp_path / "map.yaml"
    _map(3).save(str(path))
    text = path.read_text().replace("position_std: [", "position_std: &s [", 1)
    path.write_text(text + "extra: [*s, *s]\n")
    assert len(MarkerMap.load(str(path))) == 3


# --- what held in the trials (kept holding) ---------------------------------------------------

def test_a_full_disk_is_a_clear_error_and_leaves_the_map_and_no_temporary(tmp_path, monkeypatch):
    import errno

    path = tmp_path / "map.yaml"
    _map(3).save(str(path))
    before = path.read_bytes()

    def full(_fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(ConfigError) as info:
        _map(4).save(str(path))
    assert str(path) in str(info.value) and "No space left on device" in str(info.value)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.yaml"]


def test_symlinked_and_impossible_map_paths(tmp_path):
    real = tmp_path / "real.yaml"
    _map(3).save(str(real))
    link = tmp_path / "link.yaml"
    link.symlink_to(real)
    assert len(MarkerMap.load(str(link))) == 3
    loop = tmp_path / "loop.yaml"
    loop.symlink_to(loop)
    for bad in (tmp_path, loop, real / "below_a_file.yaml", tmp_path / "missing" / "map.yaml"):
        with pytest.raises(ConfigError) as info:
            MarkerMap.load(str(bad))
        assert str(bad) in str(info.value)
    with pytest.raises(ConfigError) as info:
        _map(3).save(str(real / "below_a_file.yaml"))
    assert "below_a_file.yaml" in str(info.value)
