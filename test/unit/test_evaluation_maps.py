"""evaluation.maps.map_error: reference-frame comparison, best fit, missing markers."""
from __future__ import annotations

import numpy as np

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.evaluation.maps import align_map_to_truth, map_error, map_frame_error
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap, map_frame_from_reference
from aruco_ring_localization.simulation.scene import Scene


def _as_estimate(truth: MarkerMap, ref: int, move=None) -> MarkerMap:
    """The truth re-expressed in the map frame fixed to ``ref`` (what a perfect mapper returns)."""
    T_map_truth = geo.inverse(map_frame_from_reference(truth.T_map_marker(ref)))
    out = MarkerMap(reference_marker=ref, method="test")
    for e in truth:
        T = T_map_truth @ e.T_map_marker
        if move and e.marker_id in move:
            T = geo.make_transform(T[:3, :3], T[:3, 3] + move[e.marker_id])
        out.add(MarkerEntry(e.marker_id, T, e.size))
    return out


def test_perfect_map_has_zero_error_and_offsets_are_measured():
    truth = Scene.default().truth_map()
    est = _as_estimate(truth, 95)
    err = map_error(est, truth)
    assert err["position_max_mm"] < 1e-9 and err["rotation_max_deg"] < 1e-9, err
    moved = _as_estimate(truth, 95, move={17: np.array([0.003, 0.0, 0.004])})
    err = map_error(moved, truth)
    assert abs(err["per_marker"][17][0] - 5.0) < 1e-6, err["per_marker"][17]
    assert abs(err["position_max_mm"] - 5.0) < 1e-6


def test_frame_error_is_not_hidden_but_best_fit_removes_it():
    truth = Scene.default().truth_map()
    est = _as_estimate(truth, 95)
    # Rotate the whole estimate by 0.5 deg about z: the reference comparison sees it, best fit does not.
    R = geo.make_transform(geo.rot_z(np.radians(0.5)))
    rotated = MarkerMap([MarkerEntry(e.marker_id, R @ e.T_map_marker, e.size) for e in est], reference_marker=95)
    ref = map_error(rotated, truth)
    fit = map_error(rotated, truth, best_fit=True)
    assert ref["position_rms_mm"] > 10.0, ref["position_rms_mm"]
    assert fit["position_rms_mm"] < 1e-6 and fit["alignment"] == "best_fit", fit["position_rms_mm"]
    T = align_map_to_truth(rotated, truth)
    assert np.allclose(geo.transform_points(T, rotated.corners(17)), truth.corners(17), atol=1e-9)
    fe = map_frame_error(rotated, truth)
    assert abs(abs(fe["yaw_deg"]) - 0.5) < 1e-6, fe
    assert abs(fe["mm_at_5m"] - 5000 * np.radians(0.5)) < 0.01, fe
    assert abs(map_frame_error(est, truth)["yaw_deg"]) < 1e-9


def test_missing_and_extra_markers_listed():
    truth = Scene.default().truth_map()
    est = _as_estimate(truth, 95)
    est.remove(17)
    est.add(MarkerEntry(5000, np.eye(4), 0.2))
    err = map_error(est, truth)
    assert err["missing"] == [17] and err["extra"] == [5000] and err["n"] == len(truth) - 1
