"""detection.py: image decoding, parameters, corner accuracy on exactly rendered markers, poses,
and the detector on the ring simulator's rendered images (image mode)."""
from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.camera import CameraModel
from aruco_ring_localization.detection import (Detector, DetectorParams, annotate, dictionary_name, fiducial_area,
                                               image_to_gray, marker_poses, refine_corners_lines)
from aruco_ring_localization.errors import ConfigError, MeasurementError
from aruco_ring_localization.detections import MarkerObservation
from aruco_ring_localization.markers import MarkerSizes

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
_DICT = cv2.aruco.getPredefinedDictionary(7)


def supersampled_marker(marker_id: int, x0: float, y0: float, side: float, width: int = 400, height: int = 300,
                        blur: float = 0.6, factor: int = 16, background: float = 215.0) -> np.ndarray:
    """mono8 image of an axis-aligned marker whose black square spans [x0, x0+side] x [y0, y0+side]
    (pixel centres at integer coordinates), area-integrated by supersampling, then blurred.
    Written independently of the simulator's renderer."""
    bits = cv2.aruco.generateImageMarker(_DICT, marker_id, 7)  # one pixel per module
    xs = (np.arange(width * factor) + 0.5) / factor - 0.5
    ys = (np.arange(height * factor) + 0.5) / factor - 0.5
    iu = np.floor((xs - x0) / side * 7).astype(int)
    iv = np.floor((ys - y0) / side * 7).astype(int)
    fine = np.full((height * factor, width * factor), background, np.float32)
    mask = ((iv >= 0) & (iv < 7))[:, None] & ((iu >= 0) & (iu < 7))[None, :]
    tex = bits[np.clip(iv, 0, 6)][:, np.clip(iu, 0, 6)].astype(np.float32) * (185.0 / 255.0) + 30.0
    fine[mask] = tex[mask]
    img = cv2.resize(fine, (width, height), interpolation=cv2.INTER_AREA)
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


# --- image decoding -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def bgr():
    rng = np.random.default_rng(3)
    return rng.integers(0, 256, size=(7, 5, 3), dtype=np.uint8)


@pytest.mark.parametrize("encoding, code", [("bgr8", None), ("rgb8", cv2.COLOR_BGR2RGB),
                                            ("bgra8", cv2.COLOR_BGR2BGRA), ("rgba8", cv2.COLOR_BGR2RGBA)])
def test_image_to_gray_colour_encodings(bgr, encoding, code):
    expected = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    img = bgr if code is None else cv2.cvtColor(bgr, code)
    h, w, ch = img.shape
    got = image_to_gray(encoding, w, h, w * ch, img.tobytes())
    assert got.dtype == np.uint8 and got.shape == (h, w)
    assert np.array_equal(got, expected), f"{encoding}: max diff {np.abs(got.astype(int) - expected).max()}"


def test_image_to_gray_respects_step_padding(bgr):
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    h, w = gray.shape
    padded = np.full((h, w + 3), 99, np.uint8)
    padded[:, :w] = gray
    assert np.array_equal(image_to_gray("mono8", w, h, w + 3, padded.tobytes()), gray)
    # a message whose last row omits its padding is still decodable
    assert np.array_equal(image_to_gray("mono8", w, h, w + 3, padded.tobytes()[:-3]), gray)
    padded_bgr = np.zeros((h, w * 3 + 5), np.uint8)
    padded_bgr[:, :w * 3] = bgr.reshape(h, w * 3)
    assert np.array_equal(image_to_gray("bgr8", w, h, w * 3 + 5, list(padded_bgr.tobytes())), gray)


@pytest.mark.parametrize("bigendian", [False, True])
def test_image_to_gray_mono16_scales_like_cv_bridge(bigendian):
    img16 = np.array([[0, 255, 256, 65535], [1000, 4095, 40000, 512]], dtype=np.uint16)
    data = img16.astype(">u2" if bigendian else "<u2").tobytes()
    got = image_to_gray("mono16", 4, 2, 8, data, is_bigendian=bigendian)
    assert np.array_equal(got, (img16 // 256).astype(np.uint8)), got


@pytest.mark.parametrize("kwargs, field", [
    (dict(encoding="yuv422"), "encoding"),
    (dict(encoding="32FC1"), "encoding"),
    (dict(width=0), "width/height"),
    (dict(height=0, data=b""), "width/height"),
    (dict(step=3), "step"),
    (dict(data=b"\0" * 10), "data"),
])
def test_image_to_gray_rejects_bad_fields(kwargs, field):
    args = dict(encoding="mono8", width=4, height=3, step=4, data=b"\0" * 12)
    args.update(kwargs)
    with pytest.raises(MeasurementError) as exc:
        image_to_gray(**args)
    assert str(exc.value).startswith(field), f"error should name {field!r}: {exc.value}"


# --- parameters ------------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, key", [
    (dict(dictionary=99), "dictionary"), (dict(dictionary=-1), "dictionary"), (dict(dictionary=True), "dictionary"),
    (dict(corner_refinement="best"), "corner_refinement"),
    (dict(corner_refinement_win_size=0), "corner_refinement_win_size"),
    (dict(min_marker_perimeter_rate=5.0), "min_marker_perimeter_rate"),
    (dict(error_correction_rate=1.5), "error_correction_rate"),
])
def test_detector_params_validation_names_key(kwargs, key):
    with pytest.raises(ConfigError) as exc:
        DetectorParams(**kwargs)
    assert key in str(exc.value), str(exc.value)


def test_defaults_and_opencv_mapping():
    p = DetectorParams()
    assert p.dictionary == 7 and dictionary_name(p.dictionary) == "DICT_5X5_1000"
    cv = DetectorParams(corner_refinement="contour", corner_refinement_min_accuracy=0.02).opencv()
    assert cv.cornerRefinementMethod == cv2.aruco.CORNER_REFINE_CONTOUR
    assert cv.cornerRefinementMinAccuracy == pytest.approx(0.02)


# --- detection on exactly rendered markers ----------------------------------------------------------

def test_detect_rejects_non_images_and_finds_nothing_in_blank():
    det = Detector()
    assert det.detect(np.full((120, 160), 128, np.uint8)) == []
    with pytest.raises(MeasurementError):
        det.detect(np.zeros((10, 10), np.float32))
    with pytest.raises(MeasurementError):
        det.detect(np.zeros((0, 10), np.uint8))


@pytest.mark.parametrize("side", [30.0, 60.0, 120.0])
def test_lines_refinement_corner_accuracy(side):
    x0, y0 = 100.3, 80.7
    truth = np.array([[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side]])
    img = supersampled_marker(42, x0, y0, side)
    lines = Detector().detect(img)
    sub = Detector(DetectorParams(corner_refinement="subpix")).detect(img)
    assert [o.marker_id for o in lines] == [42] and [o.marker_id for o in sub] == [42]
    err_lines = np.linalg.norm(lines[0].corners - truth, axis=1)
    err_sub = np.linalg.norm(sub[0].corners - truth, axis=1)
    assert err_lines.max() < 0.1, f"lines: corner errors {err_lines} px (limit 0.1) at side {side} px"
    assert np.median(err_lines) < np.median(err_sub), f"lines {err_lines} not better than subpix {err_sub}"


def test_refine_corners_lines_keeps_corners_on_flat_image():
    c = np.array([[10.0, 10.0], [40.0, 10.0], [40.0, 40.0], [10.0, 40.0]])
    out = refine_corners_lines(np.full((60, 60), 100, np.uint8), c)
    assert np.allclose(out, c), out


def test_refine_corners_lines_keeps_corners_without_white_margin():
    """A marker with its black border on a black background has no outer edge to fit: the
    refinement must leave OpenCV's corners alone rather than fit noise."""
    start = Detector(DetectorParams(corner_refinement="subpix")).detect(supersampled_marker(42, 100.3, 80.7, 60.0))[0]
    dark = supersampled_marker(42, 100.3, 80.7, 60.0, background=30.0)  # background as dark as the border
    assert np.allclose(refine_corners_lines(dark, start.corners), start.corners)


def test_fiducial_area_is_polygon_area():
    c = np.array([[0.0, 0.0], [10.0, 1.0], [12.0, 9.0], [-1.0, 8.0]])
    shoelace = 0.5 * abs(np.sum(c[:, 0] * np.roll(c[:, 1], -1) - np.roll(c[:, 0], -1) * c[:, 1]))
    assert fiducial_area(c) == pytest.approx(shoelace, rel=1e-12)


def test_marker_poses_recovers_projected_pose_and_skips_degenerate():
    model = CameraModel.from_yaml(os.path.join(REPO, "config", "camera_info", "cam0.yaml"))
    T = geo.make_transform(geo.matrix_from_rpy(np.pi + 0.3, 0.2, 0.1), [0.3, -0.2, 2.5])
    sizes = MarkerSizes(0.2, {5: 0.1})
    good = MarkerObservation(5, model.project(geo.transform_points(T, sizes.corners(5))))
    flat = MarkerObservation(6, np.array([[1.0, 1.0], [1.0, 1.0], [1.0, 1.0], [1.0, 1.0]]))
    poses = marker_poses([good, flat], model, sizes)
    assert [p.marker_id for p in poses] == [5]
    p = poses[0]
    assert p.size == 0.1
    assert np.linalg.norm(p.T_cam_marker[:3, 3] - T[:3, 3]) < 1e-6, p.T_cam_marker
    assert p.image_error < 1e-9 and p.object_error < 1e-9
    img = annotate(np.zeros((model.height, model.width), np.uint8), [good], poses, model)
    assert img.shape == (model.height, model.width, 3) and img.any()


# --- image mode of the ring simulator ----------------------------------------------------------------

def _render(sim, T):
    return sim.render(T, rng=np.random.default_rng(5))


def test_detector_finds_every_rendered_marker():
    """Every marker the simulator says is visible is detected, with the right id, and the median
    corner error against the true projection is below 0.3 px; no id outside the scene appears."""
    from aruco_ring_localization.ring import CameraRing
    from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
    from aruco_ring_localization.simulation.scene import Scene

    scene = Scene.default()
    sim = RingSimulator(scene, perturb_ring(CameraRing.load(os.path.join(REPO, "config", "ring.yaml"))), seed=0)
    scene_ids = {m.marker_id for m in scene.markers}
    det = Detector(DetectorParams(dictionary=scene.dictionary))
    errors, missed, n_visible = [], [], 0
    for pose in (scene.test_positions[0], scene.test_positions[-1]):
        T = Scene.T_world_base(pose)
        images = _render(sim, T)
        for cam, visible in sim.visible(T).items():
            found = {o.marker_id: o.corners for o in det.detect(images[cam])}
            assert set(found) <= scene_ids, f"{cam}: ids {set(found) - scene_ids} are not in the scene"
            for marker_id, corners in visible:
                n_visible += 1
                if marker_id in found:
                    errors.extend(np.linalg.norm(found[marker_id] - corners, axis=1))
                else:
                    missed.append((pose, cam, marker_id))
    assert n_visible >= 10, f"only {n_visible} visible markers: the test poses no longer see the scene"
    assert not missed, f"missed {len(missed)} of {n_visible} visible markers: {missed}"
    med = float(np.median(errors))
    assert med < 0.3, f"median corner error {med:.3f} px (limit 0.3) over {len(errors)} corners"


# --- fuzz: whatever a sensor_msgs/Image carries, only MeasurementError escapes -----------------------

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=150)
@given(encoding=st.sampled_from(["mono8", "mono16", "bgr8", "rgb8", "bgra8", "rgba8", "8UC1", "yuv422", "", "bgr16"]),
       width=st.integers(-3, 40), height=st.integers(-3, 40), step=st.integers(-5, 200),
       data=st.binary(max_size=3000))
def test_image_to_gray_fuzz(encoding, width, height, step, data):
    try:
        img = image_to_gray(encoding, width, height, step, data)
    except MeasurementError:
        return
    assert img.shape == (height, width) and img.dtype == np.uint8
    try:
        assert isinstance(Detector().detect(img), list)
    except MeasurementError:
        pass
