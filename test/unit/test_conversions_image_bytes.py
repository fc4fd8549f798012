"""conversions.image_bytes_to_msg: the detector node's reading of a serialised sensor_msgs/Image
gives the fields genpy's deserialisation gives and the same grey pixels, without copying them, and
names the field of a message cut short."""
from __future__ import annotations

import io

import numpy as np
import pytest
from sensor_msgs.msg import Image

from aruco_ring_localization.errors import MeasurementError
from aruco_ring_localization.ros.conversions import image_bytes_to_msg, image_msg_to_gray


def _image(encoding: str, width: int, height: int, step: int, seed: int, frame_id: str = "cam3_optical") -> Image:
    msg = Image()
    msg.header.seq = 41
    msg.header.stamp.secs, msg.header.stamp.nsecs = 1700000000, 123456789
    msg.header.frame_id = frame_id
    msg.height, msg.width, msg.encoding, msg.step = height, width, encoding, step
    msg.is_bigendian = 1 if encoding == "mono16" else 0
    msg.data = np.random.default_rng(seed).integers(0, 256, step * height, dtype=np.uint8).tobytes()
    return msg


def _bytes(msg: Image) -> bytes:
    buff = io.BytesIO()
    msg.serialize(buff)
    return buff.getvalue()


@pytest.mark.parametrize("encoding,width,height,step", [
    ("mono8", 64, 48, 64), ("mono8", 64, 48, 70), ("bgr8", 33, 21, 104), ("rgba8", 16, 9, 64),
    ("mono16", 20, 10, 40)])
def test_fields_and_pixels_are_genpys(encoding, width, height, step):
    msg = _image(encoding, width, height, step, seed=width + step, frame_id="é_cam")
    buff = _bytes(msg)
    ref = Image().deserialize(buff)
    got = image_bytes_to_msg(buff)
    assert (got.header.seq, got.header.stamp, got.header.frame_id) == \
        (ref.header.seq, ref.header.stamp, ref.header.frame_id)
    assert (got.height, got.width, got.encoding, got.is_bigendian, got.step) == \
        (ref.height, ref.width, ref.encoding, ref.is_bigendian, ref.step)
    assert bytes(got.data) == ref.data
    assert np.array_equal(image_msg_to_gray(got), image_msg_to_gray(ref))


def test_the_pixels_are_not_copied():
    buff = _bytes(_image("mono8", 64, 48, 64, seed=1))
    gray = image_msg_to_gray(image_bytes_to_msg(buff))
    assert np.shares_memory(gray, np.frombuffer(buff, np.uint8))


def test_a_message_cut_short_names_the_field():
    buff = _bytes(_image("mono8", 64, 48, 64, seed=2, frame_id="cam0"))
    # header: 12 bytes + 4 length + "cam0"; then height, width, encoding length at 20..32
    for cut, field in ((10, "header"), (24, "header.frame_id"), (34, "encoding"), (len(buff) - 1, "data")):
        with pytest.raises(MeasurementError, match=rf"^{field}:"):
            image_bytes_to_msg(buff[:cut])
