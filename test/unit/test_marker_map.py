"""Unit tests of marker_map.py: YAML and fiducial_slam round trips, atomic save, bad maps, map frame."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest
import yaml

from aruco_ring_localization import fileio
from aruco_ring_localization import geometry as geo
from aruco_ring_localization.errors import ConfigError, GeometryError
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap, map_frame_from_reference
from aruco_ring_localization.markers import marker_corners

from helpers import assert_close, assert_config_error_names, random_transform, write_text


def _sample_map(seed: int = 30, n: int = 6) -> MarkerMap:
    rng = np.random.default_rng(seed)
    entries = []
    for k in range(n):
        mid = int(3 * k + 1)
        entries.append(MarkerEntry(mid, random_transform(rng), float(rng.choice([0.1, 0.15, 0.2])),
                                   rng.uniform(0, 0.01, size=3), rng.uniform(0, 0.02, size=3), int(rng.integers(0, 500))))
    return MarkerMap(entries, frame_id="map", reference_marker=entries[0].marker_id,
                     frame_definition="origin below marker 1", method="refined", created="2026-01-02T03:04:05Z")


def _assert_maps_equal(a: MarkerMap, b: MarkerMap, tol: float = 1e-12) -> None:
    assert a.ids == b.ids
    assert (a.frame_id, a.reference_marker, a.frame_definition, a.method) == \
        (b.frame_id, b.reference_marker, b.frame_definition, b.method)
    for ea, eb in zip(a, b):
        assert_close(eb.T_map_marker, ea.T_map_marker, tol, f"marker {ea.marker_id} pose")
        assert eb.size == ea.size and eb.observations == ea.observations
        assert_close(eb.position_std, ea.position_std, 0.0, "position_std")
        assert_close(eb.rotation_std, ea.rotation_std, 0.0, "rotation_std")


# --- the container ------------------------------------------------------------------------------

def test_map_lookups_and_cached_corners():
    m = _sample_map()
    assert len(m) == 6 and m.ids == sorted(m.ids) and [e.marker_id for e in m] == m.ids
    assert 4 in m and 5 not in m and m.get(5) is None
    e = m[4]
    expected = geo.transform_points(e.T_map_marker, marker_corners(e.size))
    assert_close(m.corners(4), expected, 1e-12, "cached corners")
    assert_close(m.T_map_marker(4), e.T_map_marker, 0.0, "T_map_marker")
    m.remove(4)
    assert 4 not in m and len(m) == 5
    with pytest.raises(KeyError):
        m.corners(4)
    m.remove(4)  # removing twice is harmless


def test_add_replaces_and_updates_the_corner_cache():
    m = _sample_map()
    T = geo.transform_from_se2(1.0, 2.0, 0.5, z=1.0)
    m.add(MarkerEntry(4, T, 0.3))
    assert_close(m.corners(4), geo.transform_points(T, marker_corners(0.3)), 1e-12, "replaced corners")
    assert m[4].size == 0.3


@pytest.mark.parametrize("entry, needle", [
    (MarkerEntry(1, np.diag([1.0, 1.0, -1.0, 1.0]), 0.1), "marker 1 pose"),
    (MarkerEntry(2, np.full((4, 4), np.nan), 0.1), "marker 2 pose"),
    (MarkerEntry(3, np.eye(4), -0.1), "marker 3"),
    (MarkerEntry(4, np.eye(4), float("nan")), "marker 4"),
])
def test_add_validates(entry, needle):
    with pytest.raises(GeometryError) as info:
        MarkerMap().add(entry)
    assert needle in str(info.value), str(info.value)


# --- YAML ---------------------------------------------------------------------------------------

def test_yaml_save_load_round_trip(tmp_path):
    m = _sample_map()
    path = tmp_path / "maps" / "map.yaml"
    m.save(str(path))
    again = MarkerMap.load(str(path))
    _assert_maps_equal(m, again)
    assert again.created == "2026-01-02T03:04:05Z"
    assert path.read_text().startswith("#")
    raw = yaml.safe_load(path.read_text())
    assert raw["format_version"] == 1 and len(raw["markers"]) == 6


def test_save_fills_in_created_and_an_empty_map_round_trips(tmp_path):
    path = tmp_path / "empty.yaml"
    MarkerMap().save(str(path))
    again = MarkerMap.load(str(path))
    assert len(again) == 0 and again.created.endswith("Z") and again.reference_marker is None


def test_save_is_atomic_and_keeps_the_previous_file_as_bak(tmp_path):
    path = tmp_path / "map.yaml"
    first = _sample_map(seed=1)
    first.save(str(path))
    first_text = path.read_text()
    assert not (tmp_path / "map.yaml.bak").exists()
    second = _sample_map(seed=2)
    second.save(str(path))
    assert (tmp_path / "map.yaml.bak").read_text() == first_text
    _assert_maps_equal(MarkerMap.load(str(path)), second)
    _assert_maps_equal(MarkerMap.load(str(tmp_path / "map.yaml.bak")), first)
    second_text = path.read_text()
    _sample_map(seed=3).save(str(path))
    assert (tmp_path / "map.yaml.bak").read_text() == second_text
    # No temporary files are left behind.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.yaml", "map.yaml.bak"]


def test_failed_rename_leaves_the_old_file_intact(tmp_path, monkeypatch):
    path = tmp_path / "map.yaml"
    _sample_map(seed=1).save(str(path))
    old_text = path.read_text()

    def failing_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(fileio.os, "replace", failing_replace)
    with pytest.raises(ConfigError) as info:
        _sample_map(seed=2).save(str(path))
    assert str(path) in str(info.value) and "No space left" in str(info.value), str(info.value)
    assert path.read_text() == old_text
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")], list(tmp_path.iterdir())


def test_failed_write_leaves_the_old_file_intact(tmp_path, monkeypatch):
    path = tmp_path / "map.yaml"
    _sample_map(seed=1).save(str(path))
    old_text = path.read_text()

    def failing_fsync(fd):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(fileio.os, "fsync", failing_fsync)
    with pytest.raises(ConfigError):
        _sample_map(seed=2).save(str(path))
    assert path.read_text() == old_text
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_interrupted_save_leaves_the_old_file_intact(tmp_path, monkeypatch):
    path = tmp_path / "map.yaml"
    _sample_map(seed=1).save(str(path))
    old_text = path.read_text()

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(fileio.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _sample_map(seed=2).save(str(path))
    assert path.read_text() == old_text
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root ignores directory permissions")
def test_read_only_directory(tmp_path):
    path = tmp_path / "map.yaml"
    _sample_map(seed=1).save(str(path))
    old_text = path.read_text()
    tmp_path.chmod(0o500)
    try:
        with pytest.raises(ConfigError) as info:
            _sample_map(seed=2).save(str(path))
        assert str(tmp_path) in str(info.value)
    finally:
        tmp_path.chmod(0o700)
    assert path.read_text() == old_text


def test_atomic_write_text_without_backup(tmp_path):
    path = tmp_path / "a.txt"
    fileio.atomic_write_text(str(path), "one")
    fileio.atomic_write_text(str(path), "two", keep_backup=False)
    assert path.read_text() == "two" and not (tmp_path / "a.txt.bak").exists()


# --- bad YAML maps -------------------------------------------------------------------------

def _map_text(mutate=None) -> str:
    data = _sample_map().to_dict()
    if mutate:
        mutate(data)
    return yaml.safe_dump(data)


def _marker(i, key, value=None, delete=False):
    def mutate(data):
        if delete:
            del data["markers"][i][key]
        else:
            data["markers"][i][key] = value
    return mutate


def _top(key, value=None, delete=False):
    def mutate(data):
        if delete:
            del data[key]
        else:
            data[key] = value
    return mutate


def _duplicate(data):
    data["markers"][3]["id"] = data["markers"][1]["id"]


BAD_MAPS = {
    "empty": ("", None),
    "invalid-yaml": ("markers: [\n", None),
    "a-list": ("- 1\n", None),
    "fiducial-slam-text": ("1 0 0 0 0 0 0 0.1 3\n", None),
    "no-version": (_map_text(_top("format_version", delete=True)), "format_version"),
    "wrong-version": (_map_text(_top("format_version", 7)), "format_version"),
    "no-markers": (_map_text(_top("markers", delete=True)), "markers"),
    "markers-not-list": (_map_text(_top("markers", {"a": 1})), "markers"),
    "duplicate-ids": (_map_text(_duplicate), "markers[3].id"),
    "negative-size": (_map_text(_marker(2, "size", -0.1)), "markers[2].size"),
    "zero-size": (_map_text(_marker(2, "size", 0)), "markers[2].size"),
    "missing-size": (_map_text(_marker(2, "size", delete=True)), "markers[2].size"),
    "missing-rotation": (_map_text(_marker(1, "rotation", delete=True)), "markers[1].rotation"),
    "missing-translation": (_map_text(_marker(1, "translation", delete=True)), "markers[1].translation"),
    "bad-quaternion": (_map_text(_marker(4, "rotation", [0, 0, 0, 3])), "markers[4]"),
    "negative-id": (_map_text(_marker(0, "id", -1)), "markers[0].id"),
    "string-id": (_map_text(_marker(0, "id", "seven")), "markers[0].id"),
    "negative-std": (_map_text(_marker(5, "position_std", [0.1, -0.1, 0.1])), "markers[5].position_std"),
    "short-std": (_map_text(_marker(5, "rotation_std", [0.1, 0.1])), "markers[5].rotation_std"),
    "bad-observations": (_map_text(_marker(5, "observations", -3)), "markers[5].observations"),
    "reference-not-in-map": (_map_text(_top("reference_marker", 999)), "reference_marker"),
    "reference-not-int": (_map_text(_top("reference_marker", "a")), "reference_marker"),
    "empty-frame": (_map_text(_top("frame_id", "")), "frame_id"),
    "marker-not-mapping": (_map_text(lambda d: d["markers"].append(5)), "markers[6]"),
}


@pytest.mark.parametrize("case", sorted(BAD_MAPS))
def test_bad_maps_name_file_and_key(case, tmp_path):
    text, key = BAD_MAPS[case]
    path = write_text(tmp_path, f"{case}.yaml", text)
    with pytest.raises(ConfigError) as info:
        MarkerMap.load(str(path))
    assert_config_error_names(info, path, key)


# --- fiducial_slam map.txt -------------------------------------------------------------------------

def test_fiducial_slam_text_round_trip():
    m = _sample_map()
    text = m.to_fiducial_slam_text()
    assert len(text.strip().splitlines()) == len(m)
    again = MarkerMap.from_fiducial_slam_text(text, marker_size=0.2)
    assert again.ids == m.ids
    for a, b in zip(m, again):
        # 6 decimals of metres and degrees.
        assert_close(b.T_map_marker[:3, 3], a.T_map_marker[:3, 3], 1e-6, f"marker {a.marker_id} position")
        assert geo.rotation_angle(a.T_map_marker[:3, :3].T @ b.T_map_marker[:3, :3]) < 1e-7
        assert b.observations == a.observations and b.size == 0.2
        var = float(np.mean(np.square(a.position_std)))
        assert abs(b.position_std[0] ** 2 - var) < 1e-9


def test_fiducial_slam_line_uses_degrees_and_fixed_axis_rpy():
    T = geo.make_transform(geo.matrix_from_rpy(math.radians(90), math.radians(-10), math.radians(180)), [1, 2, 3])
    m = MarkerMap([MarkerEntry(5, T, 0.14, np.full(3, 0.01), np.zeros(3), 12)])
    fields = m.to_fiducial_slam_text().split()
    assert fields[0] == "5" and [float(v) for v in fields[1:4]] == [1.0, 2.0, 3.0]
    roll, pitch, yaw = (float(v) for v in fields[4:7])
    assert abs(roll - 90) < 1e-6 and abs(pitch + 10) < 1e-6 and abs(abs(yaw) - 180) < 1e-6, fields
    assert abs(float(fields[7]) - 1e-4) < 1e-12 and fields[8] == "12"
    again = MarkerMap.from_fiducial_slam_text("5 1 2 3 90 -10 180 0.0001 12 7 9\n", 0.14)
    assert_close(again[5].T_map_marker, T, 1e-12, "pose read from fiducial_slam line with links")


def test_fiducial_slam_file_export_import(tmp_path):
    m = _sample_map()
    path = tmp_path / "map.txt"
    m.export_fiducial_slam(str(path))
    again = MarkerMap.import_fiducial_slam(str(path), marker_size=0.15, frame_id="aruco_map")
    assert again.ids == m.ids and again.frame_id == "aruco_map" and "fiducial_slam" in again.method


@pytest.mark.parametrize("text, key", [
    ("1 2 3\n", "line 1"),
    ("# comment\n\n1 0 0 0 0 0 0 x 3\n", "line 3"),
    ("1 0 0 0 0 0 0 -0.1 3\n", "line 1"),
    ("1 0 0 0 0 0 nan 0.1 3\n", "line 1"),
    ("1 0 0 0 0 0 0 0.1 3\n1 1 1 1 0 0 0 0.1 3\n", "line 2"),
    ("# only a comment\n", None),
])
def test_bad_fiducial_slam_text(text, key, tmp_path):
    path = write_text(tmp_path, "map.txt", text)
    with pytest.raises(ConfigError) as info:
        MarkerMap.import_fiducial_slam(str(path), 0.1)
    assert_config_error_names(info, path, key)


def test_import_missing_fiducial_slam_file(tmp_path):
    with pytest.raises(ConfigError) as info:
        MarkerMap.import_fiducial_slam(str(tmp_path / "none.txt"), 0.1)
    assert "none.txt" in str(info.value)


# --- the map frame -------------------------------------------------------------------------------

def _wall_marker(x: float, y: float, z: float, facing_yaw: float, tilt: float = 0.0) -> np.ndarray:
    """Marker on a wall: z (out of the face) horizontal at ``facing_yaw``, y up, optionally tilted back."""
    z_axis = np.array([math.cos(facing_yaw), math.sin(facing_yaw), 0.0])
    y_axis = np.array([0.0, 0.0, 1.0])
    x_axis = np.cross(y_axis, z_axis)
    R = np.stack([x_axis, y_axis, z_axis], axis=1)
    R = R @ geo.matrix_from_rpy(tilt, 0.0, 0.0)  # about the marker's own x
    return geo.make_transform(R, [x, y, z])


@pytest.mark.parametrize("facing_yaw", [0.0, 1.0, -2.5, math.pi])
@pytest.mark.parametrize("tilt", [0.0, 0.2])
def test_map_frame_from_reference_wall_marker(facing_yaw, tilt):
    T_world_marker = _wall_marker(2.0, -1.0, 1.3, facing_yaw, tilt)
    T_world_map = map_frame_from_reference(T_world_marker)
    geo.validate_transform(T_world_map, "T_world_map")
    R = T_world_map[:3, :3]
    assert_close(R[:, 2], [0, 0, 1], 1e-12, "map z is up")
    assert_close(T_world_map[:3, 3], [2.0, -1.0, 0.0], 1e-12, "origin on the floor below the marker")
    # The marker's x is horizontal here (tilt is about x), so the map's x is exactly it.
    assert_close(R[:, 0], T_world_marker[:3, 0], 1e-12, "map x along marker x")
    T_map_marker = geo.compose(geo.inverse(T_world_map), T_world_marker)
    assert_close(T_map_marker[:3, 3], [0.0, 0.0, 1.3], 1e-12, "marker in map: straight above the origin")


def test_map_frame_x_is_the_marker_x_made_horizontal():
    R = geo.matrix_from_rpy(0.1, 0.4, 0.7)  # marker x tilted out of the horizontal plane
    T = geo.make_transform(R, [1.0, 2.0, 0.5])
    T_world_map = map_frame_from_reference(T, floor_z=-0.1)
    x = R[:, 0].copy()
    x[2] = 0.0
    assert_close(T_world_map[:3, 0], x / np.linalg.norm(x), 1e-12, "horizontal x")
    assert_close(T_world_map[:3, 3], [1.0, 2.0, -0.1], 0.0, "origin at floor_z")
    assert_close(T_world_map[:3, 1], np.cross([0, 0, 1], T_world_map[:3, 0]), 1e-12, "y = z cross x")


def test_map_frame_from_reference_rejects_vertical_x_and_bad_poses():
    T = geo.make_transform(geo.matrix_from_rpy(0.0, -math.pi / 2, 0.0), [0, 0, 1])  # x points up
    with pytest.raises(GeometryError, match="vertical"):
        map_frame_from_reference(T)
    with pytest.raises(GeometryError, match="reference marker pose"):
        map_frame_from_reference(np.full((4, 4), np.nan))


def test_surveyed_only_round_trips_on_both_readers(tmp_path):
    """The ``surveyed_only`` flag survives a save and a load, on the fast (whole list) reader and the
    per-marker one (taken when any marker of the list is unusual); a non-boolean names its key."""
    entries = [MarkerEntry(i, geo.transform_from_se2(i, 0.5 * i, 0.1 * i, z=1.0), 0.2, np.full(3, 0.05),
                           np.full(3, 0.01), 0 if i == 4 else 30, surveyed_only=(i == 4)) for i in (2, 4, 6)]
    path = tmp_path / "map.yaml"
    MarkerMap(entries).save(str(path))
    data = yaml.safe_load(path.read_text())
    assert [m.get("surveyed_only", False) for m in data["markers"]] == [False, True, False]
    assert MarkerMap.load(str(path)).surveyed_only_ids == [4]
    data["markers"][0]["observations"] = 30.0          # not an int: the per-marker reader names it ...
    with pytest.raises(ConfigError, match="observations"):
        MarkerMap.from_dict(data, source="m.yaml")
    data["markers"][0]["observations"] = 30
    data["markers"][0]["rms_px"] = None                 # ... here taken by the fast reader as well
    assert MarkerMap.from_dict(data).surveyed_only_ids == [4]
    data["markers"][2]["position_std"] = [0.05, 0.05]   # the fast reader declines: the per-marker one reads
    with pytest.raises(ConfigError, match="position_std"):
        MarkerMap.from_dict(data, source="m.yaml")
    data["markers"][2]["position_std"] = [0.05, 0.05, 0.05]
    data["markers"][2]["ambiguous"] = "no"
    with pytest.raises(ConfigError, match=r"markers\[2\].ambiguous"):
        MarkerMap.from_dict(data, source="m.yaml")
    data["markers"][2]["ambiguous"] = False
    data["markers"][1]["surveyed_only"] = "yes"
    with pytest.raises(ConfigError, match=r"markers\[1\].surveyed_only"):
        MarkerMap.from_dict(data, source="m.yaml")
