"""Bad files, one test each: map, ring, camera_info and scene files that are empty, truncated,
of wrong types, with duplicate ids/keys or negative sizes. Each raises ConfigError whose message
names the file and the key (issue 7, "bad input at every boundary"), never another exception.

Also the regressions the fuzz tests found (each fixed in its own commit).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

import pytest
import yaml

from aruco_ring_localization.camera import CameraModel
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.marker_map import MarkerMap
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.scene import Scene

from helpers import CAM0_YAML, CONFIG, RING_YAML

CAM_TEXT = CAM0_YAML.read_text()
RING_TEXT = RING_YAML.read_text()
SCENE_TEXT = (CONFIG / "lab_scene.yaml").read_text()
MAP_TEXT = """format_version: 1
frame_id: map
reference_marker: 3
markers:
- id: 3
  size: 0.2
  translation: [1.0, 2.0, 1.2]
  rotation: [0.5, 0.5, 0.5, 0.5]
  position_std: [0.001, 0.001, 0.001]
  rotation_std: [0.002, 0.002, 0.002]
  observations: 120
- id: 7
  size: 0.2
  translation: [3.0, 2.0, 1.2]
  rotation: [0.5, 0.5, 0.5, 0.5]
  observations: 80
"""

LOADERS = {
    "map": (MAP_TEXT, MarkerMap.load),
    "ring": (RING_TEXT, CameraRing.load),
    "camera_info": (CAM_TEXT, CameraModel.from_yaml),
    "scene": (SCENE_TEXT, Scene.load),
}


def _write(tmp_path: Path, kind: str, text: str) -> Path:
    path = tmp_path / f"bad_{kind}.yaml"
    path.write_text(text)
    if kind == "ring":  # the ring file refers to camera_info/camK.yaml next to it
        (tmp_path / "camera_info").mkdir(exist_ok=True)
        for f in (CONFIG / "camera_info").glob("*.yaml"):
            (tmp_path / "camera_info" / f.name).write_text(f.read_text())
    return path


def _expect(tmp_path: Path, kind: str, text: str, key: Optional[str], also: str = "") -> str:
    """Load ``text`` as a ``kind`` file; assert a ConfigError naming the file and ``key``."""
    path = _write(tmp_path, kind, text)
    loader: Callable = LOADERS[kind][1]
    with pytest.raises(ConfigError) as info:
        loader(str(path))
    msg = str(info.value)
    assert str(path) in msg, f"the error does not name the file: {msg}"
    if key is not None:
        assert key in msg, f"the error does not name the key {key!r}: {msg}"
    assert also in msg.replace(str(path), ""), f"the error does not say {also!r}: {msg}"
    return msg


def _edit(kind: str, fn) -> str:
    data = yaml.safe_load(LOADERS[kind][0])
    fn(data)
    return yaml.safe_dump(data, sort_keys=False)


def test_the_valid_texts_load(tmp_path):
    for kind, (text, loader) in LOADERS.items():
        loader(str(_write(tmp_path, kind, text)))


# --- empty and truncated ----------------------------------------------------------------------

@pytest.mark.parametrize("kind", sorted(LOADERS))
def test_empty_file(tmp_path, kind):
    _expect(tmp_path, kind, "", None, "empty")


@pytest.mark.parametrize("kind", sorted(LOADERS))
def test_whitespace_and_comment_only_file(tmp_path, kind):
    _expect(tmp_path, kind, "# nothing here\n\n", None, "empty")


@pytest.mark.parametrize("kind", sorted(LOADERS))
def test_truncated_inside_a_flow_list(tmp_path, kind):
    """Cut in the middle of a ``[a, b, c]`` list (an interrupted copy): invalid YAML with its line."""
    text = LOADERS[kind][0]
    cut = text.index("[", len(text) // 3) + 3
    _expect(tmp_path, kind, text[:cut], None, "line")


@pytest.mark.parametrize("kind,cut_after,key", [
    ("map", "- id: 7\n", "markers[1].size"),
    ("ring", "- name: cam3\n", "cameras[3].camera_info"),
    ("camera_info", "image_height: 960\n", "camera_matrix"),
    ("scene", "markers:\n", "markers"),
])
def test_truncated_at_a_line_end(tmp_path, kind, cut_after, key):
    """Cut at a line end: valid YAML but a half document; the first missing key is named."""
    text = LOADERS[kind][0]
    _expect(tmp_path, kind, text[: text.index(cut_after) + len(cut_after)], key)


def test_missing_file_names_it(tmp_path):
    for kind, (_, loader) in LOADERS.items():
        with pytest.raises(ConfigError, match="not found") as info:
            loader(str(tmp_path / f"nope_{kind}.yaml"))
        assert f"nope_{kind}.yaml" in str(info.value)


def test_binary_garbage(tmp_path):
    for kind in LOADERS:
        path = tmp_path / f"bin_{kind}.yaml"
        path.write_bytes(bytes(range(256)) * 4)
        with pytest.raises(ConfigError) as info:
            LOADERS[kind][1](str(path))
        assert str(path) in str(info.value)


# --- wrong types ------------------------------------------------------------------------------

def test_top_level_list(tmp_path):
    for kind in LOADERS:
        _expect(tmp_path, kind, "- 1\n- 2\n", None, "mapping")


@pytest.mark.parametrize("kind,edit,key", [
    ("map", lambda d: d["markers"][1].__setitem__("translation", "here"), "markers[1].translation"),
    ("map", lambda d: d["markers"][0].__setitem__("rotation", [0.5, 0.5, [0.5], 0.5]), "markers[0]"),
    ("map", lambda d: d["markers"][0].__setitem__("observations", 1.5), "markers[0].observations"),
    ("map", lambda d: d.__setitem__("markers", {"3": {}}), "markers"),
    ("map", lambda d: d.__setitem__("reference_marker", "three"), "reference_marker"),
    ("ring", lambda d: d["cameras"][2].__setitem__("T_base_camera", [0, 0, 0]), "cameras[2].T_base_camera"),
    ("ring", lambda d: d["cameras"][1]["T_base_camera"].__setitem__("rotation", [0, 0, 0, 0]),
     "cameras[1].T_base_camera"),
    ("ring", lambda d: d["cameras"][0].__setitem__("camera_info", 5), "cameras[0].camera_info"),
    ("ring", lambda d: d.__setitem__("cameras", "cam0"), "cameras"),
    ("camera_info", lambda d: d["camera_matrix"].__setitem__("data", ["a"] * 9), "camera_matrix.data"),
    ("camera_info", lambda d: d.__setitem__("image_width", "1280"), "image_width"),
    ("camera_info", lambda d: d["distortion_coefficients"].__setitem__("data", [0.1, 0.2]),
     "distortion_coefficients"),
    ("camera_info", lambda d: d.__setitem__("distortion_model", "fisheye"), "distortion_model"),
    ("scene", lambda d: d["markers"][4].__setitem__("position", [1, 2]), "markers[4].position"),
    ("scene", lambda d: d["markers"][0].__setitem__("facing", "north"), "markers[0].facing"),
    ("scene", lambda d: d.__setitem__("room", [11, 9]), "room"),
    ("scene", lambda d: d.__setitem__("robot", "big"), "robot"),
    ("scene", lambda d: d.__setitem__("posts", True), "posts"),
    ("scene", lambda d: d.__setitem__("test_positions", [[1, 2]]), "test_positions[0]"),
])
def test_wrong_type(tmp_path, kind, edit, key):
    _expect(tmp_path, kind, _edit(kind, edit), key)


# --- duplicates -------------------------------------------------------------------------------

def test_map_duplicate_marker_id(tmp_path):
    _expect(tmp_path, "map", _edit("map", lambda d: d["markers"][1].__setitem__("id", 3)), "markers[1].id",
            "duplicate")


def test_ring_duplicate_camera_name(tmp_path):
    _expect(tmp_path, "ring", _edit("ring", lambda d: d["cameras"][5].__setitem__("name", "cam2")), "cameras",
            "duplicate")


def test_ring_duplicate_frame_id(tmp_path):
    _expect(tmp_path, "ring",
            _edit("ring", lambda d: d["cameras"][5].__setitem__("frame_id", "cam2_optical_frame")), "cameras",
            "duplicate")


def test_scene_duplicate_marker_id(tmp_path):
    def dup(d):
        d["markers"][3]["id"] = d["markers"][0]["id"]
    _expect(tmp_path, "scene", _edit("scene", dup), "markers[3].id", "duplicate")


@pytest.mark.parametrize("kind,key", [("camera_info", "image_width"), ("map", "frame_id"),
                                      ("scene", "marker_size"), ("ring", "base_frame")])
def test_duplicate_yaml_key(tmp_path, kind, key):
    """A key written twice (PyYAML would silently keep the last one) is an error naming it."""
    text = LOADERS[kind][0]
    i = text.index(f"\n{key}:") + 1
    line = text[i: text.index("\n", i) + 1]
    _expect(tmp_path, kind, text + line, key, "duplicate")


# --- negative sizes ---------------------------------------------------------------------------

@pytest.mark.parametrize("kind,edit,key", [
    ("map", lambda d: d["markers"][0].__setitem__("size", -0.2), "markers[0].size"),
    ("map", lambda d: d["markers"][1].__setitem__("size", 0), "markers[1].size"),
    ("map", lambda d: d["markers"][0].__setitem__("position_std", [0.001, -0.001, 0.0]), "markers[0].position_std"),
    ("map", lambda d: d["markers"][0].__setitem__("observations", -3), "markers[0].observations"),
    ("map", lambda d: d["markers"][0].__setitem__("id", -1), "markers[0].id"),
    ("ring", lambda d: d["cameras"][0].__setitem__("camera_info", dict(yaml.safe_load(CAM_TEXT), image_width=-1280)),
     "image_width"),
    ("camera_info", lambda d: d.__setitem__("image_height", -960), "image_height"),
    ("camera_info", lambda d: d.__setitem__("image_width", 0), "image_width"),
    ("camera_info", lambda d: d["camera_matrix"]["data"].__setitem__(0, -800.0), "camera_matrix"),
    ("camera_info", lambda d: d["camera_matrix"].__setitem__("data", [0.0] * 9), "camera_matrix"),
    ("scene", lambda d: d.__setitem__("marker_size", -0.2), "marker_size"),
    ("scene", lambda d: d["markers"][2].__setitem__("size", -0.1), "markers[2].size"),
    ("scene", lambda d: d["room"].__setitem__("size", [11.0, -9.0]), "room.size"),
    ("scene", lambda d: d["plate"].__setitem__("size", [0.0, 2.5]), "plate.size"),
    ("scene", lambda d: d["robot"].__setitem__("footprint", [-0.98, 0.61]), "robot.footprint"),
])
def test_negative_or_zero_size(tmp_path, kind, edit, key):
    _expect(tmp_path, kind, _edit(kind, edit), key)


# --- regressions found by the fuzz tests (test_fuzz_loaders.py) -------------------------------

def test_regression_ragged_quaternion_in_ring(tmp_path):
    """Was numpy's ValueError from np.ravel on a ragged list (fixed in geometry._as_flat)."""
    _expect(tmp_path, "ring",
            _edit("ring", lambda d: d["cameras"][0]["T_base_camera"].__setitem__("rotation", [[], 0.5, -0.5, 0.5])),
            "cameras[0].T_base_camera")


def test_regression_fiducial_slam_infinite_nobs():
    """Was OverflowError from int(float('inf'))."""
    with pytest.raises(ConfigError, match="line 2") as info:
        MarkerMap.from_fiducial_slam_text("1 0 0 1 0 0 0 0.01 3\n2 1 1 1 1 1 1 1 inf\n", 0.2, source="map.txt")
    assert "map.txt" in str(info.value)


def test_regression_deeply_nested_yaml(tmp_path):
    """Was RecursionError from PyYAML's pure-Python parser (libyaml's is iterative)."""
    for kind in ("map", "camera_info"):
        _expect(tmp_path, kind, "[" * 1000 + "]" * 1000 + "\n", None, "mapping")
    _expect(tmp_path, "map", "format_version: 1\nmarkers: " + "[" * 1000 + "]" * 1000 + "\n", "markers[0]")
