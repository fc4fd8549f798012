"""Unit tests of rig.py: the 8-camera ring file, its frame conventions, save/load, bad files."""
from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.camera import CameraModel
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.ring import CameraRing, RingCamera, read_transform, ring_summary

from helpers import CONFIG, RING_YAML, assert_close, assert_config_error_names, write_text


@pytest.fixture(scope="module")
def ring() -> CameraRing:
    return CameraRing.load(str(RING_YAML))


def test_ring_has_eight_named_cameras(ring):
    assert len(ring) == 8
    assert ring.names == [f"cam{k}" for k in range(8)]
    assert ring.base_frame == "base_link"
    for k, cam in enumerate(ring):
        assert cam.frame_id == f"cam{k}_optical_frame"
        assert cam.namespace == f"ring/cam{k}"
        assert ring[cam.name] is cam
        assert (cam.model.width, cam.model.height) == (1280, 960)
        geo.validate_transform(cam.T_base_cam, cam.name)


def test_cam0_optical_frame_convention(ring):
    R = ring["cam0"].T_base_cam[:3, :3]
    # Optical frame: z forward (= base +x), x right (= base -y), y down (= base -z).
    assert_close(R[:, 2], [1, 0, 0], 1e-6, "cam0 z axis in base")
    assert_close(R[:, 0], [0, -1, 0], 1e-6, "cam0 x axis in base")
    assert_close(R[:, 1], [0, 0, -1], 1e-6, "cam0 y axis in base")


@pytest.mark.parametrize("k", range(8))
def test_camera_k_looks_at_k_times_45_degrees_ccw(ring, k):
    cam = ring[f"cam{k}"]
    yaw = math.radians(45 * k)
    R = cam.T_base_cam[:3, :3]
    assert_close(R[:, 2], [math.cos(yaw), math.sin(yaw), 0.0], 1e-6, f"cam{k} optical axis")
    assert_close(R[:, 1], [0, 0, -1], 1e-6, f"cam{k} y axis (down)")
    assert_close(R[:, 0], [math.sin(yaw), -math.cos(yaw), 0.0], 1e-6, f"cam{k} x axis (right)")
    assert abs(geo.angle_diff(cam.yaw, yaw)) < 1e-6, f"cam{k}.yaw = {math.degrees(cam.yaw)} deg"
    t = cam.T_base_cam[:3, 3]
    assert_close(t, [0.12 * math.cos(yaw), 0.12 * math.sin(yaw), 0.75], 1e-5, f"cam{k} position")


def test_point_in_front_of_cam2_is_to_the_left_of_the_robot(ring):
    cam = ring["cam2"]
    p_base = geo.transform_points(cam.T_base_cam, [[0.0, 0.0, 2.0]])[0]
    assert_close(p_base, [0.0, 2.12, 0.75], 1e-5, "2 m in front of cam2, in base")
    assert_close(geo.transform_points(cam.T_cam_base, [p_base])[0], [0, 0, 2.0], 1e-9, "back in cam2")


def test_by_frame(ring):
    assert ring.by_frame("cam3_optical_frame") is ring["cam3"]
    assert ring.by_frame("/cam3_optical_frame") is ring["cam3"]
    assert ring.by_frame("base_link") is None
    with pytest.raises(KeyError):
        ring["cam9"]


def test_with_extrinsics_replaces_only_the_given_cameras(ring):
    T_new = geo.transform_from_se2(1.0, 2.0, 0.3, z=0.5)
    other = ring.with_extrinsics({"cam4": T_new})
    assert other is not ring and len(other) == 8
    assert_close(other["cam4"].T_base_cam, T_new, 0.0, "replaced extrinsics")
    for name in ring.names:
        if name != "cam4":
            assert_close(other[name].T_base_cam, ring[name].T_base_cam, 0.0, name)
        assert other[name].model is ring[name].model
        assert other[name].frame_id == ring[name].frame_id
    assert_close(ring["cam4"].T_base_cam[:3, 3], [-0.12, 0.0, 0.75], 1e-9, "original ring untouched")
    assert other.by_frame("cam4_optical_frame") is other["cam4"]


def test_ring_summary_reports_fov_and_overlaps(ring):
    lines = ring_summary(ring)
    assert lines[0].startswith("8 cameras")
    assert sum("HFOV" in line for line in lines) == 8
    overlaps = [line for line in lines if "overlap" in line]
    assert len(overlaps) == 8, overlaps
    # 78 deg FOV at 45 deg spacing: every neighbour pair overlaps by about 33 deg.
    for line in overlaps:
        value = float(line.split(":")[1].split()[0])
        assert 28.0 < value < 38.0, line
        assert "blind gap" not in line


def test_save_load_round_trip_inline_intrinsics(ring, tmp_path):
    path = tmp_path / "sub" / "ring.yaml"
    ring.save(str(path))
    again = CameraRing.load(str(path))
    assert again.names == ring.names and again.base_frame == ring.base_frame
    for a, b in zip(ring, again):
        assert_close(b.T_base_cam, a.T_base_cam, 1e-12, f"{a.name} extrinsics")
        assert b.model == a.model, a.name
        assert (b.frame_id, b.namespace) == (a.frame_id, a.namespace)


def test_save_load_round_trip_with_camera_info_files(ring, tmp_path):
    files = {c.name: str(CONFIG / "camera_info" / f"{c.name}.yaml") for c in ring}
    path = tmp_path / "ring.yaml"
    ring.save(str(path), camera_info_files=files)
    raw = yaml.safe_load(path.read_text())
    assert raw["cameras"][0]["camera_info"] == files["cam0"]
    again = CameraRing.load(str(path))
    for a, b in zip(ring, again):
        assert b.model == a.model
        assert_close(b.T_base_cam, a.T_base_cam, 1e-12, a.name)


def test_save_keeps_previous_file_as_bak(ring, tmp_path):
    path = tmp_path / "ring.yaml"
    ring.save(str(path))
    first = path.read_text()
    ring.with_extrinsics({"cam0": np.eye(4)}).save(str(path))
    assert (tmp_path / "ring.yaml.bak").read_text() == first
    assert_close(CameraRing.load(str(path))["cam0"].T_base_cam, np.eye(4), 1e-12, "new cam0")


def test_constructor_rejects_empty_and_duplicate_rings(ring):
    with pytest.raises(ConfigError):
        CameraRing([])
    cam = ring["cam0"]
    with pytest.raises(ConfigError, match="duplicate frame_id"):
        CameraRing([cam, RingCamera("other", cam.frame_id, cam.model, cam.T_base_cam)])


def test_read_transform_parses_and_validates():
    T = read_transform({"translation": [1, 2, 3], "rotation": [0, 0, 0, 1]}, "f.yaml", "k")
    assert_close(T, geo.make_transform(t=[1, 2, 3]), 0.0, "transform")
    with pytest.raises(ConfigError) as info:
        read_transform({"translation": [1, 2, 3]}, "f.yaml", "k")
    assert "k.rotation" in str(info.value)


# --- bad ring files ---------------------------------------------------------------------------

def _ring_text(mutate=None) -> str:
    data = yaml.safe_load(RING_YAML.read_text())
    for cam in data["cameras"]:
        cam["camera_info"] = str(CONFIG / cam["camera_info"])  # absolute: the file moves to tmp_path
    if mutate:
        mutate(data)
    return yaml.safe_dump(data)


def _set(path, value):
    def mutate(data):
        node = data
        for p in path[:-1]:
            node = node[p]
        node[path[-1]] = value
    return mutate


def _delete(path):
    def mutate(data):
        node = data
        for p in path[:-1]:
            node = node[p]
        del node[path[-1]]
    return mutate


BAD_RINGS = {
    "no-cameras-key": (_delete(["cameras"]), "cameras"),
    "empty-cameras": (_set(["cameras"], []), "cameras"),
    "duplicate-names": (_set(["cameras", 3, "name"], "cam1"), "cameras"),
    "duplicate-frames": (_set(["cameras", 3, "frame_id"], "cam1_optical_frame"), "cameras"),
    "quaternion-norm": (_set(["cameras", 2, "T_base_camera", "rotation"], [0.0, 0.0, 0.0, 2.0]),
                        "cameras[2].T_base_camera"),
    "quaternion-zero": (_set(["cameras", 2, "T_base_camera", "rotation"], [0.0, 0.0, 0.0, 0.0]),
                        "cameras[2].T_base_camera"),
    "quaternion-3-values": (_set(["cameras", 2, "T_base_camera", "rotation"], [0.0, 0.0, 1.0]),
                            "cameras[2].T_base_camera.rotation"),
    "missing-translation": (_delete(["cameras", 5, "T_base_camera", "translation"]),
                            "cameras[5].T_base_camera.translation"),
    "translation-2-values": (_set(["cameras", 5, "T_base_camera", "translation"], [0.1, 0.2]),
                             "cameras[5].T_base_camera.translation"),
    "missing-extrinsics": (_delete(["cameras", 6, "T_base_camera"]), "cameras[6].T_base_camera"),
    "camera-info-file-missing": (_set(["cameras", 4, "camera_info"], "camera_info/nope.yaml"),
                                 "cameras[4].camera_info"),
    "camera-info-missing": (_delete(["cameras", 4, "camera_info"]), "cameras[4].camera_info"),
    "camera-info-bad-inline": (_set(["cameras", 1, "camera_info"], {"image_width": 10}), "cameras[1].camera_info"),
    "missing-name": (_delete(["cameras", 7, "name"]), "cameras[7].name"),
    "camera-not-mapping": (_set(["cameras", 0], "cam0"), "cameras[0]"),
    "bad-version": (_set(["format_version"], 2), "format_version"),
    "bad-base-frame": (_set(["base_frame"], ""), "base_frame"),
    "wiggle-not-mapping": (_set(["cameras", 2, "wiggle"], 0.01), "cameras[2].wiggle"),
    "wiggle-missing-rotation": (_set(["cameras", 2, "wiggle"], {"translation": 0.01}), "cameras[2].wiggle.rotation_deg"),
    "wiggle-zero": (_set(["cameras", 2, "wiggle"], {"translation": 0.0, "rotation_deg": 0.5}),
                    "cameras[2].wiggle.translation"),
    "wiggle-negative": (_set(["cameras", 2, "wiggle"], {"translation": 0.01, "rotation_deg": -0.5}),
                        "cameras[2].wiggle.rotation_deg"),
    "wiggle-text": (_set(["cameras", 2, "wiggle"], {"translation": "1 cm", "rotation_deg": 0.5}),
                    "cameras[2].wiggle.translation"),
    "wiggle-unknown-key": (_set(["wiggle"], {"translation": 0.01, "rotation_deg": 0.5, "rotation": 0.01}), "wiggle"),
}


@pytest.mark.parametrize("case", sorted(BAD_RINGS))
def test_bad_ring_files_name_file_and_key(case, tmp_path):
    mutate, key = BAD_RINGS[case]
    path = write_text(tmp_path, f"{case}.yaml", _ring_text(mutate))
    with pytest.raises(ConfigError) as info:
        CameraRing.load(str(path))
    assert_config_error_names(info, path, key)


def test_camera_info_file_missing_names_both_files(tmp_path):
    path = write_text(tmp_path, "ring.yaml", _ring_text(_set(["cameras", 4, "camera_info"], "camera_info/nope.yaml")))
    with pytest.raises(ConfigError) as info:
        CameraRing.load(str(path))
    assert str(tmp_path / "camera_info" / "nope.yaml") in str(info.value), str(info.value)


def test_broken_camera_info_file_names_its_key(tmp_path):
    (tmp_path / "camera_info").mkdir()
    write_text(tmp_path / "camera_info", "cam0.yaml",
               (CONFIG / "camera_info" / "cam0.yaml").read_text().replace("plumb_bob", "pinhole"))
    path = write_text(tmp_path, "ring.yaml", _ring_text(_set(["cameras", 0, "camera_info"], "camera_info/cam0.yaml")))
    with pytest.raises(ConfigError) as info:
        CameraRing.load(str(path))
    msg = str(info.value)
    assert str(path) in msg and "cameras[0].camera_info" in msg and "distortion_model" in msg, msg


@pytest.mark.parametrize("text", ["", "cameras: [\n", "- a\n- b\n"], ids=["empty", "invalid-yaml", "list"])
def test_unreadable_ring_files_name_the_file(text, tmp_path):
    path = write_text(tmp_path, "ring.yaml", text)
    with pytest.raises(ConfigError) as info:
        CameraRing.load(str(path))
    assert_config_error_names(info, path, None)


def test_missing_ring_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        CameraRing.load(str(tmp_path / "ring.yaml"))


def test_inline_camera_info_is_accepted(tmp_path):
    model = CameraModel.from_yaml(str(CONFIG / "camera_info" / "cam0.yaml"))
    path = write_text(tmp_path, "ring.yaml", _ring_text(_set(["cameras", 0, "camera_info"], model.to_dict())))
    assert CameraRing.load(str(path))["cam0"].model == model


# --- extrinsics_std --------------------------------------------------------------------------

def test_extrinsics_std_default_top_level_and_per_camera(tmp_path):
    from aruco_ring_localization.ring import DEFAULT_EXTRINSICS_STD_ROTATION_DEG, DEFAULT_EXTRINSICS_STD_TRANSLATION

    def load(mutate):
        return CameraRing.load(str(write_text(tmp_path, "r.yaml", _ring_text(mutate))))

    def strip(data):
        data.pop("extrinsics_std", None)
        for c in data["cameras"]:
            c.pop("extrinsics_std", None)

    r = load(strip)
    assert np.allclose(r.cameras[0].extrinsics_std, [np.radians(DEFAULT_EXTRINSICS_STD_ROTATION_DEG)] * 3
                       + [DEFAULT_EXTRINSICS_STD_TRANSLATION] * 3)

    def top_and_one(data):
        strip(data)
        data["extrinsics_std"] = {"translation": 0.001, "rotation_deg": 0.5}
        data["cameras"][3]["extrinsics_std"] = {"rotation_deg": [0.1, 0.2, 0.3]}
    r = load(top_and_one)
    assert np.allclose(r.cameras[0].extrinsics_std, [np.radians(0.5)] * 3 + [0.001] * 3)
    # A camera's own value replaces the part it gives; the rest comes from the top level.
    assert np.allclose(r.cameras[3].extrinsics_std, list(np.radians([0.1, 0.2, 0.3])) + [0.001] * 3)
    # Survives save/load and with_extrinsics (the extrinsics tf delivers keep the file's std).
    path = str(tmp_path / "saved.yaml")
    r.save(path)
    assert np.allclose(CameraRing.load(path).cameras[3].extrinsics_std, r.cameras[3].extrinsics_std)
    moved = r.with_extrinsics({"cam3": np.eye(4)})
    assert moved.cameras[3].extrinsics_std == r.cameras[3].extrinsics_std


def test_config_ring_states_the_labs_calibration_error():
    ring = CameraRing.load(str(RING_YAML))
    for c in ring.cameras:
        assert np.allclose(c.extrinsics_std, [np.radians(0.2)] * 3 + [0.002] * 3), c.name


@pytest.mark.parametrize("node, key", [
    ("0.2", "extrinsics_std"),
    ({"translation": -0.001}, "extrinsics_std.translation"),
    ({"rotation_deg": [0.1, 0.2]}, "extrinsics_std.rotation_deg"),
    ({"rotation_deg": "a lot"}, "extrinsics_std.rotation_deg"),
    ({"rotation": 0.2}, "extrinsics_std"),
])
def test_bad_extrinsics_std_names_file_and_key(node, key, tmp_path):
    path = write_text(tmp_path, "r.yaml", _ring_text(_set(["cameras", 2, "extrinsics_std"], node)))
    with pytest.raises(ConfigError) as info:
        CameraRing.load(str(path))
    assert_config_error_names(info, path, "cameras[2]." + key)


def test_wiggle_is_optional_per_camera_or_for_the_ring_and_round_trips(tmp_path):
    """``wiggle``: absent = rigid (None); at the top level for every camera without its own; ``null``
    on a camera = rigid whatever the top level says; the file written reads back the same."""
    rigid = CameraRing.load(str(write_text(tmp_path, "rigid.yaml", _ring_text())))
    assert all(c.wiggle is None for c in rigid)
    assert all("wiggle" not in c for c in rigid.to_dict()["cameras"])

    def mutate(data):
        data["wiggle"] = {"translation": 0.01, "rotation_deg": 0.5}
        data["cameras"][1]["wiggle"] = {"translation": 0.002, "rotation_deg": 0.1}
        data["cameras"][2]["wiggle"] = None
    ring = CameraRing.load(str(write_text(tmp_path, "wiggle.yaml", _ring_text(mutate))))
    assert ring["cam0"].wiggle == pytest.approx((math.radians(0.5), 0.01))
    assert ring["cam1"].wiggle == pytest.approx((math.radians(0.1), 0.002))
    assert ring["cam2"].wiggle is None
    out = str(tmp_path / "saved.yaml")
    ring.save(out)
    again = CameraRing.load(out)
    for c in ring:
        if c.wiggle is None:
            assert again[c.name].wiggle is None, c.name
        else:
            assert again[c.name].wiggle == pytest.approx(c.wiggle, rel=1e-12), c.name
    # Copies with other extrinsics keep the declared wiggle.
    moved = ring.with_extrinsics({"cam0": np.eye(4)}).with_extrinsics_std(0.001, 0.1)
    assert [c.wiggle for c in moved] == [c.wiggle for c in ring]
