"""TrackingDetector (detection.py): regions around the previous image's markers between
whole-image searches give the whole image's detections, lose nothing that stays in view, and
search the whole image on schedule and whenever a marker goes missing."""
from __future__ import annotations

import os

import cv2
import numpy as np

from aruco_ring_localization.detection import Detector, DetectorParams, TrackingDetector

from helpers import REPO

_DICT = cv2.aruco.getPredefinedDictionary(7)
UBIQUITY = os.path.join(REPO, "test", "data", "ubiquity_fiducials")


def scene_image(markers, width=1280, height=960, background=210, blur=0.7):
    """mono8 image with axis-aligned markers [(id, x0, y0, side px)] on a light background, blurred
    by a Gaussian of ``blur`` px."""
    img = np.full((height, width), background, np.uint8)
    for marker_id, x0, y0, side in markers:
        tile = cv2.aruco.generateImageMarker(_DICT, marker_id, side)
        img[y0:y0 + side, x0:x0 + side] = tile
    return cv2.GaussianBlur(img, (0, 0), blur)


def ids(obs):
    return sorted(o.marker_id for o in obs)


def test_regions_give_the_whole_image_corners_on_the_conformance_images():
    for name in ("aruco_detect_test_images/tag_01_d7_14cm.png", "aruco_detect_test_images/tag_245-246_d7_14cm.png",
                 "fiducial_slam_test/403.jpg"):
        img = cv2.imread(os.path.join(UBIQUITY, name), cv2.IMREAD_GRAYSCALE)
        assert img is not None, name
        for refinement in ("lines", "subpix"):
            plain = Detector(DetectorParams(corner_refinement=refinement)).detect(img)
            tracker = TrackingDetector(Detector(DetectorParams(corner_refinement=refinement)), edge_px=0)
            tracker.detect(img)                 # whole image
            again = tracker.detect(img)         # regions only
            assert tracker.region_searches == 1 and tracker.full_searches == 1
            assert ids(again) == ids(plain) and plain, f"{name}: {ids(again)} vs {ids(plain)}"
            ref = {o.marker_id: o.corners for o in plain}
            worst = max(float(np.abs(o.corners - ref[o.marker_id]).max()) for o in again)
            # the same pixels: only float32 rounding around another origin (measured 5e-4 px)
            assert worst < 2e-3, f"{name} {refinement}: corners moved {worst:.2e} px in a region"


def test_whole_image_every_n_and_new_markers_found_then():
    first = scene_image([(3, 500, 300, 120)])
    both = scene_image([(3, 500, 300, 120), (9, 700, 600, 100)])   # 9 appears in the middle
    t = TrackingDetector(Detector(), full_every=4, edge_px=0)
    assert ids(t.detect(first)) == [3] and t.full_searches == 1
    seen = [ids(t.detect(both)) for _ in range(3)]
    assert seen == [[3], [3], [3]], seen   # regions only: 9 not searched yet
    assert t.region_searches == 3
    assert ids(t.detect(both)) == [3, 9] and t.full_searches == 2   # the 4th image is searched whole


def test_border_strips_find_a_marker_coming_in_from_the_side_at_once():
    first = scene_image([(3, 500, 300, 120)])
    entering = scene_image([(3, 500, 300, 120), (11, 1180, 400, 90)])
    t = TrackingDetector(Detector(), full_every=10, edge_px=128)
    t.detect(first)
    assert ids(t.detect(entering)) == [3, 11] and t.full_searches == 1


def test_border_strips_take_the_threshold_windows_in_turn():
    # Blurred (sigma 2.5 px): the 3 px threshold window misses the marker, 13 and 23 find it.
    first = scene_image([(3, 500, 300, 120)], blur=2.5)
    entering = scene_image([(3, 500, 300, 120), (11, 1180, 400, 90)], blur=2.5)
    det = Detector()
    assert det.params.threshold_windows() == [3, 13, 23]
    assert ids(det.detect_in(entering, [(1152, 0, 1280, 960)], window=3)) == []
    assert ids(det.detect_in(entering, [(1152, 0, 1280, 960)], window=13)) == [11]
    t = TrackingDetector(det, full_every=10, edge_px=128)
    t.detect(first)
    seen = [ids(t.detect(entering)) for _ in range(2)]
    assert seen == [[3], [3, 11]], seen      # window 3 first, then 13 finds it in the strip
    assert t.full_searches == 1 and t.region_searches == 2


def test_scheduled_whole_image_searches_take_the_windows_in_turn_and_keep_the_tracked_markers():
    # Blurred (sigma 2.5 px): the 3 px window finds neither marker, 13 and 23 find both.
    first = scene_image([(3, 500, 300, 120)], blur=2.5)
    both = scene_image([(3, 500, 300, 120), (9, 700, 600, 100)], blur=2.5)   # 9 appears in the middle
    assert ids(Detector(DetectorParams(adaptive_thresh_win_size_max=3)).detect(both)) == []
    t = TrackingDetector(Detector(), full_every=2, edge_px=0)
    assert ids(t.detect(first)) == [3] and t.full_searches == 1             # nothing tracked: all windows
    seen = [ids(t.detect(both)) for _ in range(4)]
    # regions, whole image with window 3 (9 not seen; 3 kept by its region's windows), regions,
    # whole image with window 13 (9 found)
    assert seen == [[3], [3], [3], [3, 9]], seen
    assert t.full_searches == 3 and t.region_searches == 2
    t = TrackingDetector(Detector(), full_every=2, edge_px=0, windows_in_turn=False)
    t.detect(first)
    assert [ids(t.detect(both)) for _ in range(2)] == [[3], [3, 9]]      # all windows on schedule


def test_a_camera_that_saw_nothing_finds_a_marker_in_the_middle_at_once():
    # nothing tracked: every image is searched whole with all windows (rostest detector.test
    # publishes its conformance image after a blank one)
    t = TrackingDetector(Detector(), full_every=5, edge_px=128)
    assert ids(t.detect(scene_image([]))) == []
    assert ids(t.detect(scene_image([(9, 700, 600, 100)], blur=2.5))) == [9]
    assert t.full_searches == 2 and t.region_searches == 0


def test_a_lost_marker_makes_the_same_image_searched_whole():
    before = scene_image([(3, 500, 300, 120), (5, 200, 600, 80)])
    moved = scene_image([(3, 500, 300, 120), (5, 900, 150, 80)])     # 5 jumped out of its region
    t = TrackingDetector(Detector(), full_every=10, edge_px=0)
    t.detect(before)
    assert ids(t.detect(moved)) == [3, 5]
    assert t.full_searches == 2 and t.region_searches == 0


def test_regions_do_not_overlap_and_stay_in_the_image():
    t = TrackingDetector(Detector(), edge_px=64)
    t.detect(scene_image([(1, 10, 10, 60), (2, 90, 20, 60), (3, 1180, 860, 90), (4, 600, 400, 100)]))
    boxes = t.regions((960, 1280))
    assert t.strips((960, 1280)) == [(0, 0, 64, 960), (1216, 0, 1280, 960)]
    for i, a in enumerate(boxes):
        assert 0 <= a[0] < a[2] <= 1280 and 0 <= a[1] < a[3] <= 960, a
        for b in boxes[i + 1:]:
            assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]), (a, b)


def test_full_every_one_is_the_plain_detector_and_size_change_resets():
    img = scene_image([(3, 500, 300, 120)])
    t = TrackingDetector(Detector(), full_every=1)
    for _ in range(3):
        t.detect(img)
    assert t.full_searches == 3 and t.region_searches == 0
    t = TrackingDetector(Detector(), full_every=5)
    t.detect(img)
    small = scene_image([(3, 100, 100, 120)], width=640, height=480)
    assert ids(t.detect(small)) == [3] and t.full_searches == 2
