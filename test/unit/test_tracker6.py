"""The 6-DOF tracker (filter/model: 6dof): smooth 6-DOF motion followed, flips kept out, no lock-out."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.config import with_overrides
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.gating import ACCEPTED, INITIALIZED, REINITIALIZED, REJECTED_AMBIGUOUS
from aruco_ring_localization.kalman import FilterParams
from aruco_ring_localization.schemas import LocalizerConfig
from aruco_ring_localization.tracker6 import PENDING, Tracker6, Tracker6Params, move_pose

RATE = 30.0
POS_STD = 0.002
ROT_STD = np.radians(0.1)
COV = np.diag([POS_STD ** 2] * 3 + [ROT_STD ** 2] * 3)


def handheld(t: float) -> np.ndarray:
    """A rig carried by hand: a loop with bobbing, and roll, pitch and yaw all swinging by tens of degrees."""
    p = [0.8 * np.cos(0.5 * t), 0.8 * np.sin(0.5 * t), 1.2 + 0.1 * np.sin(1.3 * t)]
    R = geo.matrix_from_rpy(0.5 * np.sin(0.9 * t), 0.4 * np.sin(0.7 * t + 1.0), 0.5 * t + 0.6 * np.sin(0.4 * t))
    return geo.make_transform(R, p)


def noisy(T: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``T`` with the measurement noise of COV (map-frame rotation vector, position)."""
    return geo.make_transform(geo.so3_exp(rng.normal(0.0, ROT_STD, 3)) @ T[:3, :3],
                              T[:3, 3] + rng.normal(0.0, POS_STD, 3))


def flipped(T: np.ndarray, angle_deg: float = 30.0) -> np.ndarray:
    """What a single marker's mirrored IPPE pose looks like: turned about a horizontal axis, moved."""
    R = geo.so3_exp(np.radians(angle_deg) * np.array([0.6, 0.8, 0.0])) @ T[:3, :3]
    return geo.make_transform(R, T[:3, 3] + np.array([0.05, -0.08, 0.03]))


def errors(tracker: Tracker6, T_true: np.ndarray):
    dp, dr = geo.pose_distance(T_true, tracker.pose)
    return 1000.0 * dp, float(np.degrees(dr))


def run_track(tracker: Tracker6, t_end: float, rng, markers: int = 3, t0: float = 0.0):
    pos, rot, reasons = [], [], []
    for k in range(int(round((t_end - t0) * RATE))):
        t = t0 + k / RATE
        T = handheld(t)
        d = tracker.update(noisy(T, rng), t, COV, markers=markers)
        reasons.append(d.reason)
        e = errors(tracker, T)
        pos.append(e[0])
        rot.append(e[1])
    return np.array(pos), np.array(rot), reasons


def test_smooth_6dof_motion_is_tracked_better_than_per_frame():
    rng = np.random.default_rng(7)
    tracker = Tracker6()
    pos, rot, reasons = run_track(tracker, 20.0, rng)
    assert reasons[0] == INITIALIZED and set(reasons[1:]) == {ACCEPTED}
    settled = slice(int(RATE), None)
    # Per-frame noise: 2 mm per axis (~3.3 mm median of the norm), 0.1 deg per axis.
    assert np.median(pos[settled]) < 3.0
    assert pos[settled].max() < 10.0
    assert np.median(rot[settled]) < 0.15
    assert rot[settled].max() < 0.6


def test_predicts_between_frames_along_the_motion():
    rng = np.random.default_rng(3)
    tracker = Tracker6()
    run_track(tracker, 5.0, rng)
    t = 5.0 - 1.0 / RATE + 0.5 / RATE
    dp, dr = geo.pose_distance(handheld(t), tracker.predicted(t))
    assert dp < 0.01 and np.degrees(dr) < 0.5


@pytest.mark.parametrize("angle_deg", [10.0, 25.0, 60.0, 179.0])
def test_a_flip_fed_in_is_rejected_and_the_output_stays(angle_deg):
    rng = np.random.default_rng(11)
    tracker = Tracker6()
    run_track(tracker, 4.0, rng, markers=1)
    t = 4.0
    d = tracker.update(flipped(handheld(t), angle_deg), t, COV, markers=1)
    assert not d.accepted
    pos, rot = errors(tracker, handheld(t))
    assert pos < 10.0 and rot < 1.0
    # ... and the track goes on with the next good measurement.
    t += 1.0 / RATE
    assert tracker.update(noisy(handheld(t), rng), t, COV, markers=1).reason == ACCEPTED


def test_flips_on_alternate_frames_never_enter():
    """A marker flipping every other frame (a far, face-on marker): no flip enters, the track holds."""
    rng = np.random.default_rng(5)
    tracker = Tracker6()
    run_track(tracker, 2.0, rng, markers=1)
    worst = 0.0
    for k in range(int(3 * RATE)):
        t = 2.0 + k / RATE
        T = handheld(t)
        z = flipped(T, 20.0) if k % 2 else noisy(T, rng)
        d = tracker.update(z, t, COV, markers=1)
        if k % 2:
            assert not d.accepted, k
        worst = max(worst, errors(tracker, T)[1])
    assert worst < 1.0


def test_an_ambiguous_measurement_never_enters_nor_restarts():
    rng = np.random.default_rng(2)
    tracker = Tracker6()
    for k in range(10):
        d = tracker.update(noisy(handheld(k / RATE), rng), k / RATE, COV, ambiguous=True, markers=3)
        assert d.reason == REJECTED_AMBIGUOUS
    assert not tracker.initialized


def test_consistent_measurements_elsewhere_reinitialise_no_lockout():
    """A kidnapped rig (or a wrong start): recovery_count consistent measurements re-initialise."""
    rng = np.random.default_rng(4)
    params = Tracker6Params()
    tracker = Tracker6(params)
    run_track(tracker, 2.0, rng)
    jump = geo.make_transform(geo.so3_exp([0.0, 0.0, 1.5]), [2.0, -1.0, 0.0])
    reasons = []
    for k in range(params.recovery_count):
        t = 2.0 + k / RATE
        reasons.append(tracker.update(jump @ noisy(handheld(t), rng), t, COV, markers=3).reason)
    assert reasons[-1] == REINITIALIZED and not any(r == ACCEPTED for r in reasons[:-1])
    assert errors(tracker, jump @ handheld(2.0 + (params.recovery_count - 1) / RATE))[0] < 10.0


def test_a_lost_track_restarts_from_consistent_single_marker_views_only():
    rng = np.random.default_rng(9)
    params = Tracker6Params()
    tracker = Tracker6(params)
    run_track(tracker, 1.0, rng, markers=1)
    t = 1.0 + params.lost_after + 0.5          # a gap: the track is dropped
    tracker.predict(t)
    assert not tracker.initialized
    assert tracker.update(flipped(handheld(t), 40.0), t, COV, markers=1).reason == PENDING
    t += 1.0 / RATE
    # The next one disagrees with the first (it was the flip): still pending, nothing published.
    assert tracker.update(noisy(handheld(t), rng), t, COV, markers=1).reason == PENDING
    t += 1.0 / RATE
    assert tracker.update(noisy(handheld(t), rng), t, COV, markers=1).reason == INITIALIZED
    assert errors(tracker, handheld(t))[1] < 1.0


def test_a_multi_marker_view_follows_a_fast_turn_at_a_low_rate():
    """A rig filmed at 2 Hz turning fast: several markers (no mirrored solution) are not held to
    max_angle_deg, so the track follows instead of coasting."""
    rng = np.random.default_rng(8)
    tracker = Tracker6()
    for k in range(20):
        t = 0.5 * k
        T = geo.make_transform(geo.matrix_from_rpy(0.2 * np.sin(t), 0.0, 0.5 * t), [0.1 * t, 0.0, 1.0])
        d = tracker.update(noisy(T, rng), t, COV, markers=4)
        assert d.accepted, (k, d)
        assert errors(tracker, T)[1] < 0.5


def test_filter_model_is_checked():
    assert FilterParams().model == "planar"
    assert with_overrides(LocalizerConfig(), {"filter.model": "6dof"}).filter.model == "6dof"
    with pytest.raises(ConfigError, match="model"):
        FilterParams(model="3dof")
    with pytest.raises(ConfigError, match="max_angle_deg"):
        Tracker6Params(max_angle_deg=0.0)


def test_after_a_gap_the_cap_still_keeps_a_single_marker_flip_out():
    """0.3 s without a measurement: the motion bound alone would let a 45 deg turn in; a single
    marker's flip is held to max_angle_deg (widened only by the track's own rotation std)."""
    rng = np.random.default_rng(12)
    tracker = Tracker6()
    run_track(tracker, 3.0, rng, markers=1)
    t = 3.0 - 1.0 / RATE + 0.3
    assert np.degrees(tracker.thresholds(0.3, capped=False)[1]) > 50.0
    d = tracker.update(flipped(handheld(t), 45.0), t, COV, markers=1)
    assert not d.accepted
    assert errors(tracker, handheld(t))[1] < 5.0     # the coasting prediction, not the 45 deg flip
    # The same turn seen with several markers is a real one: it enters.
    d = tracker.update(noisy(handheld(t), rng), t, COV, markers=3)
    assert d.accepted


# --- coasting: the prediction is published for a bounded time only ------------------------------

def _tracked(rng, t_end: float = 3.0, **params) -> Tracker6:
    tracker = Tracker6(Tracker6Params(**params))
    run_track(tracker, t_end, rng)
    return tracker


def _published(tracker: Tracker6, gaps) -> list:
    t_last = tracker.last_accepted_stamp
    out = []
    for dt in gaps:
        tracker.predict(t_last + dt)
        out.append(tracker.publishable(t_last + dt))
    return out


GAPS = (0.05, 0.1, 0.15, 0.24, 0.26, 0.4, 0.8)


def test_a_coasting_prediction_is_published_up_to_max_coast_only():
    # The uncertainty bounds out of the way: the time bound alone decides.
    loose = dict(coast_max_angle_deg=90.0, coast_max_distance=10.0)
    tracker = _tracked(np.random.default_rng(11), **loose)
    assert tracker.publishable(tracker.last_accepted_stamp)
    assert _published(tracker, GAPS) == [True, True, True, True, False, False, False]
    assert tracker.initialized   # the track itself is kept until lost_after (1 s)
    assert tracker.withheld_total == 3
    # A longer bound publishes for longer: the bound, nothing else, withheld them.
    longer = _tracked(np.random.default_rng(11), max_coast=0.9, **loose)
    assert _published(longer, GAPS) == [True] * len(GAPS)


def test_with_the_defaults_a_turning_rig_coasts_less_than_max_coast():
    # The handheld model (angular_accel_noise 2 rad^2/s^3): after about 0.17 s its rotation is
    # uncertain by more than the flip threshold over sigma_factor (10 / 3 deg).
    tracker = _tracked(np.random.default_rng(11))
    published = _published(tracker, GAPS)
    assert published[:2] == [True, True] and not any(published[3:])
    assert 3.0 * np.degrees(np.sqrt(np.linalg.eigvalsh(tracker.covariance[3:, 3:])[-1])) > 10.0


def test_an_uncertain_prediction_is_withheld_before_max_coast():
    # A track just started (velocity std 0.5 rad/s): within 0.2 s its rotation is uncertain by more
    # than the flip threshold over sigma_factor (10 / 3 deg).
    tracker = Tracker6()
    T = handheld(0.0)
    assert tracker.update(T, 0.0, COV, markers=3).reason == INITIALIZED
    tracker.predict(0.2)
    s_rot = np.degrees(np.sqrt(np.linalg.eigvalsh(tracker.covariance[3:, 3:])[-1]))
    assert 3.0 * s_rot > 10.0
    assert not tracker.publishable(0.2)
    relaxed = Tracker6(Tracker6Params(coast_max_angle_deg=90.0))
    relaxed.update(T, 0.0, COV, markers=3)
    relaxed.predict(0.2)
    assert relaxed.publishable(0.2)


def test_a_contradicting_multi_marker_measurement_withholds_the_prediction():
    rng = np.random.default_rng(12)
    tracker = _tracked(rng)
    t = tracker.last_accepted_stamp + 1.0 / RATE
    far = geo.make_transform(handheld(t)[:3, :3], handheld(t)[:3, 3] + np.array([0.8, 0.0, 0.0]))
    d = tracker.update(far, t, COV, markers=4)
    assert not d.accepted
    assert not tracker.publishable(t)        # several markers say otherwise: neither is published
    t2 = t + 1.0 / RATE
    tracker.predict(t2)
    assert tracker.publishable(t2)           # only at that stamp
    # A single-marker measurement that far: a flip, or the map's markers disagreeing (a resolved
    # single tag 0.9 m off on TagSLAM's test_9); nothing says which, so not published either.
    t3 = t2 + 1.0 / RATE
    d = tracker.update(flipped(handheld(t3), 40.0), t3, COV, markers=1)
    assert not d.accepted
    assert not tracker.publishable(t3)
    t4 = t3 + 1.0 / RATE
    tracker.predict(t4)
    assert tracker.publishable(t4)


def test_an_ambiguous_measurement_withholds_the_prediction_only_when_every_pose_contradicts_it():
    rng = np.random.default_rng(13)
    tracker = _tracked(rng)
    t = tracker.last_accepted_stamp + 1.0 / RATE
    T = handheld(t)
    far = geo.make_transform(T[:3, :3], T[:3, 3] + np.array([0.6, 0.0, 0.0]))
    # One of its poses agrees with the prediction: the prediction is published (never fused).
    d = tracker.update(far, t, COV, ambiguous=True, alternatives=[noisy(T, rng)])
    assert d.reason == REJECTED_AMBIGUOUS and tracker.publishable(t)
    # Both of its poses are beyond the gate: the prediction is contradicted whichever is true.
    t2 = t + 1.0 / RATE
    T2 = handheld(t2)
    d = tracker.update(flipped(T2, 30.0) @ geo.make_transform(np.eye(3), [0.0, 0.0, 0.6]), t2, COV,
                       ambiguous=True, alternatives=[far])
    assert d.reason == REJECTED_AMBIGUOUS and not tracker.publishable(t2)
    # Nothing of it entered the track.
    e = errors(tracker, T2)
    assert e[0] < 20.0 and e[1] < 1.0, e


def test_an_odometry_increment_moves_the_track_along_it_and_carries_its_covariance():
    """predict_increment: an exact increment lands on the true pose; the covariance it gives is the
    one of the pose after the increment, checked by sampling the start's error and the increment's."""
    rng = np.random.default_rng(11)
    T0, T1 = handheld(2.0), handheld(2.4)
    D = geo.inverse(T0) @ T1
    tracker = Tracker6()
    tracker.reset(T0, 2.0, COV)
    # The start's rotation uncertain enough (3 deg) that its lever arm over the increment's
    # translation dominates the position's error: the cross term is what is checked.
    tracker.P[:6, :6] = np.diag([0.001 ** 2] * 3 + [np.radians(3.0) ** 2] * 3)
    P0 = tracker.P[:6, :6].copy()
    Q = np.diag([0.001 ** 2] * 3 + [np.radians(0.3) ** 2] * 3)   # (translation, rotation), body frame at t0
    tracker.predict_increment(2.4, D, Q)
    assert tracker.stamp == 2.4
    dp, dr = geo.pose_distance(T1, tracker.pose)
    assert dp < 1e-9 and dr < 1e-9
    # Sample: T0_true = (p + dp, exp(dtheta) R), D_true = (exp(n_r) R_D, t_D + n_t); the error of
    # T0_true · D_true against the tracker's pose in its convention (position, map-frame rotvec).
    n = 4000
    e0 = rng.multivariate_normal(np.zeros(6), P0, n)
    nd = rng.multivariate_normal(np.zeros(6), Q, n)
    err = np.empty((n, 6))
    for k in range(n):
        A = geo.make_transform(geo.so3_exp(e0[k, 3:]) @ T0[:3, :3], T0[:3, 3] + e0[k, :3])
        Dk = geo.make_transform(geo.so3_exp(nd[k, 3:]) @ D[:3, :3], D[:3, 3] + nd[k, :3])
        B = A @ Dk
        err[k] = np.concatenate([B[:3, 3] - tracker.p, geo.rvec_from_rotation(B[:3, :3] @ tracker.R.T).ravel()])
    C = np.cov(err.T)
    P = tracker.P[:6, :6]
    # Every direction's variance within 10 % (4000 samples: ~2 % sampling error), and more than the start's.
    s = np.sqrt(np.diag(P))
    np.testing.assert_allclose(C / np.outer(s, s), P / np.outer(s, s), atol=0.1)
    assert np.all(np.diag(P) > np.diag(P0))
    # The velocity is the increment's mean velocity.
    np.testing.assert_allclose(tracker.v, (T1[:3, 3] - T0[:3, 3]) / 0.4, atol=1e-9)


def test_an_odometry_increment_after_lost_after_drops_the_track():
    tracker = Tracker6()
    tracker.reset(handheld(0.0), 0.0, COV)
    tracker.predict_increment(tracker.params.lost_after + 0.5, np.eye(4), np.eye(6) * 1e-6)
    assert not tracker.initialized


def test_a_measurement_moved_along_an_increment_has_its_sampled_covariance():
    """move_pose (a late frame carried along the odometry): the first-order covariance of T·D agrees
    with the spread of sampled poses and increments (seeded), and the mean moves as T·D."""
    rng = np.random.default_rng(11)
    T = handheld(2.0)
    D = geo.make_transform(geo.so3_exp([0.05, -0.1, 0.3]), [0.4, -0.2, 0.1])
    cov_T = np.diag([0.003 ** 2, 0.002 ** 2, 0.004 ** 2] + [np.radians(0.3) ** 2] * 3)
    cov_D = np.diag([0.001 ** 2, 0.004 ** 2, 0.002 ** 2] + list(np.radians([0.1, 0.4, 0.2]) ** 2))
    moved, C = move_pose(T, cov_T, D, cov_D)
    np.testing.assert_allclose(moved, T @ D, atol=1e-12)
    errs = []
    for _ in range(5000):
        e = rng.multivariate_normal(np.zeros(6), cov_T)
        n = rng.multivariate_normal(np.zeros(6), cov_D)
        Ts = geo.make_transform(geo.so3_exp(e[3:]) @ T[:3, :3], T[:3, 3] + e[:3])
        Ds = geo.make_transform(geo.so3_exp(n[3:]) @ D[:3, :3], D[:3, 3] + n[:3])   # noise in its first frame
        M = Ts @ Ds
        errs.append(np.concatenate([M[:3, 3] - moved[:3, 3],
                                    geo.rvec_from_rotation(M[:3, :3] @ moved[:3, :3].T).ravel()]))
    sampled = np.cov(np.array(errs).T)
    sd = np.sqrt(np.diag(C))
    # Correlations and stds within a few per cent (5,000 samples: about 1.4 % sampling error).
    np.testing.assert_allclose(sampled / np.outer(sd, sd), C / np.outer(sd, sd), atol=0.06)
    assert move_pose(T, None, D, cov_D)[1] is None
