"""Comparison core: alignment between the two map frames, live errors, stops, tables (no ROS)."""
from __future__ import annotations

import numpy as np

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.evaluation.comparison import ComparisonConfig, ComparisonCore
from aruco_ring_localization.evaluation.stops import summarize
from aruco_ring_localization.evaluation.trajectories import apply_se2


def drive(core: ComparisonCore, T_ref_est, rng, stops=((0, 0, 0), (1, 0.5, 1.0), (-1, 1, -2.0), (0.5, -1, 3.0)),
          hold=5.0, move=2.0, rate=10.0, bias=(0.0, 0.0, 0.0), noise=(0.002, 0.002, 0.001)):
    """Stop-and-go through ``stops`` (reference frame); feeds the core; returns the last stamp."""
    t = 0.0
    prev = np.asarray(stops[0], dtype=float)
    T_est_ref = geo.se2_from_transform(geo.inverse(geo.transform_from_se2(*T_ref_est)))
    for k, goal in enumerate(stops):
        goal = np.asarray(goal, dtype=float)
        seq = []
        if k:
            for a in np.arange(0, move, 1 / rate):
                f = a / move
                seq.append(prev + f * np.array([goal[0] - prev[0], goal[1] - prev[1],
                                                np.angle(np.exp(1j * (goal[2] - prev[2])))]))
        seq += [goal] * int(hold * rate)
        for ref in seq:
            est_in_ref = ref + np.asarray(bias) + rng.normal(scale=noise)
            est = apply_se2(T_est_ref, est_in_ref[None])[0]
            core.add(t, ref, est)
            t += 1 / rate
        prev = goal
    return t


def test_alignment_and_live_errors():
    rng = np.random.default_rng(0)
    core = ComparisonCore(ComparisonConfig(still_time=3.0))
    T = np.array([2.0, -1.0, 0.7])
    drive(core, T, rng)
    A = core.alignment
    d = np.abs(A - T)
    assert d[0] < 0.003 and d[1] < 0.003 and d[2] < 0.002, f"alignment {A} vs {T}"
    assert core.last_errors is not None and core.last_errors[2] < 0.01, core.last_errors
    assert len(core.stops) == 4, f"expected 4 stops (one per still period), got {len(core.stops)}"
    rows = core.stop_rows()
    s = summarize(rows)
    assert s["position_cm_max"] < 0.5, s
    assert "stops" in core.status_text()


def test_given_alignment_keeps_bias_visible():
    rng = np.random.default_rng(1)
    T = np.array([0.3, 0.2, -0.4])
    core = ComparisonCore(ComparisonConfig(alignment=tuple(T)))
    drive(core, T, rng, bias=(0.03, 0.0, 0.0))
    rows = core.stop_rows()
    dx = np.array([r.errors[0] for r in rows])
    assert np.all(np.abs(dx - 0.03) < 0.003), f"given alignment must not absorb a 3 cm bias: {dx}"
    assert core.alignment_given and np.allclose(core.alignment, T)


def test_requested_stop_and_write(tmp_path):
    rng = np.random.default_rng(2)
    core = ComparisonCore(ComparisonConfig(still_time=0.0))
    assert core.record_stop() is None
    drive(core, np.zeros(3), rng)
    assert not core.stops, "still_time 0 disables automatic stops"
    stop = core.record_stop()
    assert stop is not None and stop.source == "request" and len(stop.stamps) in (10, 11), stop
    paths = core.write(str(tmp_path), reference_name="ground truth")
    text = (tmp_path / "table1.md").read_text()
    assert "ground truth" in text and "| 1 |" in text and "fitted alignment" in text, text
    assert (tmp_path / "table2.csv").is_file() and (tmp_path / "comparison_summary.json").is_file(), paths


def test_time_jump_back_clears_pairs():
    core = ComparisonCore(ComparisonConfig(min_pairs=3))
    for t in range(5):
        core.add(float(t), (t * 0.1, 0, 0), (t * 0.1, 0, 0))
    assert core.n_pairs == 5
    core.add(0.5, (0, 0, 0), (0, 0, 0))
    assert core.n_pairs == 1, core.n_pairs


def test_rejects_nan():
    import pytest

    from aruco_ring_localization.errors import GeometryError

    core = ComparisonCore()
    with pytest.raises(GeometryError):
        core.add(0.0, (np.nan, 0, 0), (0, 0, 0))
