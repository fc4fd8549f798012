"""Unit tests of camera.py: projection/undistortion of the three distortion models, files, errors."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import yaml

from aruco_ring_localization.camera import (CameraModel, default_model_for_tests, load_yaml_file, model_summary,
                                            save_camera_yaml)
from aruco_ring_localization.errors import ConfigError, MeasurementError

from helpers import CAM0_YAML, CONFIG, assert_close, assert_config_error_names, write_text

MODELS = ["plumb_bob", "rational_polynomial", "equidistant"]


def _pixel_grid(model: CameraModel, n: int = 25) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, model.width - 1, n), np.linspace(0, model.height - 1, n))
    return np.stack([u.ravel(), v.ravel()], axis=1)


def _strong_model(name: str) -> CameraModel:
    """A model with noticeably stronger distortion than the defaults (still monotonic on the image)."""
    D = {"plumb_bob": [-0.28, 0.09, 0.001, -0.0015, -0.01],
         "rational_polynomial": [0.2, -0.05, 0.0008, -0.0005, 0.005, 0.35, -0.02, 0.01],
         "equidistant": [-0.05, 0.01, -0.004, 0.001]}[name]
    return default_model_for_tests(name, np.array(D))


def _models():
    out = []
    for name in MODELS:
        out.append((f"{name}-default", default_model_for_tests(name)))
        out.append((f"{name}-strong", _strong_model(name)))
    out.append(("cam0.yaml", CameraModel.from_yaml(str(CAM0_YAML))))
    out.append(("plumb_bob-no-D", default_model_for_tests("plumb_bob", np.zeros(0))))
    out.append(("plumb_bob-4", default_model_for_tests("plumb_bob", np.array([-0.1, 0.02, 0.001, 0.0]))))
    return out


MODEL_CASES = _models()
MODEL_IDS = [name for name, _ in MODEL_CASES]


# --- projection / undistortion ------------------------------------------------------------------

@pytest.mark.parametrize("model", [m for _, m in MODEL_CASES], ids=MODEL_IDS)
def test_normalize_then_project_returns_the_pixels(model):
    px = _pixel_grid(model)
    xy = model.normalize(px)
    assert xy.shape == px.shape and np.all(np.isfinite(xy))
    back = model.project(np.c_[xy, np.ones(len(xy))])
    assert_close(back, px, 1e-5, f"{model.distortion_model}: project(normalize(px)) in pixels")


@pytest.mark.parametrize("model", [m for _, m in MODEL_CASES], ids=MODEL_IDS)
def test_project_then_normalize_returns_the_normalised_point(model):
    rng = np.random.default_rng(20)
    # Normalised points spread over the image: take pixels, undistort them, jitter inside.
    xy = model.normalize(_pixel_grid(model, 15)) * 0.98 + rng.normal(scale=1e-3, size=(225, 2))
    depth = rng.uniform(0.2, 10.0, size=len(xy))
    P = np.c_[xy * depth[:, None], depth]
    px = model.project(P)
    assert np.all(model.in_image(px, margin=-2.0)), "test points should lie on the image"
    assert_close(model.normalize(px), xy, 1e-6, f"{model.distortion_model}: normalize(project(p))")


@pytest.mark.parametrize("name", ["plumb_bob", "rational_polynomial"])
@pytest.mark.parametrize("strong", [False, True])
def test_project_matches_opencv_projectpoints(name, strong):
    model = _strong_model(name) if strong else default_model_for_tests(name)
    rng = np.random.default_rng(21)
    P = np.c_[rng.uniform(-0.7, 0.7, size=(200, 2)), np.ones(200)] * rng.uniform(0.3, 8.0, size=(200, 1))
    expected, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), model.K, model.opencv_distortion)
    assert_close(model.project(P), expected.reshape(-1, 2), 1e-8, f"{name} vs cv2.projectPoints")


@pytest.mark.parametrize("strong", [False, True])
def test_project_matches_opencv_fisheye(strong):
    model = _strong_model("equidistant") if strong else default_model_for_tests("equidistant")
    rng = np.random.default_rng(22)
    P = np.c_[rng.uniform(-0.9, 0.9, size=(200, 2)), np.ones(200)] * rng.uniform(0.3, 8.0, size=(200, 1))
    expected, _ = cv2.fisheye.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), model.K,
                                            model.D.reshape(4, 1))
    assert_close(model.project(P), expected.reshape(-1, 2), 1e-8, "equidistant vs cv2.fisheye.projectPoints")


@pytest.mark.parametrize("name", MODELS)
def test_normalize_inverts_project_with_skew(name):
    # K[0, 1] (skew) is applied by project(); OpenCV's undistortion ignores it, so normalize()
    # must take it out itself.
    K = np.array([[800.0, 2.5, 640.0], [0.0, 810.0, 480.0], [0.0, 0.0, 1.0]])
    model = CameraModel(K, default_model_for_tests(name).D, name, 1280, 960)
    rng = np.random.default_rng(23)
    P = np.c_[rng.uniform(-0.5, 0.5, size=(50, 2)), np.ones(50)] * 3.0
    xy = P[:, :2] / P[:, 2:]
    expected = model.pixels_from_normalized(model.distort_normalized(xy))
    assert_close(model.project(P), expected, 1e-10, "project with skew")
    assert_close(model.normalize(model.project(P)), xy, 1e-6, "normalize with skew")


@pytest.mark.parametrize("name", MODELS)
@pytest.mark.parametrize("skew", [0.0, 2.5])
def test_normalize_leaves_the_pixels_alone(name, skew):
    # normalize() hands a contiguous float64 input to OpenCV without a copy; the skew's correction
    # must go to a copy, not into the caller's pixels.
    K = np.array([[800.0, skew, 640.0], [0.0, 810.0, 480.0], [0.0, 0.0, 1.0]])
    model = CameraModel(K, default_model_for_tests(name).D, name, 1280, 960)
    px = np.random.default_rng(24).uniform([100.0, 100.0], [1100.0, 800.0], size=(12, 2))
    before = px.copy()
    xy = model.normalize(px)
    np.testing.assert_array_equal(px, before)
    np.testing.assert_array_equal(model.normalize(px.tolist()), xy)   # a list: the same numbers


@pytest.mark.parametrize("name", MODELS)
def test_points_at_or_behind_the_camera_are_nan(name):
    model = default_model_for_tests(name)
    P = np.array([[0.1, 0.2, -1.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1e-12], [0.1, -0.1, 2.0]])
    with np.errstate(all="raise"):
        px = model.project(P)
    assert px.shape == (4, 2)
    assert np.all(np.isnan(px[:3])), f"points at/behind the camera gave {px[:3]}"
    assert np.all(np.isfinite(px[3]))
    assert list(model.in_image(px)) == [False, False, False, True]


def test_centre_projects_to_principal_point_and_single_point_shape():
    model = CameraModel.from_yaml(str(CAM0_YAML))
    px = model.project([0.0, 0.0, 3.0])
    assert px.shape == (1, 2)
    assert_close(px[0], [model.cx, model.cy], 1e-12, "optical axis -> principal point")
    assert model.normalize(np.zeros((0, 2))).shape == (0, 2)


def test_undistort_pixels_and_in_image_margin():
    model = default_model_for_tests("plumb_bob")
    px = _pixel_grid(model, 7)
    ideal = model.undistort_pixels(px)
    xy = model.normalize(px)
    assert_close(ideal, xy * [model.fx, model.fy] + [model.cx, model.cy], 1e-9, "undistort_pixels")
    mask = model.in_image(np.array([[0.0, 0.0], [5.0, 5.0], [model.width - 1.0, 10.0], [model.width, 10.0],
                                    [np.nan, 3.0]]), margin=2.0)
    assert list(mask) == [False, True, False, False, False]


@pytest.mark.parametrize("path", sorted((CONFIG / "camera_info").glob("cam*.yaml")), ids=lambda p: p.name)
def test_ring_cameras_horizontal_fov_is_about_78_degrees(path):
    model = CameraModel.from_yaml(str(path))
    fov = math.degrees(model.horizontal_fov())
    assert 76.0 <= fov <= 80.0, f"{path.name}: horizontal FOV {fov:.2f} deg, expected about 77-80"
    assert (model.width, model.height) == (1280, 960)
    assert "HFOV" in model_summary(model)


def test_horizontal_fov_of_an_ideal_pinhole():
    K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
    model = CameraModel(K, np.zeros(5), "plumb_bob", 640, 480)
    expected = 2 * math.atan(319.5 / 500.0)
    assert abs(model.horizontal_fov() - expected) < 1e-9, f"{model.horizontal_fov()} vs {expected}"
    fish = CameraModel(K, np.zeros(4), "equidistant", 640, 480)
    # Equidistant without distortion: angle = r / f.
    assert abs(fish.horizontal_fov() - 2 * 319.5 / 500.0) < 1e-6, f"fisheye FOV {fish.horizontal_fov()}"


def test_frustum_segments_reach_the_image_corners_at_depth(path=CAM0_YAML):
    model = CameraModel.from_yaml(str(path))
    seg = model.frustum_segments(2.0).reshape(8, 2, 3)
    rays, rim = seg[0::2], seg[1::2]
    assert np.allclose(rays[:, 0], 0.0) and np.allclose(rays[:, 1, 2], 2.0), "rays from the centre to depth 2 m"
    px = model.project(rays[:, 1])
    corners = [[0, 0], [model.width - 1, 0], [model.width - 1, model.height - 1], [0, model.height - 1]]
    assert np.allclose(px, corners, atol=1e-3), px          # through the distortion, onto the corners
    assert np.allclose(rim[:, 0], rays[:, 1]) and np.allclose(rim[:, 1], np.roll(rays[:, 1], -1, axis=0))
    half = math.degrees(math.atan2(abs(rays[0, 1, 0]), 2.0) + math.atan2(abs(rays[1, 1, 0]), 2.0))
    assert half > 60.0, f"corner-to-corner angle {half:.1f} deg: wider than the centre row's 78 deg FOV's core"


# --- files and dicts ------------------------------------------------------------------------

def test_from_yaml_reads_cam0():
    model = CameraModel.from_yaml(str(CAM0_YAML))
    raw = yaml.safe_load(CAM0_YAML.read_text())
    assert model.distortion_model == raw["distortion_model"]
    assert_close(model.K.ravel(), raw["camera_matrix"]["data"], 0.0, "K")
    assert_close(model.D, raw["distortion_coefficients"]["data"], 0.0, "D")
    assert model.name == "cam0" and model.width == 1280 and model.height == 960


@pytest.mark.parametrize("model", [m for _, m in MODEL_CASES], ids=MODEL_IDS)
def test_to_dict_from_dict_round_trip(model, tmp_path):
    again = CameraModel.from_dict(model.to_dict())
    assert again == model
    assert_close(again.K, model.K, 0.0, "K")
    assert_close(again.D, model.D, 0.0, "D")
    path = tmp_path / "cam.yaml"
    save_camera_yaml(model, str(path))
    loaded = CameraModel.from_yaml(str(path))
    assert_close(loaded.K, model.K, 0.0, "K from file")
    assert_close(loaded.D, model.D, 0.0, "D from file")
    assert loaded.distortion_model == model.distortion_model and (loaded.width, loaded.height) == (1280, 960)


def test_from_dict_accepts_bare_lists_and_defaults_to_plumb_bob():
    data = {"image_width": 640, "image_height": 480, "camera_matrix": [500, 0, 320, 0, 500, 240, 0, 0, 1]}
    model = CameraModel.from_dict(data)
    assert model.distortion_model == "plumb_bob" and model.D.size == 0
    assert_close(model.opencv_distortion, np.zeros(5), 0.0, "padded D")


def _cam0_dict():
    return yaml.safe_load(CAM0_YAML.read_text())


def _bad(mutate):
    data = _cam0_dict()
    mutate(data)
    return yaml.safe_dump(data)


BAD_FILES = {
    "zero-K": (_bad(lambda d: d["camera_matrix"].update(data=[0.0] * 9)), "camera_matrix"),
    "K-8-values": (_bad(lambda d: d["camera_matrix"].update(data=[800.0] * 8)), "camera_matrix"),
    "K-rows-cols": (_bad(lambda d: d["camera_matrix"].update(rows=1, cols=9)), "camera_matrix"),
    "K-not-numbers": (_bad(lambda d: d["camera_matrix"].update(data=["a"] * 9)), "camera_matrix"),
    "K-negative-f": (_bad(lambda d: d["camera_matrix"]["data"].__setitem__(0, -800.0)), "camera_matrix"),
    "K-bad-last-row": (_bad(lambda d: d["camera_matrix"]["data"].__setitem__(8, 2.0)), "camera_matrix"),
    "K-missing": (_bad(lambda d: d.pop("camera_matrix")), "camera_matrix"),
    "unknown-model": (_bad(lambda d: d.update(distortion_model="kannala_brandt")), "distortion_model"),
    "D-length": (_bad(lambda d: d["distortion_coefficients"].update(data=[0.1, 0.2, 0.3])),
                 "distortion_coefficients"),
    "D-length-fisheye": (_bad(lambda d: d.update(distortion_model="equidistant")), "distortion_coefficients"),
    "D-length-rational": (_bad(lambda d: d.update(distortion_model="rational_polynomial")),
                          "distortion_coefficients"),
    "D-not-numbers": (_bad(lambda d: d["distortion_coefficients"].update(data=["x"] * 5)),
                      "distortion_coefficients"),
    "D-nan": (_bad(lambda d: d["distortion_coefficients"].update(data=[float("nan")] * 5)),
              "distortion_coefficients"),
    "no-width": (_bad(lambda d: d.pop("image_width")), "image_width"),
    "no-height": (_bad(lambda d: d.pop("image_height")), "image_height"),
    "zero-width": (_bad(lambda d: d.update(image_width=0)), "image_width"),
    "float-width": (_bad(lambda d: d.update(image_width=1280.5)), "image_width"),
    "empty": ("", None),
    "only-comment": ("# nothing here\n", None),
    "truncated-in-list": (CAM0_YAML.read_text().split("636.5994")[0], None),
    "truncated-before-D-data": (CAM0_YAML.read_text().split("  data: [-0.07")[0], "distortion_coefficients"),
    "D-cols-mismatch": (_bad(lambda d: d["distortion_coefficients"].update(cols=4)), "distortion_coefficients"),
    "invalid-yaml": ("image_width: 1280\ncamera_matrix: {rows: 3, cols: [3\n", None),
    "a-list": ("- 1\n- 2\n", None),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_camera_files_raise_config_error_naming_file_and_key(case, tmp_path):
    text, key = BAD_FILES[case]
    path = write_text(tmp_path, f"{case}.yaml", text)
    with pytest.raises(ConfigError) as info:
        CameraModel.from_yaml(str(path))
    assert_config_error_names(info, path, key)
    assert info.value.path == str(path)
    if key is not None:
        assert info.value.key and info.value.key.startswith(key), f"key attribute {info.value.key!r}, expected {key}"


def test_invalid_yaml_error_gives_the_line(tmp_path):
    path = write_text(tmp_path, "bad.yaml", "image_width: 1280\nimage_height: 960\ncamera_matrix: [1, 2\n")
    with pytest.raises(ConfigError) as info:
        load_yaml_file(str(path))
    assert str(path) in str(info.value) and "line" in str(info.value), str(info.value)


def test_missing_file_names_the_file(tmp_path):
    path = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError) as info:
        CameraModel.from_yaml(str(path))
    assert str(path) in str(info.value) and "not found" in str(info.value)


def test_constructor_rejects_bad_intrinsics_with_the_key():
    K = np.array([[800.0, 0, 640], [0, 800.0, 480], [0, 0, 1]])
    with pytest.raises(ConfigError) as info:
        CameraModel(K, np.zeros(3), "plumb_bob", 1280, 960)
    assert info.value.key == "distortion_coefficients"
    with pytest.raises(ConfigError) as info:
        CameraModel(np.zeros((3, 3)), np.zeros(5), "plumb_bob", 1280, 960)
    assert info.value.key == "camera_matrix"
    with pytest.raises(ConfigError) as info:
        CameraModel(K[:2], np.zeros(5), "plumb_bob", 1280, 960)
    assert info.value.key == "camera_matrix"
    with pytest.raises(ConfigError) as info:
        CameraModel(K, np.zeros(5), "fisheye", 1280, 960)
    assert info.value.key == "distortion_model"


# --- from_camera_info (messages) ------------------------------------------------------------------

def test_from_camera_info_builds_the_same_model():
    ref = CameraModel.from_yaml(str(CAM0_YAML))
    model = CameraModel.from_camera_info(list(ref.K.ravel()), list(ref.D), "plumb_bob", 1280, 960, name="cam0")
    assert model == ref
    # An empty distortion model string means plumb_bob (old drivers leave it empty).
    model = CameraModel.from_camera_info(list(ref.K.ravel()), [], "", 1280, 960)
    assert model.distortion_model == "plumb_bob"


@pytest.mark.parametrize("kwargs, field", [
    (dict(K=[0.0] * 9), "camera_info.camera_matrix"),
    (dict(K=[800.0] * 8), "camera_info.K"),
    (dict(D=[0.1, 0.2, 0.3]), "camera_info.distortion_coefficients"),
    (dict(distortion_model="equidistant"), "camera_info.distortion_coefficients"),
    (dict(distortion_model="weird"), "camera_info.distortion_model"),
    (dict(width=0), "camera_info.image_width"),
])
def test_from_camera_info_rejects_unusable_messages_naming_the_field(kwargs, field):
    args = dict(K=[800.0, 0, 640, 0, 800.0, 480, 0, 0, 1], D=[0.0] * 5, distortion_model="plumb_bob",
                width=1280, height=960)
    args.update(kwargs)
    with pytest.raises(MeasurementError) as info:
        CameraModel.from_camera_info(**args)
    assert field in str(info.value), f"{str(info.value)!r} does not name {field}"
    assert not isinstance(info.value, ConfigError)
