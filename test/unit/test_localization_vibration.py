"""The cameras' per-frame jitter measured from the data (localization.VibrationEstimate,
``estimator/estimate_vibration``): the statistic unbiased, with the spread it states, on synthetic
blocks, and on seeded simulated rigs: a ring that shakes by less than declared is measured within
the estimate's uncertainty and solved with it, one that does not shake gives about zero, one that
shakes as declared keeps the declared term (an upper bound), a ring declared rigid is not
estimated."""
from __future__ import annotations

from typing import List, Tuple

import numpy as np
import pytest

from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.localization import LocalizationParams, RingLocalizer, VibrationEstimate
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.conditions import RingVibration
from aruco_ring_localization.simulation.params import RingParams
from aruco_ring_localization.simulation.ring_sim import RingSimulator
from aruco_ring_localization.simulation.scene import Scene

from helpers import RING_YAML, se2_error

SIGMA = 0.3
DECLARED_DEG = 0.05   # the estimator's default extrinsic_jitter_deg (and 0.1 mm)


def _spd(rng, n=6, k=14) -> np.ndarray:
    M = rng.normal(size=(n, k))
    return M @ M.T


def test_the_statistic_is_unbiased_and_states_its_spread():
    """Blocks drawn as the model says: camera c's gradient b_c = u_c + G_c eta_c - G_c H^-1 sum_d
    (u_d + G_d eta_d), u_c ~ N(0, s^2 G_c), eta_c ~ N(0, kappa^2 V_c), plus a constant calibration
    error (the same for both frames of a pair: a parked robot sees the same markers the same way).
    Over many windows the estimate's mean is kappa^2 and its spread what it states."""
    rng = np.random.default_rng(21)
    C, s2, window = 3, 0.09, 30
    V = np.stack([0.01 * _spd(rng) for _ in range(C)])
    eta0 = rng.normal(0.0, 0.3, size=(C, 6))   # the calibration's error: persists, must cancel
    for kappa2 in (0.0, 0.4):
        est, ses = [], []
        for rep in range(100):
            ve = VibrationEstimate(window)
            for f in range(window):
                if f % 2 == 0:   # a new view every second frame
                    G = np.stack([_spd(rng) for _ in range(C)])
                H = G.sum(axis=0)
                u = np.stack([np.linalg.cholesky(s2 * G[c]) @ rng.normal(size=6) for c in range(C)])
                eta = eta0 + np.stack([np.linalg.cholesky(kappa2 * V[c] + 1e-18 * np.eye(6)) @ rng.normal(size=6)
                                       for c in range(C)])
                drive = u + np.einsum("cab,cb->ca", G, eta)
                b = drive - np.einsum("cab,bd,d->ca", G, np.linalg.inv(H), drive.sum(axis=0))
                ids = [[10 * c + f // 2] for c in range(C)]
                ve.add(["a", "b", "c"], ids, G, b, s2, V)
            k2, se, pairs = ve.estimate()
            assert pairs == C * window // 2
            est.append(k2)
            ses.append(se)
        est = np.array(est)
        # Unbiased: the mean of 100 windows within 3 standard errors of the mean of kappa^2.
        assert abs(est.mean() - kappa2) < 3.0 * est.std() / np.sqrt(len(est)), (kappa2, est.mean(), est.std())
        # The stated standard error is the spread of the estimate (within 25 %).
        assert np.median(ses) == pytest.approx(est.std(), rel=0.25), (kappa2, np.median(ses), est.std())


def test_pairs_need_the_same_markers_in_consecutive_frames():
    rng = np.random.default_rng(2)
    ve = VibrationEstimate(10)
    G = np.stack([_spd(rng) for _ in range(2)])
    V = np.stack([np.eye(6)] * 2)
    b = rng.normal(size=(2, 6))
    ve.add(["a", "b"], [[1], [2]], G, b, 0.1, V)
    ve.add(["a", "b"], [[1], [3]], G, b, 0.1, V)   # a: same markers (a pair), b: other markers
    assert ve.estimate()[2] == 1
    ve.add(["a", "b"], [[1], [3]], G, b, 0.1, V)   # a's last frame is paired already; b pairs
    assert ve.estimate()[2] == 2
    ve.add(["a"], [[1]], G[:1], b[:1], 0.1, V[:1])   # one camera: nothing to tell
    ve.add(["a", "b"], [[1], [3]], G, b, 0.1, V)   # not consecutive with a recorded frame of a
    assert ve.estimate()[2] == 2
    for _ in range(10):   # the window slides past every pair
        ve.add(["a", "b"], [[5], [6]], G, b, 0.1, V)
        ve.add(["a", "b"], [[7], [8]], G, b, 0.1, V)
    assert ve.estimate()[2] == 0


@pytest.fixture(scope="module")
def lab():
    scene = Scene.default()
    return scene, CameraRing.load(str(RING_YAML)), scene.truth_map()


def _shaking(lab, true_deg: float, frames: int = 60, **kw) -> Tuple[RingLocalizer, List[Tuple[float, float, int]],
                                                                   List[float], List[np.ndarray]]:
    """The true rig as declared exact, shaking by ``true_deg`` (and 2 mm per degree) per axis and
    frame, the robot parked two frames at each of the lab's test positions (``estimate_vibration``
    on unless ``kw`` says otherwise; it is off by default); the localizer's
    estimate after every frame, the pose's NEES / 3 (x, y, yaw) and the poses."""
    scene, ring, truth = lab
    exact = ring.with_extrinsics_std(0.0, 0.0)
    vib = RingVibration(RingParams(vibration_rot_std_deg=true_deg, vibration_trans_std=0.002 * true_deg), seed=9)
    sim = RingSimulator(scene, exact, pixel_noise=SIGMA, seed=5)
    poses = [scene.T_world_base(p) for p in scene.test_positions]
    loc = RingLocalizer(exact, truth, LocalizationParams(pixel_noise=SIGMA, **{"estimate_vibration": True, **kw}))
    hist, nees, out = [], [], []
    for k in range(frames):
        T = poses[(k // 2) % len(poses)]
        shake = vib.draw(ring.names)
        frame = sim.observe(T, 0.1 * k)
        for c in ring.names:   # each camera sees through its shaken mounting this frame
            frame.cameras[c].observations = sim.observe_camera(
                RingVibration.shaken_base(T, exact[c].T_base_cam, shake[c]), c)
        res = loc.process(frame, prediction=T)
        assert res.ok
        hist.append(loc.last_vibration)
        out.append(res.T_map_base)
        e = se2_error(res.T_map_base, T)
        nees.append(float(e @ np.linalg.solve(res.covariance_se2, e)) / 3.0)
    return loc, hist, nees, out


def test_a_ring_shaking_less_than_declared_is_measured_and_solved_with_it(lab):
    true = 0.03
    loc, hist, nees, _ = _shaking(lab, true)
    k2, se, pairs = hist[-1]
    assert pairs >= loc.params.vibration_min_pairs
    kappa2 = (true / DECLARED_DEG) ** 2
    assert abs(k2 - kappa2) <= 2.0 * se, (k2, se, kappa2)
    assert se < 0.5 * kappa2   # the estimate tells 0.03 from 0.05 deg
    # Solved with the estimate's upper one-sigma bound: the declared term scaled down.
    assert loc.vibration_scale == pytest.approx(np.clip(k2 + se, 0.0, 1.0), abs=0.05)
    assert loc.vibration_scale < 0.7
    name = loc.ring.names[0]
    assert np.allclose(loc._vib_cov[name], loc.vibration_scale * loc._vib_declared[name])
    # The covariance stays honest with the smaller term (frames after the estimate took over).
    start = next(k for k, (_, _, p) in enumerate(hist) if p >= loc.params.vibration_min_pairs) + 1
    assert 0.5 < float(np.mean(nees[start:])) < 1.6, np.mean(nees[start:])


def test_a_ring_that_does_not_shake_gives_about_zero(lab):
    loc, hist, _, _ = _shaking(lab, 0.0)
    k2, se, pairs = hist[-1]
    assert pairs >= loc.params.vibration_min_pairs
    assert abs(k2) <= 2.0 * se, (k2, se)
    assert se < 0.1   # jitter below ~0.016 deg at one sigma
    assert loc.vibration_scale < 0.1


def test_a_ring_shaking_as_declared_keeps_the_declared_term(lab):
    loc, hist, _, _ = _shaking(lab, DECLARED_DEG)
    k2, se, pairs = hist[-1]
    assert abs(k2 - 1.0) <= 2.0 * se, (k2, se)
    assert loc.vibration_scale == 1.0   # the declared jitter is an upper bound


def test_a_ring_declared_rigid_is_not_estimated(lab):
    rigid = {"extrinsic_jitter_deg": 0.0, "extrinsic_jitter_m": 0.0}
    loc, hist, _, poses = _shaking(lab, 0.03, frames=30, **rigid)
    _, _, _, ref = _shaking(lab, 0.03, frames=30, estimate_vibration=False, **rigid)
    assert all(p == 0 for _, _, p in hist)
    assert loc.vibration_scale == 1.0
    assert all(np.allclose(a, b, atol=1e-12) for a, b in zip(poses, ref))
    # estimate_vibration false: the declared term always.
    off, hist_off, _, _ = _shaking(lab, 0.03, frames=30, estimate_vibration=False)
    assert all(p == 0 for _, _, p in hist_off) and off.vibration_scale == 1.0


def test_vibration_parameters_are_checked():
    with pytest.raises(ConfigError) as exc:
        LocalizationParams(vibration_min_pairs=-1)
    assert "vibration_min_pairs" in str(exc.value)
