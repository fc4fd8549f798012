"""Fuzzing of the image boundary of the detector: ``sensor_msgs/Image`` fields -> mono8 -> detection.

Property: :func:`detection.image_to_gray` either returns a (height, width) uint8 image or raises
``MeasurementError`` (unsupported encoding, zero size, step too small, data too short), for any
encoding string, size, step, byte order and payload; :meth:`Detector.detect` on what it returns,
and on arbitrary arrays, returns observations with finite (4, 2) corners inside the image or
raises ``MeasurementError``. Plus one test per named bad image (issue 7 §2).
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from aruco_ring_localization.detection import ENCODINGS, Detector, image_to_gray
from aruco_ring_localization.errors import ArucoRingError, MeasurementError

from fuzz_support import FUZZ

DETECTOR = Detector()


@FUZZ
@given(st.data())
def test_fuzz_image_to_gray(data):
    encoding = data.draw(st.sampled_from(sorted(ENCODINGS) + ["", "yuv422", "32FC1", "MONO8", "bayer_rggb8"]),
                         label="encoding")
    width = data.draw(st.integers(0, 64), label="width")
    height = data.draw(st.integers(0, 48), label="height")
    channels, depth = ENCODINGS.get(encoding, (1, 1))
    step = data.draw(st.sampled_from([width * channels * depth, width * channels * depth + 3, width, 0,
                                      max(width * channels * depth - 1, 0)]), label="step")
    size = data.draw(st.sampled_from([step * height, max(step * height - 1, 0), step * height + 5, 0,
                                      step * (height - 1) + width * channels * depth if height else 0]),
                     label="size")
    payload = data.draw(st.binary(min_size=size, max_size=size), label="data")
    as_list = data.draw(st.booleans(), label="as list")
    try:
        img = image_to_gray(encoding, width, height, step, list(payload) if as_list else payload,
                            data.draw(st.booleans(), label="bigendian"))
    except MeasurementError:
        return
    assert img.shape == (height, width) and img.dtype == np.uint8, (img.shape, img.dtype)
    try:
        obs = DETECTOR.detect(img)
    except MeasurementError:
        return
    for o in obs:
        assert o.corners.shape == (4, 2) and np.all(np.isfinite(o.corners))


@FUZZ
@given(st.sampled_from([(0,), (10,), (0, 5), (5, 0), (20, 30), (20, 30, 3), (20, 30, 4), (8, 8, 1), (3, 3)]),
       st.sampled_from([np.uint8, np.uint16, np.float32, np.float64, np.int8, bool]),
       st.integers(0, 2 ** 32 - 1))
def test_fuzz_detect_arbitrary_arrays(shape, dtype, seed):
    rng = np.random.default_rng(seed)
    img = (rng.random(shape) * 255).astype(dtype)
    try:
        obs = DETECTOR.detect(img)
    except ArucoRingError as exc:
        assert isinstance(exc, MeasurementError), exc
        return
    assert isinstance(obs, list)


@pytest.mark.parametrize("kwargs,field", [
    (dict(encoding="yuv422", width=4, height=4, step=8, data=bytes(32)), "encoding"),
    (dict(encoding="32FC1", width=4, height=4, step=16, data=bytes(64)), "encoding"),
    (dict(encoding="mono8", width=0, height=0, step=0, data=b""), "width/height"),
    (dict(encoding="mono8", width=640, height=480, step=320, data=bytes(320 * 480)), "step"),
    (dict(encoding="bgr8", width=640, height=480, step=640, data=bytes(640 * 480)), "step"),
    (dict(encoding="mono8", width=640, height=480, step=640, data=bytes(640 * 100)), "data"),
    (dict(encoding="mono16", width=64, height=48, step=64, data=bytes(64 * 48)), "step"),
])
def test_bad_image_names_the_field(kwargs, field):
    with pytest.raises(MeasurementError, match=field):
        image_to_gray(**kwargs)


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
    from aruco_ring_localization.ros.detector import DetectorCore, DetectorNodeParams

    warnings = []
    core = DetectorCore(DetectorNodeParams(), warn=warnings.append, name="fuzz")
    floats = st.floats(allow_nan=True, allow_infinity=True) | st.floats(-2000, 2000)
    for _ in range(data.draw(st.integers(1, 4), label="events")):
        if data.draw(st.booleans(), label="camera_info?"):
            core.on_camera_info(_msg(
                K=data.draw(st.lists(floats, max_size=10) | st.just([800.0, 0, 320, 0, 800, 240, 0, 0, 1]), label="K"),
                D=data.draw(st.lists(floats, max_size=9), label="D"),
                distortion_model=data.draw(st.sampled_from(["plumb_bob", "equidistant", "", "rational_polynomial",
                                                            "x"]), label="model"),
                width=data.draw(st.integers(0, 4000), label="w"), height=data.draw(st.integers(0, 4000), label="h")))
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
