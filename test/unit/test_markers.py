"""Unit tests of markers.py: corner order (checked against OpenCV), size overrides, id lists, quads."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.camera import default_model_for_tests
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.markers import (MarkerSizes, marker_corners, parse_id_list, parse_size_overrides,
                                             quad_is_degenerate)

from helpers import assert_close


def test_marker_corners_positions_and_order():
    c = marker_corners(0.2)
    assert c.shape == (4, 3)
    assert_close(c, [[-0.1, 0.1, 0], [0.1, 0.1, 0], [0.1, -0.1, 0], [-0.1, -0.1, 0]], 0.0, "corners")


def test_marker_corners_match_opencv_ippe_square_order():
    # OpenCV documents SOLVEPNP_IPPE_SQUARE's object points in exactly this order.
    L = 0.15
    expected = np.array([[-L / 2, L / 2, 0], [L / 2, L / 2, 0], [L / 2, -L / 2, 0], [-L / 2, -L / 2, 0]])
    assert_close(marker_corners(L), expected, 0.0, "IPPE_SQUARE order")


def test_marker_corners_solvepnp_recovers_the_pose():
    model = default_model_for_tests("plumb_bob")
    T_cam_marker = geo.make_transform(geo.matrix_from_rpy(np.pi + 0.2, 0.3, 0.1), [0.1, -0.05, 1.5])
    obj = marker_corners(0.2)
    px = model.project(geo.transform_points(T_cam_marker, obj))
    ok, rvec, tvec = cv2.solvePnP(obj, px, model.K, model.opencv_distortion, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    assert ok
    T = geo.transform_from_rvec_tvec(rvec, tvec)
    d, a = geo.pose_distance(T, T_cam_marker)
    assert d < 1e-6 and a < 1e-6, f"solvePnP pose off by {d} m, {a} rad"


def test_detected_corner_order_is_top_left_first():
    """Render an upright marker, detect it with OpenCV and check corner 0 is its top-left."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    marker = cv2.aruco.generateImageMarker(dictionary, 7, 120)
    image = np.full((240, 320), 255, np.uint8)
    image[60:180, 100:220] = marker
    detector = cv2.aruco.ArucoDetector(dictionary, cv2.aruco.DetectorParameters())
    corners, ids, _ = detector.detectMarkers(image)
    assert ids is not None and list(ids.ravel()) == [7]
    c = corners[0].reshape(4, 2)
    # Image axes: u right, v down. Marker frame: x right, y up; corners 0 TL, 1 TR, 2 BR, 3 BL.
    expected = np.array([[100, 60], [220, 60], [220, 180], [100, 180]], float)
    assert np.abs(c - expected).max() < 2.0, f"detected corners {c.tolist()} vs {expected.tolist()}"
    # The same order as the model corners seen from a camera facing the marker.
    T_cam_marker = geo.make_transform(np.diag([1.0, -1.0, -1.0]), [0, 0, 1.0])
    model = default_model_for_tests("plumb_bob", np.zeros(5))
    px = model.project(geo.transform_points(T_cam_marker, marker_corners(0.2)))
    assert px[0, 0] < px[1, 0] and px[0, 1] < px[3, 1] and px[2, 0] > px[3, 0], px


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan"), float("inf")])
def test_marker_corners_reject_bad_lengths(bad):
    with pytest.raises(ConfigError):
        marker_corners(bad)


def test_parse_size_overrides():
    sizes = parse_size_overrides("1-10: 0.05, 12: 0.06")
    assert sizes == {**{i: 0.05 for i in range(1, 11)}, 12: 0.06}
    assert parse_size_overrides("") == {} and parse_size_overrides(None) == {} and parse_size_overrides("  ") == {}
    assert parse_size_overrides(" 3 - 4 :0.1 ,") == {3: 0.1, 4: 0.1}
    # Later entries win.
    assert parse_size_overrides("1-3: 0.05, 2: 0.07") == {1: 0.05, 2: 0.07, 3: 0.05}


def test_parse_id_list():
    assert parse_id_list("1,4,9-12") == frozenset({1, 4, 9, 10, 11, 12})
    assert parse_id_list("") == frozenset() and parse_id_list(None) == frozenset()
    assert parse_id_list(" 5 , 5, 6-6 ,") == frozenset({5, 6})
    assert parse_id_list([1, 2, "7-8"]) == frozenset({1, 2, 7, 8})


@pytest.mark.parametrize("text, needle", [
    ("1-", "1-"), ("a", "'a'"), ("5-3", "empty id range"), ("1;2", "1;2"), ("-3", "-3"), ("1.5", "1.5"),
    ("4096", "4096"), ("1-5000", "5000"),
])
def test_parse_id_list_errors_name_the_key_and_the_token(text, needle):
    with pytest.raises(ConfigError) as info:
        parse_id_list(text, key="ignore_fiducials", source="detect.yaml")
    msg = str(info.value)
    assert "ignore_fiducials" in msg and needle in msg and "detect.yaml" in msg, msg


@pytest.mark.parametrize("text, needle", [
    ("1-10 0.05", "ids: length"), ("1: abc", "abc"), ("1: -0.1", "positive"), ("1: 0", "positive"),
    ("x: 0.1", "'x'"), ("3-1: 0.1", "empty id range"), ("1: nan", "positive"),
])
def test_parse_size_overrides_errors_name_the_key(text, needle):
    with pytest.raises(ConfigError) as info:
        parse_size_overrides(text)
    msg = str(info.value)
    assert "fiducial_len_override" in msg and needle in msg, msg


def test_marker_sizes():
    sizes = MarkerSizes.parse(0.14, "1-10: 0.05, 12: 0.06")
    assert sizes(0) == 0.14 and sizes(5) == 0.05 and sizes(12) == 0.06 and sizes(np.int64(11)) == 0.14
    assert_close(sizes.corners(12), marker_corners(0.06), 0.0, "corners of 12")
    with pytest.raises(ConfigError, match="fiducial_len"):
        MarkerSizes(0.0)


SQUARE = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)


@pytest.mark.parametrize("quad, degenerate", [
    (SQUARE, False),
    (SQUARE[::-1], False),  # other winding
    (np.array([[100, 100], [180, 110], [175, 190], [95, 170]], float), False),  # perspective quad
    (np.array([[0, 0], [10, 10], [10, 0], [0, 10]], float), True),  # self-intersecting bow tie
    (np.array([[0, 0], [10, 0], [2, 2], [0, 10]], float), True),  # non-convex dart
    (np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float), True),  # 1 px^2 < 4 px^2
    (np.array([[0, 0], [5, 0], [10, 0], [15, 0]], float), True),  # collinear
    (np.array([[0, 0], [10, 0], [10, 10], [10, 10]], float), True),  # repeated corner
    (np.array([[0, 0], [10, 0], [np.nan, 10], [0, 10]], float), True),
    (np.array([[0, 0], [10, 0], [np.inf, 10], [0, 10]], float), True),
    (SQUARE[:3], True),  # wrong shape
    (np.zeros((4, 3)), True),
])
def test_quad_is_degenerate(quad, degenerate):
    assert quad_is_degenerate(quad) is degenerate, quad.tolist()


def test_quad_min_area_threshold():
    small = SQUARE * 0.3  # 9 px^2
    assert not quad_is_degenerate(small, min_area_px=4.0)
    assert quad_is_degenerate(small, min_area_px=10.0)


def test_quads_ok_scalar_and_array_paths_agree():
    # Up to markers._SCALAR_QUADS quads are checked on Python floats, more with numpy: the same
    # answer for every kind of quad, hostile ones included (NaN, inf, 1e200, zero, self-crossing).
    import warnings

    from aruco_ring_localization import markers

    rng = np.random.default_rng(5)
    Q = rng.normal(0, 20, (4000, 4, 2)) + rng.uniform(0, 1000, (4000, 1, 2))
    Q[::7] *= 0.05            # some below the minimum area
    Q[::97] *= 1e200          # products overflow
    Q[::89, 1, 0] = np.nan
    Q[::83, 2] = np.inf
    Q[::101] = 0.0
    Q[::103] = Q[::103][:, [0, 2, 1, 3]]   # self-intersecting
    n = markers._SCALAR_QUADS
    with warnings.catch_warnings():
        warnings.simplefilter("error")     # neither path may warn about overflow or NaN
        array = markers.quads_ok(Q)
        scalar = np.concatenate([markers.quads_ok(Q[i:i + n]) for i in range(0, len(Q), n)])
    assert 0 < array.sum() < len(Q)
    np.testing.assert_array_equal(scalar, array)
