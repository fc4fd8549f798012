"""``aruco_ring evaluate EST REF --align none|se2|se3`` end to end on two TUM files."""
from __future__ import annotations

import json

import numpy as np
from helpers import moved, stop_and_go, tilted_path

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.cli import main as cli_main
from aruco_ring_localization.evaluation import trajectories as tj


def _write(tmp_path, stamps, ref_poses, est_stamps, est_poses):
    rp, ep = str(tmp_path / "ref.tum"), str(tmp_path / "est.tum")
    tj.write_tum(rp, tj.trajectory(stamps, ref_poses))
    tj.write_tum(ep, tj.trajectory(est_stamps, est_poses))
    return ep, rp


def test_strict_by_default_and_fitted_alignments_are_diagnostics(tmp_path, capsys):
    rng = np.random.default_rng(11)
    stamps, ref, _, _ = stop_and_go(rng, n_stops=4)
    T = geo.transform_from_se2(0.5, -1.0, 0.4)
    ref_poses = np.stack([geo.transform_from_se2(*p) for p in ref])
    est_poses = moved(ref_poses, T)
    noise = rng.normal(scale=0.002, size=(len(stamps), 2))
    est_poses[:, :2, 3] += noise
    ep, rp = _write(tmp_path, stamps, ref_poses, stamps + 0.01, est_poses)
    assert cli_main(["evaluate", ep, rp]) == 0
    text = capsys.readouterr().out
    assert "alignment: none" in text and "strict" in text and "DIAGNOSTIC" not in text, text
    strict = float(text.split("position error: median ")[1].split(" mm")[0])
    assert strict > 100.0, f"the frames differ by 1.1 m: the strict error must show it ({strict} mm)"
    out = tmp_path / "out"
    code = cli_main(["evaluate", ep, rp, "--align", "se2", "--stops", "--out", str(out), "--plot"])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "DIAGNOSTIC" in text and "4 stops" in text and "p95" in text, text
    for name in ("table1.md", "table1.csv", "table2.md", "errors.csv", "summary.json", "trajectory.png",
                 "positions.png", "orientations.png", "estimate_aligned.tum"):
        assert (out / name).is_file(), f"{name} missing; have {sorted(p.name for p in out.iterdir())}"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["alignment"]["diagnostic"] and abs(summary["alignment"]["yaw_deg"] - np.degrees(0.4)) < 0.1
    # 2 mm noise: the fitted frame leaves ~2-3 mm median; 5 mm is about twice that
    assert summary["ape"]["position_mm_median"] < 5.0 and summary["stops"]["position_cm_max"] < 1.0, summary
    assert "after the fitted se2 alignment" in (out / "table1.md").read_text()
    back = tj.read_tum(str(out / "estimate_aligned.tum"))
    assert back.num_poses == summary["pairs"]


def test_se3_on_a_tilted_6dof_trajectory(tmp_path, capsys):
    s = np.arange(0, 20, 0.1)
    poses = tilted_path(s)
    T = geo.make_transform(geo.matrix_from_rpy(0.08, -0.05, 1.0), (1.0, 2.0, 0.3))
    ep, rp = _write(tmp_path, s, poses, s, moved(poses, T))
    results = {}
    for method in ("se2", "se3"):
        out = tmp_path / method
        assert cli_main(["evaluate", "--estimate", ep, "--reference", rp, "--align", method, "--out", str(out)]) == 0
        results[method] = json.loads((out / "summary.json").read_text())["ape"]
    capsys.readouterr()
    assert results["se3"]["position_mm_max"] < 1e-3 and results["se3"]["rotation_deg_max"] < 1e-3, results["se3"]
    assert results["se2"]["rotation_deg_median"] > 2.0, "SE(2) cannot remove the tilt"


def test_errors_are_reported(tmp_path, capsys):
    a = tj.trajectory([0.0, 1.0], np.zeros((2, 3)))
    b = tj.trajectory([100.0, 101.0], np.zeros((2, 3)))
    tj.write_tum(str(tmp_path / "a.tum"), a)
    tj.write_tum(str(tmp_path / "b.tum"), b)
    assert cli_main(["evaluate", str(tmp_path / "b.tum"), str(tmp_path / "a.tum")]) == 1
    assert "no estimate pose within" in capsys.readouterr().err
    assert cli_main(["evaluate", str(tmp_path / "b.tum")]) == 1
    assert "EST.tum REF.tum" in capsys.readouterr().err
    assert cli_main(["evaluate", str(tmp_path / "a.tum"), str(tmp_path / "a.tum"), "--plot"]) == 1
    assert "--out" in capsys.readouterr().err
    (tmp_path / "bad.tum").write_text("0 0 0\n")
    assert cli_main(["evaluate", str(tmp_path / "bad.tum"), str(tmp_path / "a.tum")]) == 1
    err = capsys.readouterr().err
    assert "bad.tum" in err and "line 1" in err, err
