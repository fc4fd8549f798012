"""kalman.py: the 9-state filter follows constant velocity, smooths a static pose, wraps yaw."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.kalman import FilterParams, PoseFilter, process_noise, transition_matrix


def test_transition_and_noise_shapes():
    F = transition_matrix(0.1)
    x = np.zeros(9)
    x[2], x[4] = 1.0, 2.0  # x' = 1, x'' = 2
    x2 = F @ x
    assert x2[0] == pytest.approx(0.1 + 0.5 * 2 * 0.01) and x2[2] == pytest.approx(1.2)
    Q = process_noise(0.1, 1.0, 1.0)
    assert np.allclose(Q, Q.T) and np.all(np.linalg.eigvalsh(Q) > -1e-15)


@pytest.mark.parametrize("dt", [0.001, 0.05, 0.1, 0.7, 5.0])
def test_process_noise_is_the_white_jerk_block_per_axis(dt):
    # filterpy's Q_continuous_white_noise replaced this hand-written block: equal to 1e-12, each
    # block on its own axis (x, y, phi), the axes uncoupled.
    q_xy, q_yaw = 0.3, 0.02
    block = np.array([[dt ** 5 / 20, dt ** 4 / 8, dt ** 3 / 6],
                      [dt ** 4 / 8, dt ** 3 / 3, dt ** 2 / 2],
                      [dt ** 3 / 6, dt ** 2 / 2, dt]])
    expected = np.zeros((9, 9))
    for idx, q in (([0, 2, 4], q_xy), ([1, 3, 5], q_xy), ([6, 7, 8], q_yaw)):  # (x x' x''), (y ...), (phi ...)
        expected[np.ix_(idx, idx)] = q * block
    assert np.abs(process_noise(dt, q_xy, q_yaw) - expected).max() <= 1e-12


def test_follows_constant_velocity():
    rng = np.random.default_rng(1)
    f = PoseFilter()
    v = np.array([0.3, -0.2, 0.1])
    errs = []
    for k in range(200):
        t = 0.1 * k
        truth = np.array([1.0, 2.0, 0.0]) + v * t
        z = truth + rng.normal(0, [0.01, 0.01, 0.005])
        f.update(z, t, np.diag([1e-4, 1e-4, 2.5e-5]))
        if k > 50:
            e = f.pose - truth
            e[2] = geo.wrap_angle(e[2])
            errs.append(e)
    errs = np.array(errs)
    rms = np.sqrt(np.mean(errs ** 2, axis=0))
    assert rms[0] < 0.01 and rms[1] < 0.01 and rms[2] < 0.005, f"tracking RMS {rms}"
    assert np.allclose(f.velocity, v, atol=0.05), f"velocity {f.velocity} vs {v}"


def test_reduces_noise_when_static():
    rng = np.random.default_rng(2)
    f = PoseFilter(FilterParams(jerk_noise_xy=0.001, jerk_noise_yaw=0.001))
    truth = np.array([3.0, -1.0, 2.0])
    out, meas = [], []
    for k in range(300):
        z = truth + rng.normal(0, [0.02, 0.02, 0.01])
        f.update(z, 0.1 * k, np.diag([4e-4, 4e-4, 1e-4]))
        if k > 100:
            out.append(f.pose - truth)
            meas.append(z - truth)
    ratio = np.std(np.array(out)[:, 0]) / np.std(np.array(meas)[:, 0])
    # A constant-acceleration model smooths a static pose only so much (~0.55 at this q).
    assert ratio < 0.65, f"filtered/measured std ratio {ratio:.3f}"
    reported = np.sqrt(f.covariance[0, 0])
    empirical = np.std(np.array(out)[:, 0])
    assert 0.7 < reported / empirical < 1.4, f"filter std {reported:.4f} vs empirical {empirical:.4f}"


def test_yaw_across_pi_never_jumps():
    rng = np.random.default_rng(3)
    f = PoseFilter()
    w = 0.5
    for k in range(100):
        t = 0.1 * k
        truth_yaw = geo.wrap_angle(np.pi - 1.0 + w * t)   # crosses +pi -> -pi at t = 2 s
        z = np.array([0.0, 0.0, geo.wrap_angle(truth_yaw + rng.normal(0, 0.005))])
        f.update(z, t, np.diag([1e-4, 1e-4, 2.5e-5]))
        err = abs(geo.angle_diff(f.pose[2], truth_yaw))
        assert err < 0.05, f"t={t:.1f}: yaw error {err:.3f} rad (estimate {f.pose[2]:.3f}, truth {truth_yaw:.3f})"
        assert -np.pi <= f.pose[2] < np.pi
    assert f.velocity[2] == pytest.approx(w, abs=0.05)


def test_predict_only_grows_covariance_and_mahalanobis():
    f = PoseFilter()
    f.update([1.0, 1.0, 0.0], 0.0)
    c0 = np.trace(f.covariance)
    f.predict(1.0)
    assert np.trace(f.covariance) > c0
    assert f.mahalanobis([1.0, 1.0, 0.0]) < f.mahalanobis([3.0, 1.0, 0.0])


def test_time_jump_back_resets():
    f = PoseFilter()
    for k in range(20):
        f.update([0.1 * k, 0.0, 0.0], 100.0 + 0.1 * k)
    assert f.initialized
    f.update([5.0, 5.0, 1.0], 10.0)  # the bag looped: restart at the new measurement
    assert np.allclose(f.pose, [5.0, 5.0, 1.0]), f"after the time jump the filter is at {f.pose}"
    assert np.allclose(f.velocity, 0.0) and f.stamp == 10.0


def test_kept_interval_model_is_the_one_of_each_interval_and_of_the_params():
    # PoseFilter keeps the last interval's (F, Q) (a ring frame asks for it up to three times): a
    # new interval or new jerk noises must not get the kept one.
    f = PoseFilter(FilterParams(jerk_noise_xy=0.1, jerk_noise_yaw=0.1))
    f.reset(np.array([1.0, 2.0, 0.3]), 0.0, np.diag([1e-4, 1e-4, 1e-5]))
    f.kf.x[2, 0], f.kf.x[7, 0] = 0.5, 0.2   # moving: F matters

    def expected(dt):
        F, Q = transition_matrix(dt), process_noise(dt, f.params.jerk_noise_xy, f.params.jerk_noise_yaw)
        P = F @ f.kf.P @ F.T + Q
        return (F @ f.kf.x.ravel())[[0, 1, 6]], P[np.ix_([0, 1, 6], [0, 1, 6])]

    for dt in (0.1, 0.1, 0.25, 0.1):
        x, P = expected(dt)
        assert np.array_equal(f.predicted(dt)[:2], x[:2]) and np.array_equal(f.predicted_covariance(dt), P)
    f.params = FilterParams(jerk_noise_xy=3.0, jerk_noise_yaw=0.5)
    x, P = expected(0.1)
    assert np.array_equal(f.predicted_covariance(0.1), P)
    F, Q = f._model(0.1)
    with pytest.raises(ValueError):   # read-only: a caller cannot change the kept matrices
        F[0, 0] = 2.0
