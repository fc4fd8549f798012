"""importers.tagslam_measurements: TagSLAM's distance / plane / coordinate measurements."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.importers.tagslam import TAGSLAM_CORNER, tagslam_measurements
from aruco_ring_localization.markers import marker_corners

DATA = Path(__file__).resolve().parents[1] / "data" / "tagslam"


def test_corner_numbers_are_converted_to_the_package_order():
    """TagSLAM's object corners (its tag.cpp): (-s/2, -s/2), (s/2, -s/2), (s/2, s/2), (-s/2, s/2);
    each must be the package's corner of the same position."""
    s = 0.3
    tagslam = np.array([[-s / 2, -s / 2, 0], [s / 2, -s / 2, 0], [s / 2, s / 2, 0], [-s / 2, s / 2, 0]])
    ours = marker_corners(s)
    for k in range(4):
        assert np.allclose(ours[TAGSLAM_CORNER[k]], tagslam[k])
    assert TAGSLAM_CORNER[-1] is None


def test_test_13_distances_and_coordinates():
    m = tagslam_measurements(str(DATA / "test_13" / "tagslam.yaml"))
    assert len(m.distances) == 14 and len(m.planes) == 21
    d = m.distances[0]                       # tag24_60: tag 24 corner 0 to tag 60 corner 0, 6.017 m, noise 0.0002
    assert (d.a.marker_id, d.a.corner, d.b.marker_id, d.b.corner) == (24, 3, 60, 3)
    assert d.distance == 6.017 and d.std == 0.0002 and "tag24_60" in d.key
    assert all(x.std == 0.00159 for x in m.distances[1:])
    p = m.planes[0]                          # tag6_z: corner 0 at z = 2.07 m
    assert p.markers == (6,) and p.points == "3" and np.allclose(p.normal, [0, 0, 1]) and p.distance == 2.07
    assert [(q.marker_id, q.corner) for q in p.marker_points()] == [(6, 3)]
    x = [q for q in m.planes if "tag60_x" in q.key][0]
    assert np.allclose(x.normal, [1, 0, 0]) and x.distance == 0.00635 and x.std == 0.001
    # Ignored tags' measurements are left out.
    assert len(tagslam_measurements(str(DATA / "test_13" / "tagslam.yaml"), exclude={60}).distances) == 10


def test_test_24_plane_of_centres_and_distance():
    m = tagslam_measurements(str(DATA / "test_24" / "tagslam.yaml"))
    (d,), (p,) = m.distances, m.planes
    assert (d.a.marker_id, d.b.marker_id, d.distance, d.std) == (0, 17, 0.72111, 0.01)
    assert p.markers == (0, 36, 72, 108, 180, 216, 252, 288, 324) and p.points == "centres"
    assert p.distance == 0.0 and p.std == 0.01 and np.allclose(p.normal, [0, 0, 1])
    assert tagslam_measurements(str(DATA / "test_12" / "tagslam.yaml")) is None


@pytest.mark.parametrize("body, key", [
    ("distance_measurements: 3", "distance_measurements"),
    ("distance_measurements: [{d: {tag1: 1, tag2: 2, corner1: 5, corner2: 0, distance: 1.0, noise: 0.01}}]",
     "distance_measurements[0].corner1"),
    ("distance_measurements: [{d: {tag1: 1, corner1: 0, corner2: 0, distance: 1.0, noise: 0.01}}]",
     "distance_measurements[0].tag2"),
    ("plane_measurements: [{p: {tags: [1], distance: 0.0, noise: 0.01, direction: [0, 0, 2]}}]",
     "plane_measurements[0].direction"),
    ("coordinate_measurements: [{c: {tag: 1, corner: 0, length: x, noise: 0.01, direction: [0, 0, 1]}}]",
     "coordinate_measurements[0].length"),
])
def test_bad_entries_name_the_file_and_key(tmp_path, body, key):
    path = tmp_path / "tagslam.yaml"
    path.write_text(body + "\n")
    with pytest.raises(ConfigError) as err:
        tagslam_measurements(str(path))
    assert err.value.key == key and str(path) in str(err.value), str(err.value)
