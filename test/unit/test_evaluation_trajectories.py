"""evaluation.trajectories (on evo): TUM files, association, alignment none/se2/se3, APE, planar pairs."""
from __future__ import annotations

import numpy as np
import pytest
from helpers import moved, random_transform, tilted_path

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.errors import ConfigError, GeometryError
from aruco_ring_localization.evaluation import trajectories as tj


def test_tum_round_trip_keeps_6dof_poses(tmp_path):
    rng = np.random.default_rng(1)
    poses = np.stack([random_transform(rng) for _ in range(25)])
    stamps = 1.7e9 + 0.1 * np.arange(25)
    path = str(tmp_path / "a.tum")
    tj.write_tum(path, tj.trajectory(stamps, poses), header="test\nsecond line")
    text = open(path).read()
    assert text.startswith("# test\n# second line\n"), text[:40]
    back = tj.read_tum(path)
    assert np.allclose(back.timestamps, stamps, rtol=0, atol=1e-6)
    err = np.max(np.abs(np.stack(back.poses_se3) - poses))
    assert err < 1e-9, f"TUM round trip changed the poses by {err}"


def test_planar_poses_become_trajectories():
    se2 = np.array([[1.0, 2.0, 0.5], [-1.0, 0.5, -3.0]])
    traj = tj.trajectory([0.0, 1.0], se2)
    assert np.allclose(tj.planar(traj), se2, atol=1e-12)
    with pytest.raises(GeometryError):
        tj.trajectory([0.0], se2)
    with pytest.raises(GeometryError):
        tj.trajectory([], np.zeros((0, 3)))


def test_read_tum_names_file_and_line(tmp_path):
    path = tmp_path / "bad.tum"
    cases = {"# header\n0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n": "line 3: expected 8 numbers",
             "0 0 0 0 0 0 0 1\n\n1 0 0 0 0 0 0 0\n": "line 3: quaternion norm 0.0000",
             "0 0 0 0 0 0 0 1\n1 0 x 0 0 0 0 1\n": "line 2: not a number",
             "0 0 0 nan 0 0 0 1\n": "line 1: non-finite value",
             "# only a comment\n": "no poses"}
    for text, want in cases.items():
        path.write_text(text)
        with pytest.raises(ConfigError) as exc:
            tj.read_tum(str(path))
        assert "bad.tum" in str(exc.value) and want in str(exc.value), (text, str(exc.value))
    with pytest.raises(ConfigError, match="cannot read"):
        tj.read_tum(str(tmp_path / "missing.tum"))


def test_read_tum_accepts_loose_spacing_and_sorts(tmp_path):
    path = tmp_path / "loose.tum"
    path.write_text("# t x y z qx qy qz qw\n\n2.0  1 0 0  0 0 0 1  \n1.0,0,0,0,0,0,0,1\n2.0 9 9 9 0 0 0 1\n")
    traj = tj.read_tum(str(path))
    assert list(traj.timestamps) == [1.0, 2.0], traj.timestamps
    assert np.allclose(traj.positions_xyz, [[0, 0, 0], [1, 0, 0]]), "the repeated stamp keeps its first pose"


def test_association_with_a_clock_offset():
    s = np.arange(0, 20, 0.1)
    ref = tj.trajectory(s, tilted_path(s))
    est_t = s[::2]
    est = tj.trajectory(np.r_[est_t + 0.3, 500.0], np.concatenate([tilted_path(est_t), tilted_path([0.0])]))
    r, e = tj.associate(ref, est, max_dt=0.02)
    # 500 s has no partner, nor 19.8 + 0.3 s (past the reference's end at 19.9 s)
    assert r.num_poses == len(est_t) - 1, r.num_poses
    lagged = np.median(tj.ape(r, e).position_m)
    r, e = tj.associate(ref, est, max_dt=0.02, offset=-0.3)
    assert r.num_poses == len(est_t)
    fixed = np.max(tj.ape(r, e).position_m)
    assert fixed < 1e-9 and lagged > 0.05, f"offset-corrected max {fixed} m, lagged median {lagged} m"
    with pytest.raises(ConfigError, match="no estimate pose within"):
        tj.associate(ref, tj.trajectory([100.0], tilted_path([0.0])), max_dt=0.05)


def test_se3_alignment_recovers_a_known_transform_and_none_sees_it():
    rng = np.random.default_rng(3)
    s = np.arange(0, 20, 0.1)
    poses = tilted_path(s)
    T_true = random_transform(rng, scale=3.0)
    ref, est = tj.trajectory(s, poses), tj.trajectory(s, moved(poses, T_true))
    fit = tj.fit_alignment(ref, est, "se3")
    assert fit.fitted and fit.n == len(s)
    assert np.max(np.abs(fit.T_ref_est - T_true)) < 1e-9, fit.T_ref_est
    assert np.max(tj.ape(ref, fit.apply(est)).position_m) < 1e-9
    assert np.max(tj.ape(ref, fit.apply(est)).rotation_deg) < 1e-6
    strict = tj.fit_alignment(ref, est, "none")
    assert not strict.fitted and "strict" in strict.describe()
    assert np.min(tj.ape(ref, strict.apply(est)).position_m) > 0.1, "no alignment: the frame offset must show"
    assert "DIAGNOSTIC" in fit.describe()


def test_a_wrong_alignment_is_seen():
    s = np.arange(0, 20, 0.1)
    poses = tilted_path(s)
    T_true = geo.transform_from_se2(0.5, -0.2, 0.3)
    ref, est = tj.trajectory(s, poses), tj.trajectory(s, moved(poses, T_true))
    wrong = tj.Alignment("se2", geo.transform_from_se2(0.5, -0.2, 0.3 + np.radians(1.0)), len(s))
    errors = tj.ape(ref, wrong.apply(est))
    assert abs(np.median(errors.rotation_deg) - 1.0) < 1e-6, "a 1 deg wrong heading is a 1 deg rotation error"
    assert np.min(errors.position_m) > 0.01, np.min(errors.position_m)


def test_se2_versus_se3_on_a_tilted_trajectory():
    s = np.arange(0, 20, 0.1)
    poses = tilted_path(s)
    planar_T = geo.transform_from_se2(1.0, 2.0, 0.7)
    ref = tj.trajectory(s, poses)
    # A frame offset that is a planar motion: both fits remove it exactly.
    est = tj.trajectory(s, moved(poses, planar_T))
    for method in ("se2", "se3"):
        fit = tj.fit_alignment(ref, est, method)
        assert np.max(np.abs(fit.T_ref_est - planar_T)) < 1e-9, (method, fit.T_ref_est)
    # A tilted frame (5 deg roll, -3 deg pitch): SE(3) removes it, SE(2) cannot.
    tilted_T = planar_T @ geo.make_transform(geo.matrix_from_rpy(np.radians(5.0), np.radians(-3.0), 0.0))
    est = tj.trajectory(s, moved(poses, tilted_T))
    se3 = tj.ape(ref, tj.fit_alignment(ref, est, "se3").apply(est))
    se2 = tj.ape(ref, tj.fit_alignment(ref, est, "se2").apply(est))
    assert np.max(se3.position_m) < 1e-9 and np.max(se3.rotation_deg) < 1e-6
    assert np.median(se2.rotation_deg) > 3.0, f"SE(2) cannot remove a 5 deg tilt: {np.median(se2.rotation_deg)} deg"
    assert np.median(se2.position_m) > 0.02, np.median(se2.position_m)


def test_se2_on_a_straight_drive_and_se3_refuses_it():
    s = np.arange(0, 10, 0.1)
    se2 = np.column_stack([0.3 * s, np.zeros_like(s), np.zeros_like(s)])
    T = np.array([1.5, -0.7, 0.9])
    ref = tj.trajectory(s, tj.apply_se2(T, se2))
    est = tj.trajectory(s, se2)
    fit = tj.fit_alignment(ref, est, "se2")
    assert np.allclose(geo.se2_from_transform(fit.T_ref_est), T, atol=1e-9), fit.T_ref_est
    with pytest.raises(GeometryError, match="se2"):
        tj.fit_alignment(ref, est, "se3")


def test_align_se2_with_noise_and_from_the_first_pairs():
    rng = np.random.default_rng(7)
    ref = np.column_stack([rng.uniform(-3, 3, 50), rng.uniform(-3, 3, 50), rng.uniform(-np.pi, np.pi, 50)])
    T_true = np.array([1.5, -0.7, 0.9])
    noise = rng.normal(scale=[0.002, 0.002, 0.001], size=(50, 3))
    est = tj.apply_se2(geo.se2_from_transform(geo.inverse(geo.transform_from_se2(*T_true))), ref) + noise
    T = tj.align_se2(est, ref)
    d = np.abs(T - T_true)
    # 2 mm noise over 50 points: the fit is good to ~0.3 mm / 0.1 mrad; 3 mm / 2 mrad is 10 sigma.
    assert d[0] < 0.003 and d[1] < 0.003 and d[2] < 0.002, f"alignment error {d}"
    ref_t, est_t = tj.trajectory(np.arange(50.0), ref), tj.trajectory(np.arange(50.0), est)
    first = tj.fit_alignment(ref_t, est_t, "se2", n=10)
    assert first.n == 10 and np.abs(geo.se2_from_transform(first.T_ref_est) - T_true).max() < 0.01


def test_align_se2_spin_on_the_spot_uses_yaw_and_rejects_bad_input():
    yaw = np.radians(np.arange(0, 360, 45))
    ref = np.column_stack([np.full(8, 2.0), np.full(8, 1.0), np.angle(np.exp(1j * yaw))])
    T_true = np.array([0.1, 0.2, 0.3])
    est = tj.apply_se2(geo.se2_from_transform(geo.inverse(geo.transform_from_se2(*T_true))), ref)
    assert np.allclose(tj.align_se2(est, ref), T_true, atol=1e-9)
    with pytest.raises(GeometryError):
        tj.align_se2(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(GeometryError):
        tj.align_se2(np.full((3, 2), np.nan), np.zeros((3, 2)))
    with pytest.raises(GeometryError, match="no yaw"):
        tj.align_se2(np.zeros((3, 2)), np.zeros((3, 2)))
    with pytest.raises(ConfigError, match="unknown alignment"):
        tj.fit_alignment(tj.trajectory([0.0], ref[:1]), tj.trajectory([0.0], ref[:1]), "sim3")


def test_ape_statistics_of_a_known_error():
    s = np.arange(0, 10, 0.1)
    poses = tilted_path(s)
    offset = geo.make_transform(geo.rot_z(np.radians(1.0)), (0.01, 0.0, 0.0))
    est = np.stack([P @ offset for P in poses])  # 10 mm ahead along the body's x, turned by 1 deg
    errors = tj.ape(tj.trajectory(s, poses), tj.trajectory(s, est))
    st = errors.statistics()
    for key in ("median", "p95", "max", "rms", "mean"):
        assert abs(st[f"position_mm_{key}"] - 10.0) < 1e-9, (key, st)
        assert abs(st[f"rotation_deg_{key}"] - 1.0) < 1e-6, (key, st)
    assert np.allclose(np.linalg.norm(errors.xyz_m, axis=1), 0.01)
    assert "p95" in tj.format_statistics(st) and st["n"] == len(s)


def test_planar_pairs_and_signed_errors():
    ref = tj.trajectory([0.0, 1.0], np.array([[0.0, 0.0, 3.1], [1.0, 1.0, 0.0]]))
    est = tj.trajectory([0.0, 1.0], np.array([[0.01, -0.02, -3.1], [1.0, 1.0, 0.1]]))
    pairs = tj.MatchedPairs.of(ref, est)
    e = tj.pose_errors(pairs.ref, pairs.est)
    assert np.allclose(e[0], [0.01, -0.02, np.hypot(0.01, 0.02), 2 * np.pi - 6.2], atol=1e-12), e[0]
    st = tj.error_statistics(e)
    assert st["n"] == 2 and abs(st["position_cm_max"] - 100 * np.hypot(0.01, 0.02)) < 1e-9
    assert tj.error_statistics(np.zeros((0, 4))) == {"n": 0}
