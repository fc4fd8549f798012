"""Importers: Kalibr camchains, TagSLAM cameras.yaml + camera_poses.yaml, tagslam.yaml; import-kalibr."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.cli import main
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.importers import read_rig, read_tagslam_tags, write_ring_files
from aruco_ring_localization.markers import MAX_MARKER_ID
from aruco_ring_localization.ring import CameraRing

DATA = Path(__file__).resolve().parents[1] / "data" / "tagslam"


def _camchain(tmp_path: Path, cams: dict) -> str:
    p = tmp_path / "camchain.yaml"
    p.write_text(yaml.safe_dump(cams))
    return str(p)


def _cam(**extra) -> dict:
    c = {"camera_model": "pinhole", "intrinsics": [460.0, 461.0, 640.0, 512.0], "distortion_model": "equidistant",
         "distortion_coeffs": [-0.01, 0.002, -0.001, 0.0003], "resolution": [1280, 1024],
         "rostopic": "/rig/left/image_raw"}
    c.update(extra)
    return c


def _T(rvec, t) -> np.ndarray:
    return geo.transform_from_rvec_tvec(np.array(rvec, dtype=float), np.array(t, dtype=float))


def test_tagslam_cameras_and_poses_of_a_stereo_rig():
    rig = read_rig(str(DATA / "test_11" / "cameras.yaml"))
    ring = rig.ring()
    assert ring.names == ["cam0", "cam1"] and ring.base_frame == "rig"
    # camera_poses.yaml: position + rotation vector of each camera in the rig body (T_rig_cam).
    want = _T([0.00040784, -0.00929578, 0.00284823], [0.20031766, 0.00166686, 0.00093769])
    dp, dr = geo.pose_distance(ring["cam1"].T_base_cam, want)
    assert dp < 1e-9 and dr < 1e-9
    assert ring["cam0"].namespace == "fla/ovc_node/left"      # from tagtopic /fla/ovc_node/left/tags
    m = ring["cam0"].model
    assert m.distortion_model == "equidistant" and (m.fx, m.fy, m.cx, m.cy) == (603.924, 603.166, 665.041, 554.34)
    assert (m.width, m.height) == (1280, 1024)
    assert "rig body" in rig.base_definition


def test_cameras_without_a_pose_are_named_never_guessed():
    rig = read_rig(str(DATA / "test_5" / "cameras.yaml"))     # camera_poses.yaml has cam0 only
    assert rig.missing_poses() == ["cam1", "cam2", "cam3"]
    with pytest.raises(ConfigError) as err:
        rig.ring()
    assert "cam1, cam2, cam3" in str(err.value) and "never guessed" in str(err.value)


def test_mixed_fisheye_and_radtan_models(tmp_path):
    """test_21: two equidistant fisheyes and two ToF cameras with 5-coefficient radtan."""
    rig = read_rig(str(DATA / "test_21" / "cameras.yaml"))
    models = {c.name: c.model for c in rig.cameras}
    assert models["cam0"].distortion_model == "equidistant" and models["cam0"].D.size == 4
    assert models["cam2"].distortion_model == "plumb_bob" and models["cam2"].D.size == 5
    assert models["cam2"].D[4] == pytest.approx(7.789391040802002)    # k3 last, as OpenCV's plumb_bob


def test_tagslam_wiggle_is_kept_and_said(tmp_path):
    """TagSLAM's wiggle_rotation / wiggle_translation (a camera not rigid on its rig): kept per
    camera and named in the notes; absent: rigid (None), no note; one of the two: TagSLAM's 1e-5 for the other."""
    path = _camchain(tmp_path, {"cam0": _cam(wiggle_rotation=0.01, wiggle_translation=0.02),
                                "cam1": _cam(rostopic="/rig/right/image_raw", wiggle_rotation=0.003),
                                "cam2": _cam(rostopic="/rig/back/image_raw")})
    rig = read_rig(path)
    w = {c.name: c.wiggle for c in rig.cameras}
    assert w == {"cam0": (0.01, 0.02), "cam1": (0.003, 1e-5), "cam2": None}
    note = [n for n in rig.notes if "wiggle" in n]
    assert len(note) == 1 and "cam0, cam1" in note[0] and "0.01 rad / 0.02 m" in note[0] and "cam2" not in note[0]
    rigid = read_rig(_camchain(tmp_path, {"cam0": _cam()}))
    assert rigid.cameras[0].wiggle is None and not any("wiggle" in n for n in rigid.notes)
    # TagSLAM's test 5 (the recording bench_calibration_real.py calibrates) declares 0.01 / 0.01 for all four.
    test5 = read_rig(str(DATA / "test_5" / "cameras.yaml"))
    assert [c.wiggle for c in test5.cameras] == [(0.01, 0.01)] * 4
    assert any("cam0, cam1, cam2, cam3" in n for n in test5.notes)


def test_import_writes_the_declared_wiggle_to_the_ring_file(tmp_path):
    """The ring (and the ring file import-kalibr writes) carries TagSLAM's wiggle as the ring file's
    ``wiggle`` (rotation in deg there); an undeclared one (or TagSLAM's rigid 1e-5) stays rigid."""
    path = _camchain(tmp_path, {"cam0": _cam(wiggle_rotation=0.01, wiggle_translation=0.02),
                                "cam1": _cam(rostopic="/rig/right/image_raw", wiggle_rotation=1e-5,
                                             wiggle_translation=1e-5),
                                "cam2": _cam(rostopic="/rig/back/image_raw")})
    poses = tmp_path / "camera_poses.yaml"
    poses.write_text(yaml.safe_dump({c: {"pose": {"position": {"x": 0.1 * k, "y": 0.0, "z": 0.0},
                                                  "rotation": {"x": 0.0, "y": 0.0, "z": 0.0}}}
                                     for k, c in enumerate(("cam0", "cam1", "cam2"))}))
    ring = read_rig(path, camera_poses=str(poses)).ring()
    assert ring["cam0"].wiggle == pytest.approx((0.01, 0.02))
    assert ring["cam1"].wiggle is None and ring["cam2"].wiggle is None
    out = tmp_path / "ring.yaml"
    write_ring_files(ring, str(out))
    data = yaml.safe_load(out.read_text())
    assert data["cameras"][0]["wiggle"] == pytest.approx({"translation": 0.02, "rotation_deg": np.degrees(0.01)})
    assert "wiggle" not in data["cameras"][1] and "wiggle" not in data["cameras"][2]
    assert CameraRing.load(str(out))["cam0"].wiggle == pytest.approx((0.01, 0.02))


@pytest.mark.parametrize("value", [-0.01, 0.0, "a lot"])
def test_a_bad_wiggle_is_refused_by_key(tmp_path, value):
    with pytest.raises(ConfigError) as err:
        read_rig(_camchain(tmp_path, {"cam0": _cam(wiggle_translation=value)}))
    assert err.value.key == "cam0.wiggle_translation"


def test_kalibr_chain_from_camera_0(tmp_path):
    T_c1_c0 = _T([0.01, -0.02, 0.03], [-0.11, 0.002, 0.001])   # p_cam1 = T_cn_cnm1 p_cam0
    T_c2_c1 = _T([0.0, 1.5, 0.0], [0.05, 0.0, -0.08])
    path = _camchain(tmp_path, {"cam0": _cam(), "cam1": _cam(T_cn_cnm1=T_c1_c0.tolist(), rostopic="/rig/right/image_raw"),
                                "cam2": _cam(T_cn_cnm1=T_c2_c1.tolist(), distortion_model="radtan",
                                             distortion_coeffs=[-0.2, 0.05, 0.001, 0.0], rostopic="/c2/image_raw/compressed")})
    rig = read_rig(path, camera_poses=None)
    ring = rig.ring()
    np.testing.assert_allclose(ring["cam0"].T_base_cam, np.eye(4))
    np.testing.assert_allclose(ring["cam1"].T_base_cam, geo.inverse(T_c1_c0), atol=1e-12)
    np.testing.assert_allclose(ring["cam2"].T_base_cam, geo.inverse(T_c1_c0) @ geo.inverse(T_c2_c1), atol=1e-12)
    assert ring["cam2"].model.distortion_model == "plumb_bob"
    assert [c.namespace for c in ring.cameras] == ["rig/left", "rig/right", "c2"]
    # A tag topic's namespace is its parent (/detector/tags/left: TagSLAM's test_22); two cameras
    # in one namespace are refused, naming them.
    one = _camchain(tmp_path, {"cam0": _cam(tagtopic="/detector/tags/left")})
    assert read_rig(one, camera_poses=None).ring()["cam0"].namespace == "detector/tags"
    two = _camchain(tmp_path, {"cam0": _cam(tagtopic="/detector/tags/left"),
                               "cam1": _cam(tagtopic="/detector/tags/right")})
    with pytest.raises(ConfigError, match=r"\['cam0', 'cam1'\] would share the namespace 'detector/tags'"):
        read_rig(two, camera_poses=None)
    assert "cam0's optical frame" in rig.base_definition


def test_kalibr_imu_frame_when_every_camera_has_T_cam_imu(tmp_path):
    T0 = _T([1.2, -1.2, 1.2], [0.05, 0.01, -0.02])
    T1 = _T([1.2, -1.1, 1.25], [-0.06, 0.01, -0.02])
    rig = read_rig(_camchain(tmp_path, {"cam0": _cam(T_cam_imu=T0.tolist()),
                                        "cam1": _cam(T_cam_imu=T1.tolist(), rostopic="/rig/right/image_raw")}))
    ring = rig.ring()
    np.testing.assert_allclose(ring["cam1"].T_base_cam, geo.inverse(T1), atol=1e-12)
    assert "IMU" in rig.base_definition


def test_a_second_camera_without_T_cn_cnm1_is_reported(tmp_path):
    rig = read_rig(_camchain(tmp_path, {"cam0": _cam(), "cam1": _cam(rostopic="/rig/right/image_raw")}))
    with pytest.raises(ConfigError, match="cam1"):
        rig.ring()


@pytest.mark.parametrize("change, key, needle", [
    ({"distortion_model": "fov", "distortion_coeffs": [0.9]}, "cam0.distortion_model", "FOV"),
    ({"camera_model": "omni"}, "cam0.camera_model", "omni"),
    ({"distortion_model": "radtan", "distortion_coeffs": [0.1, 0.2, 0.3]}, "cam0.distortion_coeffs", "4 or 5"),
    ({"intrinsics": [460.0, 461.0, 640.0]}, "cam0.intrinsics", "4 numbers"),
    ({"resolution": [1280.5, 1024]}, "cam0.resolution", "integer"),
    ({"T_cn_cnm1": [[1, 0, 0, 0]] * 4}, "cam0.T_cn_cnm1", "rotation"),
])
def test_unrepresentable_or_bad_cameras_are_refused_by_key(tmp_path, change, key, needle):
    path = _camchain(tmp_path, {"cam0": _cam(**change)})
    with pytest.raises(ConfigError) as err:
        read_rig(path).ring()
    assert err.value.key == key and needle in str(err.value), str(err.value)


def test_written_ring_files_load_back(tmp_path):
    rig = read_rig(str(DATA / "test_11" / "cameras.yaml"))
    files = write_ring_files(rig.ring(), str(tmp_path / "out" / "ring.yaml"))
    assert [Path(f).name for f in files] == ["cam0.yaml", "cam1.yaml", "ring.yaml"]
    back = CameraRing.load(str(tmp_path / "out" / "ring.yaml"))
    for a, b in zip(rig.ring().cameras, back.cameras):
        assert a.model == b.model and a.namespace == b.namespace and a.frame_id == b.frame_id
        np.testing.assert_allclose(a.T_base_cam, b.T_base_cam, atol=1e-12)


def test_import_kalibr_command(tmp_path, capsys):
    out = tmp_path / "ring.yaml"
    assert main(["import-kalibr", str(DATA / "test_11" / "cameras.yaml"), "--out", str(out),
                 "--tagslam", str(DATA / "test_12" / "tagslam.yaml")]) == 0
    text = capsys.readouterr().out
    assert "base frame 'rig'" in text and "fiducial_len 0.15" in text and '"166, 213' in text
    assert CameraRing.load(str(out)).names == ["cam0", "cam1"]
    assert main(["import-kalibr", str(DATA / "test_5" / "cameras.yaml"), "--out", str(tmp_path / "r5.yaml")]) == 1
    assert "cam1, cam2, cam3" in capsys.readouterr().err and not (tmp_path / "r5.yaml").exists()


def test_import_kalibr_writes_tagslams_known_poses_as_anchors(tmp_path, capsys):
    from aruco_ring_localization.anchors import load_anchors

    anchors = tmp_path / "anchors.yaml"
    args = ["import-kalibr", str(DATA / "test_11" / "cameras.yaml"), "--out", str(tmp_path / "ring.yaml")]
    assert main(args + ["--tagslam", str(DATA / "test_12" / "tagslam.yaml"), "--anchors-out", str(anchors)]) == 0
    assert "1 anchored tags" in capsys.readouterr().out
    back = load_anchors(str(anchors))
    assert back.ids == [6] and back.anchors[0].rotation is not None
    np.testing.assert_allclose(back.anchors[0].position_std, [1e-4] * 3)
    assert main(args + ["--anchors-out", str(tmp_path / "a2.yaml")]) == 2      # needs --tagslam
    assert "--tagslam" in capsys.readouterr().err and not (tmp_path / "a2.yaml").exists()


def test_tagslam_tags_sizes_ignored_moving_and_remaps():
    t12 = read_tagslam_tags(str(DATA / "test_12" / "tagslam.yaml"))
    assert t12.default_size == 0.15 and t12.marker_sizes()(6) == 0.15
    assert {166, 381, 585} <= t12.ignore
    assert 6 in t12.known_poses                          # the tag test_12 fixes
    assert t12.remap(20, 1541686900.0) == 420 and t12.remap(20, 1541687200.0) == 520 and t12.remap(20, 0.0) == 20
    t18 = read_tagslam_tags(str(DATA / "test_18" / "tagslam.yaml"))
    assert t18.moving == set(range(100, 110)) and "block" in t18.moving_bodies   # the tumbling block
    # No default_body: besides the moving block's tags, every tag no body lists (TagSLAM ignores them).
    assert t18.fiducial_len_override() == "100-109: 0.05" and t18.ignore_fiducials() == "4-4095"
    t24 = read_tagslam_tags(str(DATA / "test_24" / "tagslam.yaml"))      # staggered boards
    assert t24.marker_sizes()(2080) == 0.06 and t24.marker_sizes()(72) == 0.05


def test_tagslam_tags_without_default_body_ignore_the_undeclared_ones(tmp_path):
    # TagSLAM attaches a tag no body lists to the default_body; without one it ignores the tag.
    body = ("bodies:\n - lab:\n     is_static: true\n     default_tag_size: 0.05\n     tags:\n"
            "     - id: 7\n       size: 0.05\n - board_10:\n     is_static: true\n     type: board\n"
            "     board: {tag_start_id: 10, tag_size: 0.06, tag_spacing: 0.5, tag_rows: 1, tag_columns: 2}\n"
            " - rig:\n     is_static: false\n     ignore_tags: [3]\n")
    p = tmp_path / "tagslam.yaml"
    p.write_text(body)
    t = read_tagslam_tags(str(p))
    assert t.default_body is None and t.undeclared_ignored
    ignored = t.ignored_ids()
    assert {7, 10, 11}.isdisjoint(ignored) and {0, 3, 8, 9, 12, MAX_MARKER_ID} <= ignored
    assert t.ignore_fiducials() == f"0-6, 8-9, 12-{MAX_MARKER_ID}"
    # With a default_body the undeclared tags are mapped (at its default size): only ignore_tags go.
    p.write_text("default_body: lab\n" + body)
    t = read_tagslam_tags(str(p))
    assert t.default_body == "lab" and not t.undeclared_ignored
    assert t.ignored_ids() == {3} and t.ignore_fiducials() == "3" and t.marker_sizes()(8) == 0.05
    # test_24 lists its boards only: the tags of the boards it does not declare (2090-2094, 2100-2104,
    # whose size is not the default 0.05) are ignored, the declared boards' kept.
    t24 = read_tagslam_tags(str(DATA / "test_24" / "tagslam.yaml"))
    assert set(range(2090, 2095)) | set(range(2100, 2105)) <= t24.ignored_ids()
    assert t24.ignored_ids().isdisjoint(set(range(2080, 2085)) | set(range(2105, 2110)) | set(range(0, 18)))


def test_tagslam_tags_bad_file_names_the_key(tmp_path):
    p = tmp_path / "tagslam.yaml"
    p.write_text("bodies:\n - lab:\n     is_static: true\n     default_tag_size: -1\n")
    with pytest.raises(ConfigError) as err:
        read_tagslam_tags(str(p))
    assert err.value.key == "bodies[0].lab.default_tag_size"


def test_tagslam_fixed_tags_become_anchors(tmp_path):
    from aruco_ring_localization.anchors import load_anchors
    from aruco_ring_localization.importers import tagslam_anchors

    t12 = read_tagslam_tags(str(DATA / "test_12" / "tagslam.yaml"))
    a = tagslam_anchors(t12, t12.ignore | t12.moving)
    # One fixed tag: its full pose, with the noise tagslam.yaml gives it (0.1 mm, 1e-5 rad).
    assert a.ids == [6]
    (anchor,) = a.anchors
    np.testing.assert_allclose(anchor.position, t12.known_poses[6][:3, 3])
    np.testing.assert_allclose(anchor.rotation, t12.known_poses[6][:3, :3])
    np.testing.assert_allclose(anchor.position_std, [1e-4] * 3)
    assert anchor.rotation_std == pytest.approx(1e-5)
    # Written as an anchors file, it reads back as build-map --anchors reads it.
    from aruco_ring_localization.anchors import anchors_yaml
    p = tmp_path / "anchors.yaml"
    p.write_text(anchors_yaml(a))
    back = load_anchors(str(p))
    assert back.ids == [6]
    np.testing.assert_allclose(back.anchors[0].rotation, anchor.rotation, atol=1e-9)
    assert tagslam_anchors(t12, {6}) is None                     # excluded: nothing to anchor
    t24 = read_tagslam_tags(str(DATA / "test_24" / "tagslam.yaml"))
    assert tagslam_anchors(t24) is None                          # boards, no surveyed tag


def test_tagslam_pose_uncertainty_comes_from_its_R_and_a_made_up_one_is_said(tmp_path):
    # test_11's camera_poses.yaml fixes both cameras: R = 1e6 I (1e-6 rad / m per axis).
    rig = read_rig(str(DATA / "test_11" / "cameras.yaml"))
    for c in rig.ring().cameras:
        np.testing.assert_allclose(c.extrinsics_std, [1e-6] * 6, rtol=1e-9)
    assert not any("no uncertainty" in n for n in rig.notes)
    back = CameraRing.load(write_ring_files(rig.ring(), str(tmp_path / "a" / "ring.yaml"))[-1])
    np.testing.assert_allclose(back["cam1"].extrinsics_std, [1e-6] * 6, rtol=1e-6)
    # A correlated R (upper triangular, GTSAM's order: rotation, translation): std = sqrt(diag((R^T R)^-1)).
    R = np.triu(np.arange(1.0, 37.0).reshape(6, 6)) + np.diag([900.0, 800.0, 700.0, 600.0, 500.0, 400.0])
    poses = {"cam0": {"pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "rotation": {"x": 0.0, "y": 0.0, "z": 0.0},
                               "R": [float(v) for v in R.ravel()]}},
             "cam1": {"pose": {"position": {"x": 0.2, "y": 0.0, "z": 0.0}, "rotation": {"x": 0.0, "y": 0.0, "z": 0.0}}}}
    p = tmp_path / "camera_poses.yaml"
    p.write_text(yaml.safe_dump(poses))
    rig = read_rig(str(DATA / "test_11" / "cameras.yaml"), camera_poses=str(p))
    want = np.sqrt(np.diag(np.linalg.inv(R.T @ R)))
    np.testing.assert_allclose(rig.ring()["cam0"].extrinsics_std, want, rtol=1e-9)
    # No R: the ring file's default, and the importer says it is made up.
    from aruco_ring_localization.ring import DEFAULT_EXTRINSICS_STD_ROTATION_DEG, DEFAULT_EXTRINSICS_STD_TRANSLATION

    np.testing.assert_allclose(rig.ring()["cam1"].extrinsics_std,
                               [np.radians(DEFAULT_EXTRINSICS_STD_ROTATION_DEG)] * 3
                               + [DEFAULT_EXTRINSICS_STD_TRANSLATION] * 3)
    assert any("no uncertainty is given for the pose of cam1" in n for n in rig.notes)
    # A bad R names the file and the key.
    poses["cam0"]["pose"]["R"] = [1.0, 2.0]
    p.write_text(yaml.safe_dump(poses))
    with pytest.raises(ConfigError) as err:
        read_rig(str(DATA / "test_11" / "cameras.yaml"), camera_poses=str(p))
    assert "cam0.pose.R" in str(err.value) and "camera_poses.yaml" in str(err.value)


_SURVEYED = """
tagslam_parameters:
  pixel_noise: 0.8
body_defaults:
  position_noise: 0.05
  rotation_noise: 0.01
default_body: lab
bodies:
 - lab:
     is_static: true
     default_tag_size: 0.15
     {override}
     pose:
       position: {{x: 0, y: 0, z: 0}}
       rotation: {{x: 0, y: 0, z: 0}}
     tags:
       - id: 3
         pose:
           position: {{x: 1.0, y: 2.0, z: 0.5}}
           rotation: {{x: 0, y: 1.570796327, z: 0}}
           position_noise: {{x: 0.0001, y: 0.0001, z: 0.0001}}
           rotation_noise: {{x: 1.0e-05, y: 1.0e-05, z: 1.0e-05}}
       - id: 4
         pose:
           position: {{x: 3.0, y: 2.0, z: 0.5}}
           rotation: {{x: 0, y: 0, z: 0}}
"""


def test_tagslam_anchors_are_full_poses_with_the_files_noise(tmp_path):
    """Every known tag pose becomes a full-pose anchor (one anchored tag can place a group that no
    image links to the others); its noise is the tag's, else body_defaults'; TagSLAM's pixel_noise
    is read (what the images weigh against the known poses)."""
    from aruco_ring_localization.importers import tagslam_anchors

    p = tmp_path / "tagslam.yaml"
    p.write_text(_SURVEYED.format(override=""))
    tags = read_tagslam_tags(str(p))
    assert tags.pixel_noise == pytest.approx(0.8)
    a = tagslam_anchors(tags, source=str(p))
    assert a.ids == [3, 4] and all(x.rotation is not None for x in a.anchors)
    three, four = a.anchors
    np.testing.assert_allclose(three.position_std, [1e-4] * 3)
    assert three.rotation_std == pytest.approx(1e-5)
    np.testing.assert_allclose(three.rotation, geo.transform_from_rvec_tvec([0, np.pi / 2, 0], [0, 0, 0])[:3, :3], atol=1e-9)
    np.testing.assert_allclose(four.position_std, [0.05] * 3)          # body_defaults
    assert four.rotation_std == pytest.approx(0.01)
    positions = tagslam_anchors(tags, full_pose=False)
    assert all(x.rotation is None for x in positions.anchors)


def test_tagslam_body_override_replaces_every_tags_noise(tmp_path):
    """override_tag_position_noise / override_tag_rotation_noise (test_10, test_11): TagSLAM replaces
    the noise of every known tag pose of the body with them, when both are positive."""
    p = tmp_path / "tagslam.yaml"
    p.write_text(_SURVEYED.format(override="override_tag_position_noise: 0.5\n     override_tag_rotation_noise: 0.1"))
    tags = read_tagslam_tags(str(p))
    for i in (3, 4):
        pos, rot = tags.known_noise[i]
        np.testing.assert_allclose(pos, [0.5] * 3)
        assert rot == pytest.approx(0.1)
    p.write_text(_SURVEYED.format(override="override_tag_position_noise: 0.5"))       # one alone: ignored
    assert read_tagslam_tags(str(p)).known_noise[3][1] == pytest.approx(1e-5)
    p.write_text(_SURVEYED.format(override="override_tag_position_noise: fast\n     override_tag_rotation_noise: 0.1"))
    with pytest.raises(ConfigError) as err:
        read_tagslam_tags(str(p))
    assert err.value.key == "bodies[0].lab.override_tag_position_noise"


def test_tagslam_override_noise_and_odometry(tmp_path):
    """A body's override_tag_*_noise replaces every tag's own noise (TagSLAM's rule); the rig body's
    odom_topic, T_body_odom and odom_acceleration are read (defaults when omitted)."""
    import numpy as np

    from aruco_ring_localization.importers import read_tagslam_tags, tagslam_odometry

    pose = ("pose: {position: {x: 1.0, y: 2.0, z: 0.5}, rotation: {x: 0.0, y: 0.0, z: 0.0}, "
            "position_noise: {x: 0.0001, y: 0.0001, z: 0.0001}, rotation_noise: {x: 1.0e-5, y: 1.0e-5, z: 1.0e-5}}")
    text = f"""
default_body: floor
bodies:
 - floor:
     is_static: true
     default_tag_size: 0.15
     override_tag_position_noise: 0.1
     override_tag_rotation_noise: 0.05
     pose: {{position: {{x: 0, y: 0, z: 0}}, rotation: {{x: 0, y: 0, z: 0}}}}
     tags:
       - {{id: 3, size: 0.15, {pose}}}
 - rig:
     is_static: false
     odom_topic: /vio/odom
     odom_acceleration: 2.0
     T_body_odom: {{position: {{x: 0.1, y: 0.0, z: 0.0}}, rotation: {{x: 0.0, y: 0.0, z: 3.14159265}}}}
"""
    path = tmp_path / "tagslam.yaml"
    path.write_text(text)
    tags = read_tagslam_tags(str(path), rig_bodies=("rig",))
    pos_std, rot_std = tags.known_noise[3]
    assert np.allclose(pos_std, 0.1) and rot_std == 0.05
    odo = tagslam_odometry(str(path), "rig")
    T = odo.T_body_odom
    assert odo.topic == "/vio/odom" and odo.acceleration == 2.0 and odo.angular_acceleration == 5.0
    # TagSLAM's maximum defaults to 10 x the minimum; a fixed noise only when both are set.
    assert odo.acceleration_max == 20.0 and odo.angular_acceleration_max == 50.0
    assert odo.translation_noise == 0.0 and odo.rotation_noise == 0.0
    assert odo.link_noise()["noise_model"] == "per_message" and odo.link_noise()["message_acceleration"] == 2.0
    assert np.allclose(T[:3, 3], [0.1, 0, 0]) and np.allclose(T[:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-6)
    assert tagslam_odometry(str(path), "floor") is None
    # The newer names win over odom_acceleration; one fixed noise alone is not used (TagSLAM's rule).
    path.write_text(text.replace("odom_acceleration: 2.0", "odom_acceleration: 2.0\n     "
                                 "odom_acceleration_noise_min: 3.0\n     odom_acceleration_noise_max: 7.0\n     "
                                 "odom_translation_noise: 0.02"))
    odo = tagslam_odometry(str(path), "rig")
    assert (odo.acceleration, odo.acceleration_max, odo.translation_noise) == (3.0, 7.0, 0.0)
    path.write_text(text.replace("odom_acceleration: 2.0", "odom_translation_noise: 0.02\n     "
                                 "odom_rotation_noise: 0.01"))
    odo = tagslam_odometry(str(path), "rig")
    assert (odo.translation_noise, odo.rotation_noise, odo.acceleration) == (0.02, 0.01, 5.0)
    path.write_text(text.replace("odom_acceleration: 2.0", "odom_acceleration: -1"))
    with pytest.raises(ConfigError, match="odom_acceleration"):
        tagslam_odometry(str(path), "rig")


def test_tagslam_pixel_noise_is_the_files_and_a_bad_one_is_named(tmp_path):
    """``tagslam_parameters.pixel_noise`` (what ``localize --smooth --odom-tagslam`` weighs the
    corners with), None when the file states none, and a non-positive one named by its key."""
    from aruco_ring_localization.importers import tagslam_pixel_noise

    path = tmp_path / "tagslam.yaml"
    path.write_text("tagslam_parameters:\n  pixel_noise: 2.0\nbodies: []\n")
    assert tagslam_pixel_noise(str(path)) == 2.0
    path.write_text("tagslam_parameters:\n  max_num_incremental_opt: 100\nbodies: []\n")
    assert tagslam_pixel_noise(str(path)) is None
    path.write_text("tagslam_parameters:\n  pixel_noise: -1\nbodies: []\n")
    with pytest.raises(ConfigError, match="pixel_noise"):
        tagslam_pixel_noise(str(path))
