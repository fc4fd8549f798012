"""evaluation.stops: stops found at the right times, the errors at each stop, settle, summaries."""
from __future__ import annotations

import numpy as np

from helpers import stop_and_go

from aruco_ring_localization.evaluation.stops import Stop, StopError, detect_stops, stop_errors, summarize
from aruco_ring_localization.evaluation.trajectories import MatchedPairs


def test_stops_found_at_the_right_times_with_known_errors():
    rng = np.random.default_rng(3)
    stamps, ref, targets, holds = stop_and_go(rng, n_stops=5)
    stops = detect_stops(stamps, ref, min_duration=2.0)
    assert len(stops) == 5, f"expected 5 stops, found {len(stops)}: {stops}"
    for stop, (start, end) in zip(stops, holds):
        # within one sample (1/20 s): the first pose of the next move still equals the goal
        assert abs(stop.start - start) <= 0.05 + 1e-9 and abs(stop.end - end) <= 0.05 + 1e-9, (stop, start, end)
    offset = np.array([0.01, -0.02, np.radians(0.5)])  # a constant error, estimate - reference
    est = ref + offset + rng.normal(scale=[0.001, 0.001, 0.0005], size=ref.shape)
    rows = stop_errors(MatchedPairs(stamps, ref, est), stops)
    for r, target in zip(rows, targets):
        assert np.allclose(r.ref[:2], target[:2], atol=1e-9)
        dx, dy, d, dyaw = r.errors
        # 1 mm noise, medians over ~80 poses: 1 mm / 0.05 deg are several sigma
        assert abs(dx - 0.01) < 0.001 and abs(dy + 0.02) < 0.001, f"stop {r.label}: dx {dx}, dy {dy}"
        assert abs(np.degrees(dyaw) - 0.5) < 0.05, f"stop {r.label}: dyaw {np.degrees(dyaw)} deg"
    s = summarize(rows)
    assert abs(s["position_cm_median"] - 100 * np.hypot(0.01, 0.02)) < 0.1, s


def test_settle_and_short_holds():
    stamps = np.arange(0, 10, 0.1)
    ref = np.zeros((len(stamps), 3))
    ref[stamps >= 5, 0] = 1.0
    assert len(detect_stops(stamps, ref, min_duration=4.0)) == 2
    assert len(detect_stops(stamps, ref, min_duration=4.0, settle=1.0)) == 0
    turned = ref.copy()
    turned[stamps >= 2.5, 2] = np.radians(1.0)  # a 1 deg turn ends the first stop (tolerance 0.5 deg)
    assert [round(s.start, 1) for s in detect_stops(stamps, turned, min_duration=2.0)] == [0.0, 2.5, 5.0]


def test_stop_without_estimates_and_missing_rows():
    pairs = MatchedPairs(np.array([0.0, 1.0]), np.zeros((2, 3)), np.zeros((2, 3)))
    assert stop_errors(pairs, [Stop(5.0, 6.0)]) == []
    missing = StopError("1", np.zeros(3), np.full(3, np.nan), 0)
    good = StopError("2", np.zeros(3), np.array([0.03, 0.04, 0.0]))
    assert not missing.ok and good.ok
    assert summarize([missing, good])["position_cm_max"] == 5.0
    assert summarize([missing]) == {"n": 0}
