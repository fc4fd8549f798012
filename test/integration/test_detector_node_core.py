"""The detector node's logic without a ROS master (DetectorCore), its image decoding and its
message builders. Needs the ROS Python packages (the ROS messages; no master): it fails without them.

Bad input (unsupported encoding, zero-size image, wrong step, short data, undecodable compressed
data, camera_info missing or with an all-zero K) must give ONE clear warning per problem per
period, never raise, and the next good image must be processed normally. Messages are duck-typed
(SimpleNamespace) except for the message builders.
"""
from __future__ import annotations

import os
from types import SimpleNamespace
from typing import List

import cv2
import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.camera import CameraModel
from aruco_ring_localization.detection import ENCODINGS
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.ros.detector import DetectorCore
from aruco_ring_localization.schemas import DetectorConfig
from aruco_ring_localization.throttle import ThrottledWarnings
from hypothesis import given
from hypothesis import strategies as st

from fuzz_support import FUZZ

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
DATA = os.path.join(REPO, "test", "data", "ubiquity_fiducials")
IMG_245 = os.path.join(DATA, "aruco_detect_test_images", "tag_245-246_d7_14cm.png")


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def header(seq=1, frame_id="cam0_optical_frame", secs=100, nsecs=0):
    return SimpleNamespace(seq=seq, frame_id=frame_id, stamp=SimpleNamespace(secs=secs, nsecs=nsecs))


def image_msg(img: np.ndarray, encoding="bgr8", **over):
    if "format" in over:  # a sensor_msgs/CompressedImage
        return SimpleNamespace(header=header(), **over)
    h, w = img.shape[:2]
    msg = SimpleNamespace(header=header(), encoding=encoding, width=w, height=h, step=img.strides[0],
                          data=img.tobytes(), is_bigendian=0)
    for k, v in over.items():
        setattr(msg, k, v)
    return msg


def info_msg(model: CameraModel, frame_id="cam0_optical_frame", K=None):
    return SimpleNamespace(header=header(frame_id=frame_id), K=list(model.K.ravel()) if K is None else K,
                           D=list(model.D), distortion_model=model.distortion_model,
                           width=model.width, height=model.height)


@pytest.fixture(scope="module")
def real_image():
    img = cv2.imread(IMG_245, cv2.IMREAD_COLOR)
    assert img is not None
    return img


@pytest.fixture(scope="module")
def model():
    return CameraModel.from_yaml(os.path.join(DATA, "camera_info.yaml"))


def make_core(**params):
    lines: List[str] = []
    clock = FakeClock()
    core = DetectorCore(DetectorConfig(**params), warn=lines.append, name="ring/cam0", clock=clock)
    return core, lines, clock


def test_detects_and_estimates_poses(real_image, model):
    core, warnings, _ = make_core(fiducial_len=0.14)
    core.on_camera_info(info_msg(model))
    det = core.on_image(image_msg(real_image))
    assert sorted(o.marker_id for o in det.observations) == [245, 246]
    assert det.poses is not None and sorted(p.marker_id for p in det.poses) == [245, 246]
    for p in det.poses:
        d = np.linalg.norm(p.T_cam_marker[:3, 3])
        assert 0.55 < d < 0.75, f"marker {p.marker_id} at {d:.3f} m (expected ~0.64 m)"
        assert p.image_error < 0.5 and p.fiducial_area > 1e4
    assert det.header.frame_id == "cam0_optical_frame" and det.annotated is None
    assert warnings == [], warnings


def test_ignore_fiducials_and_overrides(real_image, model):
    core, _, _ = make_core(fiducial_len=0.14, ignore_fiducials="1-245", fiducial_len_override="246: 0.07",
                           publish_images=True)
    core.on_camera_info(info_msg(model))
    det = core.on_image(image_msg(real_image))
    assert [o.marker_id for o in det.observations] == [246]
    assert det.poses[0].size == 0.07
    assert det.annotated.shape == real_image.shape


def test_empty_image_gives_empty_detections(model):
    core, warnings, _ = make_core()
    core.on_camera_info(info_msg(model))
    det = core.on_image(image_msg(np.full((model.height, model.width), 120, np.uint8), encoding="mono8"))
    assert det is not None and det.observations == [] and det.poses == []
    assert warnings == []


@pytest.mark.parametrize("over, field", [
    (dict(encoding="yuv422"), "encoding"),
    (dict(format="jpeg", data=b"not a jpeg"), "data"),
    (dict(format="png", data=b""), "data"),
    (dict(width=0, height=0, step=0, data=b""), "width/height"),
    (dict(step=100), "step"),
    (dict(data=b"\0" * 1000), "data"),
])
def test_bad_image_warns_once_per_period_and_recovers(real_image, model, over, field):
    core, warnings, clock = make_core()
    core.on_camera_info(info_msg(model))
    for _ in range(20):
        assert core.on_image(image_msg(real_image, **over)) is None
        clock.t += 0.1
    assert len(warnings) == 1, f"expected one warning for 20 bad images in 2 s, got {warnings}"
    assert field in warnings[0] and "ring/cam0" in warnings[0], warnings[0]
    assert core.rejected_images == 20
    clock.t += 20.0
    core.on_image(image_msg(real_image, **over))
    assert len(warnings) == 2 and "21 times" in warnings[1], warnings
    det = core.on_image(image_msg(real_image))  # the node keeps running
    assert det is not None and len(det.observations) == 2


def test_missing_camera_info_publishes_vertices_only(real_image, model):
    core, warnings, clock = make_core()
    for _ in range(5):
        det = core.on_image(image_msg(real_image))
        assert det is not None and len(det.observations) == 2 and det.poses is None
        clock.t += 0.5
    assert len(warnings) == 1 and "camera_info" in warnings[0], warnings
    core.on_camera_info(info_msg(model))
    assert core.on_image(image_msg(real_image)).poses is not None


def test_zero_K_camera_info_is_ignored_with_one_warning(real_image, model):
    core, warnings, clock = make_core()
    for _ in range(10):
        core.on_camera_info(info_msg(model, K=[0.0] * 9))
        clock.t += 0.2
    assert core.model is None
    k_warnings = [w for w in warnings if "all zeros" in w]
    assert len(k_warnings) == 1, warnings
    det = core.on_image(image_msg(real_image))
    assert det is not None and det.poses is None  # vertices still flow
    core.on_camera_info(info_msg(model))
    assert core.model is not None
    # a later bad camera_info keeps the good intrinsics
    core.on_camera_info(info_msg(model, K=[0.0] * 9))
    assert core.model is not None and core.on_image(image_msg(real_image)).poses


def test_camera_info_with_bad_distortion_warns(model):
    core, warnings, _ = make_core()
    bad = info_msg(model)
    bad.D = [0.1, 0.2, 0.3]
    core.on_camera_info(bad)
    assert core.model is None and len(warnings) == 1 and "camera_info" in warnings[0], warnings


def test_image_size_differs_from_camera_info(real_image, model):
    core, warnings, _ = make_core()
    core.on_camera_info(info_msg(model))
    small = cv2.resize(real_image, (640, 480))
    det = core.on_image(image_msg(small))
    assert det is not None and det.poses is None
    assert len(warnings) == 1 and "640x480" in warnings[0], warnings


def test_stale_images_dropped_when_max_image_age_set(real_image):
    core, warnings, _ = make_core(max_image_age=0.5)
    assert core.on_image(image_msg(real_image), now=100.2) is not None
    assert core.on_image(image_msg(real_image), now=101.0) is None
    assert core.dropped_stale == 1 and "stale" in warnings[-1], warnings


@pytest.mark.parametrize("params, key", [(dict(dictionary=42), "dictionary"), (dict(fiducial_len=0.0), "fiducial_len"),
                                         (dict(corner_refinement="fast"), "corner_refinement"),
                                         (dict(ignore_fiducials="a-b"), "ignore_fiducials"),
                                         (dict(fiducial_len_override="3: x"), "fiducial_len_override"),
                                         (dict(adaptiveThreshWinSizeMin=1), "adaptiveThreshWinSizeMin"),
                                         (dict(adaptiveThreshWinSizeStep=0), "adaptiveThreshWinSizeStep"),
                                         (dict(image_transport="theora"), "image_transport")])
def test_bad_parameters_name_the_key(params, key):
    with pytest.raises(ConfigError) as exc:
        DetectorCore(DetectorConfig(**params))
    assert key in str(exc.value), str(exc.value)


def test_threshold_windows_reach_opencv():
    core, _, _ = make_core(adaptiveThreshWinSizeMin=5, adaptiveThreshWinSizeMax=21, adaptiveThreshWinSizeStep=16)
    p = core.detector.params.opencv()
    assert (p.adaptiveThreshWinSizeMin, p.adaptiveThreshWinSizeMax, p.adaptiveThreshWinSizeStep) == (5, 21, 16)


def test_throttled_warnings_are_per_key():
    lines, clock = [], FakeClock()
    w = ThrottledWarnings(lines.append, period=10.0, clock=clock)
    w("a", "A"), w("a", "A"), w("b", "B")
    assert lines == ["A", "B"]
    clock.t = 10.0
    w("a", "A")
    assert lines[-1] == "A (3 times so far)"


def test_message_builders(real_image, model):
    from aruco_ring_localization.ros.conversions import msg_to_transform
    from aruco_ring_localization.ros.detector import fiducial_array_msg, fiducial_transform_array_msg, image_msg as to_img
    from std_msgs.msg import Header

    core, _, _ = make_core(fiducial_len=0.14, publish_images=True)
    core.on_camera_info(info_msg(model))
    msg = image_msg(real_image)
    msg.header = Header(seq=7, frame_id="cam3_optical_frame")
    det = core.on_image(msg)
    va = fiducial_array_msg(det)
    assert va.image_seq == 7 and va.header.frame_id == "cam3_optical_frame" and len(va.fiducials) == 2
    f = va.fiducials[0]
    assert np.allclose([f.x0, f.y0, f.x2, f.y2], det.observations[0].corners[[0, 2]].ravel())
    ta = fiducial_transform_array_msg(det)
    assert [t.fiducial_id for t in ta.transforms] == [p.marker_id for p in det.poses]
    T = msg_to_transform(ta.transforms[0].transform)
    assert geo.pose_distance(T, det.poses[0].T_cam_marker)[0] < 1e-9
    im = to_img(det.annotated, det.header)
    assert im.encoding == "bgr8" and len(im.data) == im.step * im.height


def compressed_msg(img: np.ndarray, ext=".png", fmt="png"):
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return SimpleNamespace(header=header(), format=fmt, data=buf.tobytes())


@pytest.mark.parametrize("ext, fmt", [(".png", "png"), (".jpg", "bgr8; jpeg compressed bgr8")])
@pytest.mark.parametrize("grey", [False, True])
def test_compressed_images_give_the_raw_images_detections(real_image, model, ext, fmt, grey):
    img = cv2.cvtColor(real_image, cv2.COLOR_BGR2GRAY) if grey else real_image
    # Whole-image searches both times: the regions of the tracking give the corners in float32
    # around other origins (within 1e-3 px, test_detection.py), and this compares the decoding.
    core, warnings, _ = make_core(do_pose_estimation=False, tracking_full_every=1)
    raw = core.on_image(image_msg(img, encoding="mono8" if grey else "bgr8"))
    comp = core.on_image(compressed_msg(img, ext, fmt))
    assert comp is not None and warnings == [], warnings
    ids = sorted(o.marker_id for o in comp.observations)
    assert ids == sorted(o.marker_id for o in raw.observations) == [245, 246]
    worst = max(float(np.abs(a.corners - b.corners).max())
                for a, b in zip(sorted(raw.observations, key=lambda o: o.marker_id),
                                sorted(comp.observations, key=lambda o: o.marker_id)))
    # PNG is lossless: the same pixels, the same corners. JPEG (OpenCV's quality 95) moves them a
    # little: measured 0.048 px on this image (colour and grey); bound 0.1 px (2x).
    assert worst <= (0.0 if ext == ".png" else 0.1), f"{ext}: corners moved by {worst:.3f} px"


def test_image_decoding_matches_for_every_encoding(real_image):
    from aruco_ring_localization.ros.conversions import image_msg_to_gray

    grey = cv2.cvtColor(real_image, cv2.COLOR_BGR2GRAY)
    rgb = cv2.cvtColor(real_image, cv2.COLOR_BGR2RGB)
    assert np.array_equal(image_msg_to_gray(image_msg(grey, encoding="mono8")), grey)
    assert np.array_equal(image_msg_to_gray(image_msg(real_image, encoding="bgr8")), grey)
    assert np.array_equal(image_msg_to_gray(image_msg(rgb, encoding="rgb8")), grey)
    assert np.array_equal(image_msg_to_gray(compressed_msg(grey)), grey)
    assert np.array_equal(image_msg_to_gray(compressed_msg(real_image)), grey)


# --- the detector node's logic (ros/detector.py DetectorCore: no rospy needed) ----------------

def _msg(**fields):
    from types import SimpleNamespace

    header = SimpleNamespace(stamp=SimpleNamespace(secs=fields.pop("secs", 100), nsecs=0),
                             frame_id=fields.pop("frame_id", "cam0_optical_frame"))
    return SimpleNamespace(header=header, **fields)


@FUZZ
@given(st.data())
def test_fuzz_detector_core_callbacks_never_raise(data):
    """Any camera_info and Image field values: the detector's callbacks return (None or
    detections) and warn through the throttled sink; they never raise."""
    warnings = []
    core = DetectorCore(DetectorConfig(), warn=warnings.append, name="fuzz")
    floats = st.floats(allow_nan=True, allow_infinity=True) | st.floats(-2000, 2000)
    for _ in range(data.draw(st.integers(1, 4), label="events")):
        if data.draw(st.booleans(), label="camera_info?"):
            core.on_camera_info(_msg(
                K=data.draw(st.lists(floats, max_size=10) | st.just([800.0, 0, 320, 0, 800, 240, 0, 0, 1]), label="K"),
                D=data.draw(st.lists(floats, max_size=9), label="D"),
                distortion_model=data.draw(st.sampled_from(["plumb_bob", "equidistant", "", "rational_polynomial",
                                                            "x"]), label="model"),
                width=data.draw(st.integers(0, 4000), label="w"), height=data.draw(st.integers(0, 4000), label="h")))
        elif data.draw(st.booleans(), label="compressed?"):
            out = core.on_image(_msg(format=data.draw(st.sampled_from(["png", "jpeg", ""]), label="format"),
                                     data=data.draw(st.binary(max_size=200) | st.sampled_from(
                                         [cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes()]),
                                                    label="data")))
            assert out is None or isinstance(out.observations, list)
        else:
            w, h = data.draw(st.integers(0, 80), label="w"), data.draw(st.integers(0, 60), label="h")
            enc = data.draw(st.sampled_from(sorted(ENCODINGS) + ["yuv422", ""]), label="encoding")
            step = data.draw(st.sampled_from([w, w * 3, w * 2 + 1, 0]), label="step")
            n = data.draw(st.sampled_from([step * h, max(step * h - 7, 0), 0]), label="n")
            out = core.on_image(_msg(encoding=enc, width=w, height=h, step=step, is_bigendian=0,
                                     data=data.draw(st.binary(min_size=n, max_size=n), label="data"),
                                     secs=data.draw(st.integers(0, 2 ** 31 - 1), label="secs")),
                                now=data.draw(st.none() | st.floats(0, 1e10), label="now"))
            assert out is None or isinstance(out.observations, list)
    assert all(isinstance(w, str) for w in warnings)


def test_tracking_parameters_reach_the_search():
    core, _, _ = make_core(tracking_full_every=7, tracking_edge_px=64, tracking_windows_in_turn=False)
    assert (core.detector.full_every, core.detector.edge_px, core.detector.windows_in_turn) == (7, 64, False)
    core, _, _ = make_core()
    assert core.detector.windows_in_turn is True   # config/detector.yaml's default
