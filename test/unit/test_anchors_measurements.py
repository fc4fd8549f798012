"""anchors: survey measurements (distances, planes) in the anchors file, their record and check."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.anchors import (anchors_from_dict, check_measurement_report, load_anchors,
                                             measurement_lines, measurement_report)
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.markers import marker_corners

ANCHORS = "anchors: [{marker: 3, position: [0, 0, 0], std: 0.001}, {marker: 4, position: [2, 0, 0], std: 0.001}]\n"
DIST = "distances: [{from: {marker: 3, corner: 0}, to: {marker: 4, corner: centre}, distance: 2.0, std: 0.001}]\n"
PLANE = "planes: [{markers: [3, 4], normal: [0, 0, 1], distance: 0.0, std: 0.002}]\n"


def test_file_round_trip_with_measurements(tmp_path):
    path = tmp_path / "plate.yaml"
    path.write_text(ANCHORS + DIST + PLANE.replace("std: 0.002}", "std: 0.002, points: centres, instrument: level}"))
    a = load_anchors(str(path))
    (d,), (p,) = a.measurements.distances, a.measurements.planes
    assert (d.a.marker_id, d.a.corner, d.b.marker_id, d.b.corner) == (3, 0, 4, None)
    assert d.distance == 2.0 and d.std == 0.001 and d.key == "distances[0]"
    assert p.markers == (3, 4) and p.points == "centres" and p.instrument == "level"
    assert [(q.marker_id, q.corner) for q in p.marker_points()] == [(3, None), (4, None)]
    back = anchors_from_dict(yaml.safe_load(yaml.safe_dump(a.to_dict())))
    assert back.measurements.to_dict() == a.measurements.to_dict() and back.ids == a.ids


def test_a_file_of_distances_only_defines_no_frame(tmp_path):
    path = tmp_path / "tape.yaml"
    path.write_text(DIST)
    a = load_anchors(str(path))
    assert a.anchors == [] and len(a.measurements) == 1 and a.measurements.ids == [3, 4]
    # A plane is in the surveyed frame: without anchors there is none.
    path.write_text(DIST + PLANE)
    with pytest.raises(ConfigError) as err:
        load_anchors(str(path))
    assert err.value.key == "planes[0]" and str(path) in str(err.value)


@pytest.mark.parametrize("body, key", [
    ("distances: 3", "distances"),
    ("distances: [{from: {marker: 3, corner: 0}, distance: 2.0, std: 0.001}]", "distances[0].to"),
    ("distances: [{from: {marker: 3, corner: 4}, to: {marker: 4}, distance: 2.0, std: 0.001}]",
     "distances[0].from.corner"),
    ("distances: [{from: {marker: 3, corner: middle}, to: {marker: 4}, distance: 2.0, std: 0.001}]",
     "distances[0].from.corner"),
    ("distances: [{from: {marker: -3}, to: {marker: 4}, distance: 2.0, std: 0.001}]", "distances[0].from.marker"),
    ("distances: [{from: {marker: 3, side: 1}, to: {marker: 4}, distance: 2.0, std: 0.001}]",
     "distances[0].from.side"),
    ("distances: [{from: {marker: 3}, to: {marker: 3, corner: 1}, distance: 2.0, std: 0.001}]", "distances[0].to"),
    ("distances: [{from: {marker: 3}, to: {marker: 4}, distance: -2.0, std: 0.001}]", "distances[0].distance"),
    ("distances: [{from: {marker: 3}, to: {marker: 4}, distance: 2.0, std: 0}]", "distances[0].std"),
    ("distances: [{from: {marker: 3}, to: {marker: 4}, distance: 2.0, std: 0.001, length: 2}]",
     "distances[0].length"),
    (ANCHORS + "planes: [{markers: [], normal: [0, 0, 1], distance: 0, std: 0.01}]", "planes[0].markers"),
    (ANCHORS + "planes: [{markers: [3, 3], normal: [0, 0, 1], distance: 0, std: 0.01}]", "planes[0].markers"),
    (ANCHORS + "planes: [{markers: [3], normal: [0, 0, 2], distance: 0, std: 0.01}]", "planes[0].normal"),
    (ANCHORS + "planes: [{markers: [3], normal: [0, 1], distance: 0, std: 0.01}]", "planes[0].normal"),
    (ANCHORS + "planes: [{markers: [3], normal: [0, 0, 1], distance: .nan, std: 0.01}]", "planes[0].distance"),
    (ANCHORS + "planes: [{markers: [3], normal: [0, 0, 1], distance: 0, std: 0.01, points: edges}]",
     "planes[0].points"),
    (ANCHORS + "planes: [{markers: [3], normal: [0, 0, 1], distance: 0}]", "planes[0].std"),
    ("planes: [{markers: [3], normal: [0, 0, 1], distance: 0, std: 0.01}]", "planes[0]"),
])
def test_bad_measurements_name_the_file_and_key(tmp_path, body, key):
    path = tmp_path / "bad_survey.yaml"
    path.write_text(body + "\n")
    with pytest.raises(ConfigError) as err:
        load_anchors(str(path))
    assert err.value.key == key and str(path) in str(err.value), str(err.value)


def _map():
    """Marker 3 at the origin facing up, marker 4 2 m along x and 1 cm higher."""
    return {3: np.eye(4), 4: geo.make_transform(np.eye(3), [2.0, 0.0, 0.01])}


def test_report_gives_each_residual_and_the_check_flags_beyond_the_limit():
    a = anchors_from_dict(yaml.safe_load(ANCHORS + DIST + PLANE), source="plate.yaml")
    T = _map()
    rep = measurement_report(a.measurements, T, lambda m: 0.2)
    (d,), (p,) = rep["distances"], rep["planes"]
    mapped = float(np.linalg.norm(marker_corners(0.2)[0] - T[4][:3, 3]))
    assert d["mapped_distance"] == pytest.approx(mapped)
    assert d["residual_mm"] == pytest.approx(1000 * (mapped - 2.0))
    assert d["residual_sigmas"] == pytest.approx(abs(mapped - 2.0) / 0.001)
    # Marker 4's corners are 10 mm above the plane z = 0: 5 sigma of 2 mm.
    assert p["residual_mm"] == pytest.approx(10.0) and p["residual_sigmas"] == pytest.approx(5.0)
    assert p["worst"]["marker"] == 4 and p["rms_mm"] == pytest.approx(10.0 / np.sqrt(2))
    # The distance is 102 mm off (corner 0 to the centre, not 2 m): flagged at 6 sigma, the plane not.
    (problem,) = check_measurement_report(rep, 6.0)
    assert "distances[0]" in problem and "plate.yaml" in problem, problem
    problems = check_measurement_report(rep, 4.9)
    assert len(problems) == 2
    assert "planes[0]" in problems[1] and "marker 4" in problems[1] and "plate.yaml" in problems[1], problems
    assert len(measurement_lines(rep)) == 2
    # A marker not in the map: recorded, not checked.
    rep = measurement_report(a.measurements, {3: T[3]}, lambda m: 0.2)
    assert rep["distances"][0]["mapped"] is False and check_measurement_report(rep, 0.1) == []
