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
