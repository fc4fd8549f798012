"""evaluation.report (the demo's pure parts): route, motion, report files, summary table, on synthetic runs."""
from __future__ import annotations

import json

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.evaluation import report
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap, map_frame_from_reference
from aruco_ring_localization.simulation.scene import Scene


def test_plan_has_paper_stops():
    scene = Scene.default()
    stops = report.plan_stops(scene.test_positions, scene.test_orientations)
    assert [s.kind for s in stops].count("position") == 15
    assert [s.kind for s in stops].count("orientation") == 8
    assert stops[0].label == "1" and stops[-1].label == "8"
    labels = [s.label for s in stops if s.kind == "position"]
    assert sorted(labels, key=int) == [str(k) for k in range(1, 16)], labels
    hops = [np.hypot(b.pose[0] - a.pose[0], b.pose[1] - a.pose[1]) for a, b in zip(stops[:14], stops[1:15])]
    assert max(hops) < 1.0, f"serpentine route expected, longest hop {max(hops):.2f} m"


def test_interpolate_motion_reaches_goal_within_limits():
    a, b, dt = (0.0, 0.0, 3.0), (1.0, 0.5, -3.0), 0.2
    seq = report.interpolate_motion(a, b, dt, max_speed=0.5, max_yaw_rate=1.0)
    assert np.allclose(seq[-1][0], b), seq[-1][0]
    poses = np.array([a] + [p for p, _ in seq])
    step = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert step.max() <= 0.5 * dt + 1e-9, f"step {step.max()} m exceeds the speed limit"
    dyaw = np.abs(np.angle(np.exp(1j * np.diff(poses[:, 2]))))
    assert dyaw.max() <= 1.0 * dt + 1e-9, "turned the long way round or too fast"
    # the command integrates to the motion (robot frame -> world)
    p, cmd = seq[0]
    c, s = np.cos(p[2]), np.sin(p[2])
    v_world = np.array([c * cmd[0] - s * cmd[1], s * cmd[0] + c * cmd[1]])
    assert np.allclose(v_world * dt, np.array(seq[1][0][:2]) - np.array(seq[0][0][:2]), atol=1e-9)
    assert report.interpolate_motion(b, b, dt) == []


def _map_in_reference_frame(truth: MarkerMap, ref_id: int) -> MarkerMap:
    """The truth expressed in the map frame fixed to ``ref_id`` (a perfect map)."""
    T_world_map = map_frame_from_reference(truth.T_map_marker(ref_id))
    T_map_world = geo.inverse(T_world_map)
    m = MarkerMap(frame_id="map", reference_marker=ref_id)
    for e in truth:
        m.add(MarkerEntry(e.marker_id, T_map_world @ e.T_map_marker, e.size))
    return m


def _synthetic_run(scene, est_map, T_map_world, bias, rng, hold=6):
    """Records of a run whose estimates are the truth (map frame) plus ``bias`` and seeded noise."""
    records, traj_est, traj_truth = [], [], []
    t = 100.0
    for stop in report.plan_stops(scene.test_positions, scene.test_orientations):
        rec = report.StopRecord(stop, np.asarray(stop.pose, dtype=float))
        truth_map_frame = report.se2_in_frame(T_map_world, stop.pose)
        for _ in range(hold):
            est = truth_map_frame + bias + rng.normal(scale=[0.0005, 0.0005, 0.0002])
            rec.estimates.append((t, est))
            traj_est.append((t, est))
            traj_truth.append((t, np.asarray(stop.pose, dtype=float)))
            t += 0.2
        rec.camera_estimates = [truth_map_frame + rng.normal(scale=[0.02, 0.02, 0.01]) for _ in range(4)]
        records.append(rec)
    return records, traj_est, traj_truth


def _lab():
    """The simulated lab, its truth, a perfect map fixed to the first marker and ``T_world_map``."""
    scene = Scene.default()
    truth = scene.truth_map()
    ref_id = truth.ids[0]
    return scene, truth, _map_in_reference_frame(truth, ref_id), map_frame_from_reference(truth.T_map_marker(ref_id))


def test_report_on_synthetic_run(tmp_path):
    rng = np.random.default_rng(4)
    scene, truth, est_map, T_world_map = _lab()
    T_map_world = geo.inverse(T_world_map)
    bias = np.array([0.004, -0.003, np.radians(0.1)])  # estimate - truth, map frame
    records, traj_est, traj_truth = _synthetic_run(scene, est_map, T_map_world, bias, rng)
    summary = report.write_report(tmp_path, records, est_map, truth, scene, traj_est, traj_truth, "joint", "refined",
                                "corners", 12.0)
    want = 100 * np.hypot(bias[0], bias[1])
    med = summary["position_error_cm"]["median"]
    # 0.5 mm noise, medians of 5 poses: 0.1 cm is several sigma
    assert abs(med - want) < 0.1, f"median {med} cm, want {want:.3f} cm"
    assert len(summary["position_error_cm"]["per_position"]) == 15
    # per-position x, y are in the lab frame (as the figures): the map-frame bias turned into it
    lab_bias = 100 * T_world_map[:2, :2] @ bias[:2]
    p1 = summary["position_error_cm"]["per_position"]["1"]
    assert summary["frame"] == "lab" and abs(p1["x"] - lab_bias[0]) < 0.1 and abs(p1["y"] - lab_bias[1]) < 0.1, \
        (p1, lab_bias)
    assert abs(summary["yaw_error_deg"]["mean_abs"] - 0.1) < 0.02, summary["yaw_error_deg"]
    assert summary["map_error_mm"]["rms"] < 1e-6 and summary["map_error_mm"]["best_fit_rms"] < 1e-6
    for key in ("fusion", "runtime_s"):
        assert key in summary
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["position_error_cm"]["max"] == pytest.approx(summary["position_error_cm"]["max"])
    for name in ("table1.md", "table2.md", "table1.csv", "table2.csv", "trajectory_estimate.tum",
                 "trajectory_truth.tum", "map.png", "fig8_positions.png", "fig9_camera_estimates.png",
                 "fig10_orientations.png"):
        assert (tmp_path / name).is_file(), f"{name} missing"
    table1 = (tmp_path / "table1.md").read_text()
    assert "lab frame" in table1.splitlines()[0], table1.splitlines()[0]
    sign = "+" if lab_bias[1] > 0 else "-"
    row1 = next(line for line in table1.splitlines() if line.startswith("| 1 |"))
    assert row1.split("|")[3].strip().startswith(sign), f"the y error keeps its sign ({lab_bias[1]:+.3f} cm): {row1}"
    # This run meets every target: the line says so, with what each side was measured against.
    line = report.summary_line(summary)
    assert "ours vs ground truth: position error median" in line and "Paper vs gmapping" in line, line
    assert summary["targets_missed"] == [] and "Meets every target" in line, line
    table = report.summary_table(summary)
    cells = [c.strip() for c in table.splitlines()[0].split(" | ")]
    assert cells == ["figure", "ours (vs ground truth)", "target", "pass/miss", "paper (measured against)"], table
    assert "MISS" not in table and table.count("| pass ") == 5 and "3.10 (vs gmapping)" in table, table
    text = report.console_text(summary, tmp_path)
    assert text.index("Table I") < text.index("SUMMARY") < text.index("pass/miss"), text


def test_summary_says_when_the_run_misses_its_targets(tmp_path):
    rng = np.random.default_rng(5)
    scene, truth, est_map, T_world_map = _lab()
    T_map_world = geo.inverse(T_world_map)
    bias = np.array([0.012, 0.0, np.radians(0.4)])  # 1.2 cm and 0.4 deg: median and yaw mean miss
    records, _, _ = _synthetic_run(scene, est_map, T_map_world, bias, rng)
    summary = report.write_report(tmp_path, records, est_map, truth, scene, [], [], "joint", "refined", "corners", 1.0)
    assert summary["targets_missed"] == ["position_error_cm.median", "yaw_error_deg.mean_abs"], summary["targets_missed"]
    assert "MISSES its targets: position_error_cm.median, yaw_error_deg.mean_abs" in report.summary_line(summary)
    rows = {line.split(" | ")[0].strip(): line for line in report.summary_table(summary).splitlines()}
    assert "MISS" in rows["position error, median (cm)"] and "pass" in rows["position error, max (cm)"], rows
    assert rows["map: marker position RMS, own frame (mm)"].split(" | ")[2].strip() == "-", rows


def test_report_fails_visibly_on_a_rotated_map_frame(tmp_path):
    """A map frame rotated by 1 deg about the reference marker must show up as position errors."""
    scene, truth, est_map, T_world_map = _lab()
    T_map_world = geo.inverse(T_world_map)
    R = geo.transform_from_se2(0, 0, np.radians(1.0))
    records = []
    for stop in report.plan_stops(scene.test_positions, scene.test_orientations)[:15]:
        rec = report.StopRecord(stop, np.asarray(stop.pose, dtype=float))
        rec.estimates.append((0.0, report.se2_in_frame(R @ T_map_world, stop.pose)))
        records.append(rec)
    summary = report.write_report(tmp_path, records, est_map, truth, scene, [], [], "joint", "refined", "corners", 1.0)
    assert summary["position_error_cm"]["median"] > 3.0, summary["position_error_cm"]
    c = summary["after_best_fit_se2"]
    assert c["position_error_cm"]["max"] < 0.01 and abs(c["alignment"]["yaw_deg"] + 1.0) < 1e-6, c
