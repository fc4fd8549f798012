"""Scene files: the paper's lab, the other-hall example, and clear errors for bad files."""
from __future__ import annotations

import os

import numpy as np
import pytest
import yaml

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.simulation.scene import Scene, marker_pose

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


def test_default_scene_is_the_paper_lab():
    s = Scene.default()
    assert s.world_frame == "world"
    assert s.room.size == (11.0, 9.0)
    assert s.plate.size == (3.67, 2.51)
    assert len(s.markers) == 10
    ids = s.marker_ids
    assert len(set(ids)) == 10 and ids != list(range(10)), ids
    assert s.dictionary == 7
    assert all(abs(m.size - 0.20) < 1e-12 for m in s.markers)
    assert len(s.test_positions) == 15 and len(s.test_orientations) == 8
    yaws = sorted(np.degrees(geo.wrap_angle(p[2])) for p in s.test_orientations)
    assert np.allclose(np.diff(yaws), 45.0), yaws
    for p in s.test_positions + s.test_orientations + s.mapping_stations:
        # The whole footprint stays on the plate.
        half = max(s.robot.footprint) / 2
        assert s.plate.contains(p[0], p[1], margin=half * 0.5), p
    assert s.plate.contains(*s.mapping_pose[:2])
    for m in s.markers:
        assert 0.5 <= m.T_world_marker[2, 3] <= 1.6, (m.marker_id, m.T_world_marker[2, 3])


def test_markers_face_into_the_room_and_are_upright():
    s = Scene.default()
    c = np.array([*s.plate.centre, 0.75])
    for m in s.markers:
        geo.validate_transform(m.T_world_marker)
        to_plate = c - m.T_world_marker[:3, 3]
        cos = m.normal @ to_plate / np.linalg.norm(to_plate)
        assert cos > 0.7, f"marker {m.marker_id} faces away from the plate (cos {cos:.2f})"
        assert np.allclose(m.T_world_marker[:3, 1], [0, 0, 1], atol=1e-12), "y axis (top edge) must be up"


def test_marker_pose_axes():
    T = marker_pose([1, 2, 3], facing=0.0)
    # Face looks along +x; x axis (right as seen by a viewer in front) is +y; y is up.
    assert np.allclose(T[:3, 2], [1, 0, 0]) and np.allclose(T[:3, 0], [0, 1, 0]) and np.allclose(T[:3, 1], [0, 0, 1])
    T = marker_pose([0, 0, 1], facing=np.pi / 2, tilt=np.radians(30))
    assert np.isclose(T[2, 2], 0.5), T[:3, 2]


def test_truth_map_matches_markers():
    s = Scene.default()
    m = s.truth_map()
    assert m.frame_id == "world" and sorted(m.ids) == sorted(s.marker_ids)
    for sm in s.markers:
        assert np.allclose(m.corners(sm.marker_id), sm.corners_world())


def test_other_hall_example_loads():
    s = Scene.load(os.path.join(REPO, "config", "hall_18m.yaml"))
    assert len(s.markers) == 40, len(s.markers)
    assert s.plate.size[0] == pytest.approx(18.0)
    assert len(s.test_positions) >= 5


def _write(tmp_path, data):
    p = tmp_path / "scene.yaml"
    p.write_text(yaml.safe_dump(data))
    return str(p)


@pytest.mark.parametrize("mutate, key", [
    (lambda d: d["markers"][0].pop("position"), "markers[0].position"),
    (lambda d: d["markers"][1].update(id=d["markers"][0]["id"]), "markers[1].id"),
    (lambda d: d["markers"][0].update(facing="north"), "markers[0].facing"),
    (lambda d: d.pop("room"), "room"),
    (lambda d: d["plate"].update(size=[1.0]), "plate.size"),
    (lambda d: d.update(dictionary=99), "dictionary"),
    (lambda d: d["markers"][0].update(position=[50.0, 1.0, 1.0]), "markers"),
])
def test_bad_scene_names_file_and_key(tmp_path, mutate, key):
    with open(os.path.join(REPO, "config", "lab_scene.yaml")) as f:
        data = yaml.safe_load(f)
    mutate(data)
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as info:
        Scene.load(path)
    assert info.value.key == key and path in str(info.value), str(info.value)
