"""Conformance of the detector with UbiquityRobotics' aruco_detect / fiducial_slam tests.

Data and expected values: test/data/ubiquity_fiducials/SOURCE.txt (real 1280x960 Raspberry Pi
camera images, DICT_5X5_1000, the numbers that repository's own tests assert).
(A) corners of markers 1, 245, 246 within 0.05 px; (B) 403.jpg: marker 403 in the map (robot at
the origin, the given base_link -> camera transform) within 1 mm and 0.002 rad.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.camera import CameraModel
from aruco_ring_localization.detection import Detector, DetectorParams, image_to_gray, marker_poses
from aruco_ring_localization.markers import MarkerSizes

DATA = Path(__file__).resolve().parents[1] / "data" / "ubiquity_fiducials"
CAMERA_INFO = DATA / "camera_info.yaml"
IMG_01 = DATA / "aruco_detect_test_images" / "tag_01_d7_14cm.png"
IMG_245 = DATA / "aruco_detect_test_images" / "tag_245-246_d7_14cm.png"
IMG_403 = DATA / "fiducial_slam_test" / "403.jpg"

EXPECTED_CORNERS = {
    1: [569.89917, 201.55890, 777.42560, 206.85025, 767.95856, 415.37830, 565.75311, 409.24496],
    245: [307.68246, 157.38346, 545.10131, 167.04420, 540.11614, 403.27578, 305.64746, 395.01422],
    246: [671.51892, 173.46070, 900.29650, 178.44973, 895.06933, 407.39855, 666.39910, 403.12911],
}
CORNER_TOL_PX = 0.05

# static_transform_publisher x y z yaw pitch roll of base_link -> camera in fiducial_slam's test
BASE_CAM_XYZ = (0.035, 0.145, 0.14)
BASE_CAM_YPR = (-1.479119, -0.041544, -1.204205)
EXPECTED_403_XYZ = (0.7611, 0.2505, 0.4028)
EXPECTED_403_RPY = (1.5751, -0.014, -1.546)
SIZE_403 = 0.145


SUBPIX = DetectorParams(dictionary=7, corner_refinement="subpix")  # aruco_detect's refinement


def _gray(path: Path) -> np.ndarray:
    """The image as the node sees it: decoded to BGR (as aruco_detect's cv_bridge) then mono8.

    (imread's own grayscale PNG decoding rounds differently and moves corners by ~0.03 px.)
    """
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, f"cannot read {path}"
    return image_to_gray("bgr8", img.shape[1], img.shape[0], img.strides[0], img.tobytes())


@pytest.mark.parametrize("path, ids", [(IMG_01, (1,)), (IMG_245, (245, 246))])
def test_corners_match_aruco_detect(path, ids):
    obs = {o.marker_id: o.corners for o in Detector(SUBPIX).detect(_gray(path))}
    assert sorted(obs) == sorted(ids), f"{path.name}: detected ids {sorted(obs)}, expected {sorted(ids)}"
    for marker_id in ids:
        expected = np.array(EXPECTED_CORNERS[marker_id]).reshape(4, 2)
        err = np.abs(obs[marker_id] - expected).max()
        assert err <= CORNER_TOL_PX, (f"marker {marker_id}: max corner deviation {err:.4f} px > "
                                      f"{CORNER_TOL_PX} px\n{obs[marker_id]}\nvs\n{expected}")


def test_corner_refinement_none_is_worse_but_close():
    """Without subpixel refinement the corners move (so the test above checks the refinement)."""
    obs = Detector(DetectorParams(corner_refinement="none")).detect(_gray(IMG_01))
    err = np.abs(obs[0].corners - np.array(EXPECTED_CORNERS[1]).reshape(4, 2)).max()
    assert CORNER_TOL_PX < err < 3.0, f"unrefined corner deviation {err:.3f} px"


def test_marker_403_pose_in_map():
    model = CameraModel.from_yaml(str(CAMERA_INFO))
    obs = Detector(SUBPIX).detect(_gray(IMG_403))
    assert [o.marker_id for o in obs] == [403], f"detected {[o.marker_id for o in obs]}"
    poses = marker_poses(obs, model, MarkerSizes(SIZE_403))
    assert len(poses) == 1
    yaw, pitch, roll = BASE_CAM_YPR
    T_base_cam = geo.make_transform(geo.matrix_from_rpy(roll, pitch, yaw), BASE_CAM_XYZ)
    T_map_marker = T_base_cam @ poses[0].T_cam_marker  # robot at the map origin
    dpos = T_map_marker[:3, 3] - np.array(EXPECTED_403_XYZ)
    assert np.abs(dpos).max() <= 0.001, f"position error {dpos} m (tolerance 1 mm)"
    rpy = np.array(geo.rpy_from_matrix(T_map_marker))
    drpy = np.array([geo.wrap_angle(a) for a in rpy - np.array(EXPECTED_403_RPY)])
    assert np.abs(drpy).max() <= 0.002, f"roll/pitch/yaw error {drpy} rad (tolerance 0.002 rad)"


def test_marker_403_quality_figures():
    """image_error (mean squared px), object_error and fiducial_area as aruco_detect defines them."""
    model = CameraModel.from_yaml(str(CAMERA_INFO))
    pose = marker_poses(Detector(SUBPIX).detect(_gray(IMG_403)), model, MarkerSizes(SIZE_403))[0]
    proj = model.project(geo.transform_points(pose.T_cam_marker, MarkerSizes(SIZE_403).corners(403)))
    mse = float(np.mean(np.sum((proj - pose.corners) ** 2, axis=1)))
    assert pose.image_error == pytest.approx(mse, rel=1e-9), f"image_error {pose.image_error} vs {mse}"
    assert pose.image_error < 0.1, f"image_error {pose.image_error} px^2 on a sharp real image"
    diag = np.linalg.norm(pose.corners[0] - pose.corners[2])
    expected_obj = mse / diag * np.linalg.norm(pose.T_cam_marker[:3, 3]) / SIZE_403
    assert pose.object_error == pytest.approx(expected_obj, rel=1e-9)
    area = cv2.contourArea(pose.corners.astype(np.float32))
    assert pose.fiducial_area == pytest.approx(area, rel=1e-4), f"area {pose.fiducial_area} vs {area}"


@pytest.mark.parametrize("path, size", [(IMG_01, 0.14), (IMG_245, 0.14), (IMG_403, SIZE_403)])
def test_lines_refinement_on_real_images(path, size):
    """The default ``lines`` refinement stays within 0.6 px of aruco_detect's corners, and its
    corners fit a square through the lens model at least as well overall (lower total image_error)."""
    model = CameraModel.from_yaml(str(CAMERA_INFO))
    gray = _gray(path)
    sub = {p.marker_id: p for p in marker_poses(Detector(SUBPIX).detect(gray), model, MarkerSizes(size))}
    lin = {p.marker_id: p for p in marker_poses(Detector().detect(gray), model, MarkerSizes(size))}
    assert sorted(sub) == sorted(lin), f"ids differ: subpix {sorted(sub)}, lines {sorted(lin)}"
    for i in sub:
        dev = np.abs(lin[i].corners - sub[i].corners).max()
        assert dev < 0.6, f"marker {i}: lines vs subpix corners differ by {dev:.3f} px (limit 0.6)"
    e_sub = sum(p.image_error for p in sub.values())
    e_lin = sum(p.image_error for p in lin.values())
    assert e_lin < 2.0 * e_sub, f"lines image_error {e_lin:.4f} px^2 vs subpix {e_sub:.4f}"


def test_cli_detect_json_on_conformance_image(capsys):
    """``aruco_ring detect 403.jpg --camera-info ... --json``: the contract's JSON, aruco_detect's pose."""
    import json

    from aruco_ring_localization.cli import main

    code = main(["detect", str(IMG_403), "--camera-info", str(CAMERA_INFO), "--fiducial-len", str(SIZE_403),
                 "--corner-refinement", "subpix", "--json"])
    out = capsys.readouterr().out
    assert code == 0, out
    data = json.loads(out)
    assert [m["id"] for m in data["markers"]] == [403]
    m = data["markers"][0]
    assert np.array(m["corners"]).shape == (4, 2)
    T = np.array(m["T_camera_marker"])
    assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
    yaw, pitch, roll = BASE_CAM_YPR
    T_map_marker = geo.make_transform(geo.matrix_from_rpy(roll, pitch, yaw), BASE_CAM_XYZ) @ T
    dpos = T_map_marker[:3, 3] - np.array(EXPECTED_403_XYZ)
    assert np.abs(dpos).max() <= 0.001, f"CLI pose: position error {dpos} m"


def test_cli_detect_table_and_errors(capsys, tmp_path):
    from aruco_ring_localization.cli import main

    assert main(["detect", str(IMG_245), "--camera-info", str(CAMERA_INFO)]) == 0
    out = capsys.readouterr().out
    assert "2 marker(s)" in out and "id  245" in out and "id  246" in out, out
    assert main(["detect", str(tmp_path / "missing.png"), "--camera-info", str(CAMERA_INFO)]) == 1
    assert "missing.png" in capsys.readouterr().err
    bad = tmp_path / "info.yaml"
    bad.write_text("image_width: 10\n")
    assert main(["detect", str(IMG_245), "--camera-info", str(bad)]) == 1
    assert "info.yaml" in capsys.readouterr().err
