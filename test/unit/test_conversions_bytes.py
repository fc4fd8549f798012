"""conversions.fiducial_array_bytes_to_observations: the localizer's reading of serialised
fiducial_vertices gives what genpy's deserialisation + fiducial_array_to_observations give, bit for
bit, and names the field of a message cut short."""
from __future__ import annotations

import io
import math

import numpy as np
import pytest
import rospy
from fiducial_msgs.msg import Fiducial, FiducialArray
from hypothesis import given, settings
from hypothesis import strategies as st

from aruco_ring_localization.errors import MeasurementError
from aruco_ring_localization.ros.conversions import (fiducial_array_bytes_to_observations,
                                                     fiducial_array_to_observations, stamp_to_sec)

from fuzz_support import FUZZ

coordinate = st.floats(allow_nan=True, allow_infinity=True, width=64)
fiducial = st.builds(lambda i, d, c: Fiducial(i, d, *c), st.integers(-2 ** 31, 2 ** 31 - 1),
                     st.integers(-2 ** 31, 2 ** 31 - 1), st.lists(coordinate, min_size=8, max_size=8))


def _bytes(msg: FiducialArray) -> bytes:
    buff = io.BytesIO()
    msg.serialize(buff)
    return buff.getvalue()


def _same(a, b) -> bool:
    """Same ids and the same float64 corner bits (NaN payloads included)."""
    return [o.marker_id for o in a] == [o.marker_id for o in b] and all(
        x.corners.shape == (4, 2) and x.corners.dtype == np.float64 and x.corners.tobytes() == y.corners.tobytes()
        for x, y in zip(a, b))


@settings(FUZZ)
@given(st.lists(fiducial, max_size=40), st.text(max_size=20), st.integers(0, 2 ** 32 - 1),
       st.integers(0, 999_999_999), st.integers(-2 ** 31, 2 ** 31 - 1), st.none() | st.integers(0, 50))
def test_bytes_read_as_genpy_reads_them(fiducials, frame_id, secs, nsecs, image_seq, limit):
    msg = FiducialArray()
    msg.header.seq = 7
    msg.header.stamp = rospy.Time(secs, nsecs)
    msg.header.frame_id = frame_id
    msg.image_seq = image_seq
    msg.fiducials = fiducials
    buff = _bytes(msg)
    stamp, frame, observations = fiducial_array_bytes_to_observations(buff, limit=limit)
    parsed = FiducialArray().deserialize(buff)
    assert stamp == stamp_to_sec(parsed.header.stamp)
    assert frame == parsed.header.frame_id == frame_id
    expected = fiducial_array_to_observations(parsed, limit=limit)
    assert len(observations) == len(expected) == (len(fiducials) if limit is None else min(limit, len(fiducials)))
    assert _same(observations, expected)
    for o in observations:  # corners are the pipeline's to use: aligned, writable, native float64
        assert o.corners.flags.writeable and o.corners.flags.aligned


def test_a_message_cut_short_names_the_field():
    msg = FiducialArray()
    msg.header.frame_id = "cam0_optical"
    msg.fiducials = [Fiducial(1, 0, *range(8)), Fiducial(2, 0, *range(8))]
    buff = _bytes(msg)
    for cut, field in ((10, "header"), (20, "header.frame_id"), (len(buff) - 1, "fiducials")):
        with pytest.raises(MeasurementError, match=field):
            fiducial_array_bytes_to_observations(buff[:cut])
    stamp, frame, observations = fiducial_array_bytes_to_observations(buff + b"\0" * 3)  # trailing bytes: as genpy
    assert frame == "cam0_optical" and [o.marker_id for o in observations] == [1, 2] and math.isfinite(stamp)
    # a count that announces more fiducials than there are bytes (a corrupt or hostile message)
    count_at = 16 + len("cam0_optical") + 4
    huge = buff[:count_at] + (2 ** 31).to_bytes(4, "little") + buff[count_at + 4:]
    with pytest.raises(MeasurementError, match="fiducials: 2147483648 announced"):
        fiducial_array_bytes_to_observations(huge)
