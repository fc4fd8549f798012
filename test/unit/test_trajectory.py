"""Trajectory evaluation: TUM round trip, time matching, SE(2) alignment, stops, tables, CLI."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import trajectory as tr
from aruco_ring_localization.cli import main as cli_main
from aruco_ring_localization.errors import ConfigError, GeometryError


def stop_and_go(rng: np.random.Generator, n_stops: int = 5, hold: float = 4.0, move: float = 2.0, rate: float = 20.0):
    """A reference that visits ``n_stops`` random poses, holding each for ``hold`` s (seeded)."""
    targets = np.column_stack([rng.uniform(-2, 2, n_stops), rng.uniform(-1.5, 1.5, n_stops),
                               rng.uniform(-np.pi, np.pi, n_stops)])
    stamps, poses = [], []
    t, prev = 0.0, targets[0]
    for k, goal in enumerate(targets):
        if k:
            for a in np.arange(0, move, 1 / rate):
                f = a / move
                stamps.append(t)
                poses.append([prev[0] + f * (goal[0] - prev[0]), prev[1] + f * (goal[1] - prev[1]),
                              prev[2] + f * np.angle(np.exp(1j * (goal[2] - prev[2])))])
                t += 1 / rate
        for _ in np.arange(0, hold, 1 / rate):
            stamps.append(t)
            poses.append(goal.copy())
            t += 1 / rate
        prev = goal
    poses = np.array(poses)
    poses[:, 2] = np.angle(np.exp(1j * poses[:, 2]))
    return np.array(stamps), poses, targets


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    se2 = np.column_stack([rng.normal(size=20), rng.normal(size=20), rng.uniform(-np.pi, np.pi, 20)])
    traj = tr.Trajectory.from_se2(np.arange(20) * 0.1 + 1e9, se2, z=0.3)
    path = str(tmp_path / "a.tum")
    tr.write_tum(path, traj, header="test")
    back = tr.read_tum(path)
    assert np.allclose(back.stamps, traj.stamps, atol=1e-8)
    err = np.max(np.abs(back.poses - traj.poses))
    assert err < 1e-6, f"TUM round trip changed poses by {err}"


def test_read_tum_names_file_and_line(tmp_path):
    path = tmp_path / "bad.tum"
    path.write_text("# header\n0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n")
    with pytest.raises(ConfigError) as exc:
        tr.read_tum(str(path))
    assert "bad.tum" in str(exc.value) and "line 3" in str(exc.value), str(exc.value)
    path.write_text("0 0 0 0 0 0 0 0\n")
    with pytest.raises(ConfigError, match="line 1"):
        tr.read_tum(str(path))


def test_match_nearest_and_interpolate():
    s = np.arange(0, 10, 0.1)
    ref = tr.Trajectory.from_se2(s, np.column_stack([s, 2 * s, np.zeros_like(s)]))
    es = np.array([0.02, 0.53, 3.33, 20.0])
    est = tr.Trajectory.from_se2(es, np.column_stack([es, 2 * es, np.zeros_like(es)]))
    near = tr.match(ref, est, max_dt=0.05, method="nearest")
    assert len(near) == 3, f"expected 3 matches (20 s is outside), got {len(near)}"
    assert np.allclose(near.ref[:, 0], [0.0, 0.5, 3.3], atol=1e-9), near.ref
    interp = tr.match(ref, est, max_dt=0.15, method="interpolate")
    assert len(interp) == 3
    err = np.max(np.abs(interp.ref[:, :2] - interp.est[:, :2]))
    assert err < 1e-9, f"interpolated reference off by {err}"


def test_align_se2_recovers_transform():
    rng = np.random.default_rng(7)
    ref = np.column_stack([rng.uniform(-3, 3, 50), rng.uniform(-3, 3, 50), rng.uniform(-np.pi, np.pi, 50)])
    T_true = np.array([1.5, -0.7, 0.9])
    # est lives in a frame; ref = T_true * est
    est = tr.apply_se2(tr.invert_se2(T_true), ref) + rng.normal(scale=[0.002, 0.002, 0.001], size=(50, 3))
    T = tr.align_se2(est, ref)
    d = np.abs(T - T_true)
    assert d[0] < 0.003 and d[1] < 0.003 and d[2] < 0.002, f"alignment error {d}"


def test_align_se2_spin_on_the_spot_uses_yaw():
    yaw = np.radians(np.arange(0, 360, 45))
    ref = np.column_stack([np.full(8, 2.0), np.full(8, 1.0), np.angle(np.exp(1j * yaw))])
    T_true = np.array([0.1, 0.2, 0.3])
    est = tr.apply_se2(tr.invert_se2(T_true), ref)
    T = tr.align_se2(est, ref)
    assert np.allclose(T, T_true, atol=1e-9), f"got {T}, want {T_true}"


def test_align_se2_rejects_bad_input():
    with pytest.raises(GeometryError):
        tr.align_se2(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(GeometryError):
        tr.align_se2(np.full((3, 2), np.nan), np.zeros((3, 2)))


def test_se2_compose_invert():
    a = np.array([1.0, 2.0, 2.5])
    ident = tr.compose_se2(a, tr.invert_se2(a))
    assert np.allclose(ident, 0, atol=1e-12), ident


def test_stops_and_tables_recover_known_errors():
    rng = np.random.default_rng(3)
    stamps, ref, targets = stop_and_go(rng, n_stops=5)
    offset = np.array([0.01, -0.02, np.radians(0.5)])  # a constant error, estimate - reference
    est = ref + offset + rng.normal(scale=[0.001, 0.001, 0.0005], size=ref.shape)
    pairs = tr.MatchedPairs(stamps, ref, est)
    stops = tr.detect_stops(stamps, ref, min_duration=2.0)
    assert len(stops) == 5, f"expected 5 stops, found {len(stops)}: {stops}"
    rows = tr.stop_errors(pairs, stops)
    for r, target in zip(rows, targets):
        assert np.allclose(r.ref[:2], target[:2], atol=1e-9)
        dx, dy, d, dyaw = r.errors
        assert abs(dx - 0.01) < 0.001 and abs(dy + 0.02) < 0.001, f"stop {r.label}: dx {dx}, dy {dy}"
        assert abs(np.degrees(dyaw) - 0.5) < 0.05, f"stop {r.label}: dyaw {np.degrees(dyaw)} deg"
    s = tr.summarize(rows)
    assert abs(s["position_cm_median"] - 100 * np.hypot(0.01, 0.02)) < 0.1, s
    md1 = tr.position_table_markdown(rows)
    md2 = tr.orientation_table_markdown(rows)
    assert md1.count("\n| ") == 6 and "Median Euclidean error" in md1, md1
    assert "+0.5" in md2, md2
    csv = tr.stops_csv(rows).splitlines()
    assert len(csv) == 6 and csv[0].startswith("label,"), csv


def test_stops_settle_and_short_holds():
    stamps = np.arange(0, 10, 0.1)
    ref = np.zeros((len(stamps), 3))
    ref[stamps >= 5, 0] = 1.0
    assert len(tr.detect_stops(stamps, ref, min_duration=4.0)) == 2
    assert len(tr.detect_stops(stamps, ref, min_duration=4.0, settle=1.0)) == 0


def test_evaluate_cli(tmp_path, capsys):
    rng = np.random.default_rng(11)
    stamps, ref, _ = stop_and_go(rng, n_stops=4)
    T = np.array([0.5, -1.0, 0.4])
    est = tr.apply_se2(tr.invert_se2(T), ref) + rng.normal(scale=[0.002, 0.002, 0.001], size=ref.shape)
    rp, ep = str(tmp_path / "ref.tum"), str(tmp_path / "est.tum")
    tr.write_tum(rp, tr.Trajectory.from_se2(stamps, ref))
    tr.write_tum(ep, tr.Trajectory.from_se2(stamps + 0.01, est))
    out = tmp_path / "out"
    code = cli_main(["evaluate", "--reference", rp, "--estimate", ep, "--stops", "--out", str(out)])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "4 stops" in text, text
    for name in ("table1.md", "table1.csv", "table2.md", "pairs.csv", "summary.json", "trajectory.png",
                 "positions.png", "orientations.png", "estimate_aligned.tum"):
        assert (out / name).is_file(), f"{name} missing; have {sorted(p.name for p in out.iterdir())}"
    import json

    summary = json.loads((out / "summary.json").read_text())
    assert summary["stops"]["position_cm_max"] < 1.0, summary
    assert abs(summary["alignment"]["yaw_deg"] - np.degrees(0.4)) < 0.1, summary
    # without alignment the errors are large: the frames differ by 1.1 m
    code = cli_main(["evaluate", "--reference", rp, "--estimate", ep, "--align", "none"])
    text = capsys.readouterr().out
    assert code == 0 and "max" in text


def test_evaluate_cli_no_overlap(tmp_path, capsys):
    a = tr.Trajectory.from_se2([0.0, 1.0], np.zeros((2, 3)))
    b = tr.Trajectory.from_se2([100.0, 101.0], np.zeros((2, 3)))
    tr.write_tum(str(tmp_path / "a.tum"), a)
    tr.write_tum(str(tmp_path / "b.tum"), b)
    code = cli_main(["evaluate", "--reference", str(tmp_path / "a.tum"), "--estimate", str(tmp_path / "b.tum")])
    err = capsys.readouterr().err
    assert code == 1 and "no estimate pose" in err, err
