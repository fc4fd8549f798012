"""Ring calibration from rough values: the initialisation (hand-eye, per-camera motion, the turn
centre) and the observability warnings (ring_calibration.py)."""
from __future__ import annotations

import os

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization import ring_calibration as rc
from aruco_ring_localization.errors import MeasurementError
from aruco_ring_localization.markers import MarkerSizes
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.calibration_run import calibration_poses, rough_ring
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene

RING = os.path.join(os.path.dirname(__file__), "..", "..", "config", "ring.yaml")


def _camera(rng) -> np.ndarray:
    """A camera of the ring: looking outwards at a random heading, 0.75 m up, tilted a little."""
    ring = CameraRing.load(RING)
    c = ring.cameras[int(rng.integers(len(ring)))]
    return geo.se3_perturb(c.T_base_cam, np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.01, 3)])


def _planar_motions(rng, n=30):
    return [geo.transform_from_se2(*rng.uniform([-1, -1, -1.5], [1, 1, 1.5])) for _ in range(n)]


def test_hand_eye_recovers_a_camera_from_10_deg_and_5_cm_off_and_keeps_the_unobservable_height():
    rng = np.random.default_rng(3)
    X = _camera(rng)
    B = _planar_motions(rng)
    A = [geo.inverse(X) @ b @ X for b in B]
    X0 = X @ geo.make_transform(geo.so3_exp(np.radians([10.0, -10.0, 10.0])), [0.05, -0.05, 0.05])
    Xs, cov = rc.solve_hand_eye(B, A, X0)
    assert geo.rotation_angle(Xs[:3, :3].T @ X[:3, :3]) < 1e-6
    assert np.allclose(Xs[:2, 3], X[:2, 3], atol=1e-6), (Xs[:3, 3], X[:3, 3])
    # The robot turns about z only: the camera's height is not in the data, it stays the start's.
    assert Xs[2, 3] == pytest.approx(X0[2, 3], abs=1e-6)
    assert abs(X0[2, 3] - X[2, 3]) > 0.01
    assert cov.shape == (6, 6) and np.sqrt(cov[5, 5]) > 10 * np.sqrt(cov[3, 3])   # z the least known


def test_hand_eye_with_tilting_motion_recovers_the_height_too():
    rng = np.random.default_rng(4)
    X = _camera(rng)
    B = [geo.make_transform(geo.so3_exp(rng.normal(0, 0.4, 3)), rng.normal(0, 0.5, 3)) for _ in range(30)]
    A = [geo.inverse(X) @ b @ X for b in B]
    X0 = geo.se3_perturb(X, [0.1, -0.1, 0.1, 0.04, 0.03, -0.04])
    Xs, _ = rc.solve_hand_eye(B, A, X0, prior_trans=(1.0, 1.0, 1.0))
    assert np.abs(Xs - X).max() < 1e-6


def test_hand_eye_is_robust_to_a_few_wrong_motions():
    rng = np.random.default_rng(5)
    X = _camera(rng)
    B = _planar_motions(rng, 40)
    A = [geo.inverse(X) @ b @ X for b in B]
    for k in (3, 17, 30):       # flipped single-marker poses: wildly wrong camera motions
        A[k] = geo.se3_perturb(A[k], [0.5, -0.3, 0.2, 0.2, 0.1, 0.3])
    Xs, _ = rc.solve_hand_eye(B, A, geo.se3_perturb(X, [0.1, 0.1, -0.1, 0.03, 0.03, 0.0]))
    assert np.degrees(geo.rotation_angle(Xs[:3, :3].T @ X[:3, :3])) < 0.2
    assert np.linalg.norm(Xs[:2, 3] - X[:2, 3]) < 0.005


def _det(frame, marker, T_cam_marker):
    return rc._Det(frame, "cam0", marker, np.zeros((4, 2)), np.ones(2), np.zeros((4, 2, 2)), T_cam_marker)


def test_camera_trajectory_chains_markers_and_splits_segments():
    rng = np.random.default_rng(6)
    markers = {m: geo.make_transform(geo.so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 1.0, 3) + [0, 0, 3])
               for m in range(4)}
    cams = [geo.make_transform(geo.so3_exp([0, 0.05 * k, 0]), [0.02 * k, 0, 0]) for k in range(10)]
    # Frames 0-4 see markers 0, 1 then 1, 2; frame 5 nothing known (marker 3 alone): a new segment.
    seen = {0: [0, 1], 1: [0, 1], 2: [1, 2], 3: [1, 2], 4: [2], 6: [3], 7: [3]}
    dets = [_det(k, m, geo.inverse(cams[k]) @ markers[m]) for k, ms in seen.items() for m in ms]
    traj = rc.camera_trajectory(dets)
    assert sorted(traj) == sorted(seen)
    assert {traj[k][0] for k in (0, 1, 2, 3, 4)} == {0} and {traj[k][0] for k in (6, 7)} == {1}
    mot = rc.relative_motions(traj, lags=(1, 2))
    assert (4, 6) not in mot and (6, 7) in mot
    for (i, j), A in mot.items():
        assert np.abs(A - geo.inverse(cams[i]) @ cams[j]).max() < 1e-9, (i, j)


def test_turn_centre_is_the_point_that_stays_still():
    c = np.array([0.03, -0.02, 0.0])
    Tc = geo.make_transform(t=c)
    poses = [geo.transform_from_se2(1.0, 2.0, 0.0) @ Tc @ geo.make_transform(geo.rot_z(a)) @ geo.inverse(Tc)
             for a in np.radians(np.arange(0, 360, 5))]
    # A drive in the middle (translation only) must not pull it.
    poses += [poses[-1] @ geo.make_transform(t=[0.1 * k, 0, 0]) for k in range(1, 5)]
    p = rc._turn_centre(poses, np.array([0.0, 0.0, 1.0]))
    assert np.allclose(p, c, atol=1e-9), p


def test_motion_extent_sums_turns_and_travel():
    poses = [geo.transform_from_se2(0.1 * k, 0, np.radians(2 * k)) for k in range(46)]
    turn, travel, axis = rc.motion_extent(poses)
    assert turn == pytest.approx(90.0, abs=1e-6) and travel == pytest.approx(4.5, rel=1e-2)
    assert np.allclose(axis, [0, 0, 1])


def test_warnings_name_the_missing_motion():
    o = rc.CalibrationOptions()
    frames = {"cam0": 100, "cam1": 3}
    w = rc.observability_warnings(10.0, 0.1, has_odometry=True, has_floor_map=False, camera_frames=frames, opts=o,
                                  rough_height=0.75)
    text = "\n".join(w)
    assert "no rotation" in text and "turn the robot on the spot" in text
    assert "planar motion only" in text and "height (z)" in text and "0.750 m" in text
    assert "no driving" in text
    assert "cam1: markers in only 3 frames" in text and "cam0:" not in text
    w = rc.observability_warnings(400.0, 5.0, has_odometry=False, has_floor_map=True, camera_frames={"cam0": 50},
                                  opts=o)
    assert len(w) == 1 and w[0].startswith("no odometry: base_link's heading"), w
    assert rc.observability_warnings(400.0, 5.0, True, True, {"cam0": 50}, o) == []


def _lab_frames(poses, seed=0):
    ring = CameraRing.load(RING)
    true = perturb_ring(ring, seed=seed + 1)
    scene = Scene.default()
    sim = RingSimulator(scene, true, pixel_noise=0.3, seed=seed)
    frames = [sim.observe(Scene.T_world_base(p), stamp=0.1 * k) for k, p in enumerate(poses)]
    return true, rough_ring(true, seed=seed + 5), frames, MarkerSizes(scene.markers[0].size)


def test_a_drive_without_turning_warns_no_rotation():
    st = Scene.default().mapping_stations
    poses = [(st[0][0] + 0.05 * k, st[0][1], 0.0) for k in range(25)]
    _, rough, frames, sizes = _lab_frames(poses)
    cal = rc.calibrate_ring(frames, rough, sizes, options=rc.CalibrationOptions(min_camera_frames=3))
    assert any(w.startswith("no rotation") for w in cal.warnings), cal.warnings
    assert cal.turn_deg < 1.0


def test_a_recording_without_markers_is_refused():
    _, rough, frames, sizes = _lab_frames([(0.3, 0.3, 0.0)] * 3)
    for f in frames:
        for cf in f.cameras.values():
            cf.observations = []
    with pytest.raises(MeasurementError, match="frames with markers"):
        rc.calibrate_ring(frames, rough, sizes)


def test_calibrate_ring_turning_on_the_spot_gets_the_cameras_relative_to_each_other():
    st = Scene.default().mapping_stations
    true, rough, frames, sizes = _lab_frames(calibration_poses(st[:1], turn_step_deg=10.0))
    cal = rc.calibrate_ring(frames, rough, sizes)
    G = geo.average_transforms([c.T_base_cam @ geo.inverse(cal.ring[c.name].T_base_cam) for c in true])
    for c in true:
        D = geo.inverse(c.T_base_cam) @ G @ cal.ring[c.name].T_base_cam
        assert np.linalg.norm(D[:3, 3]) < 0.002 and np.degrees(geo.rotation_angle(D[:3, :3])) < 0.1, c.name
    assert not any(w.startswith("no rotation") for w in cal.warnings)
    assert any(w.startswith("no odometry") for w in cal.warnings)
    # The tilt of base_link comes from the turning: its z is the true z.
    assert np.degrees(np.arccos(np.clip(G[2, 2], -1, 1))) < 0.05


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.8])
def test_residual_lag1_correlation_recovers_an_ar1_series(rho):
    """Residuals of 6 (camera, marker) series over 400 stations, AR(1) with coefficient rho (what a
    detector erring alike on near-identical views gives), shuffled: the measured rho."""
    rng = np.random.default_rng(11)
    rows, cams, marks, stations = [], [], [], []
    for g in range(6):
        x = rng.normal(0.0, 1.0, 8)
        for s in range(400):
            x = rho * x + np.sqrt(1.0 - rho ** 2) * rng.normal(0.0, 1.0, 8)
            rows.append(x.copy())
            cams.append(g % 3)
            marks.append(g // 3)
            stations.append(s)
    perm = rng.permutation(len(rows))
    got = rc.residual_lag1_correlation(np.array(rows)[perm], np.array(cams)[perm], np.array(marks)[perm],
                                       np.array(stations)[perm])
    assert got == pytest.approx(rho, abs=0.03)
