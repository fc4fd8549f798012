"""gating.py: reject jumps, thresholds growing with time and speed, recovery after a kidnap, flips
(the full rotation's tilt, ambiguous measurements)."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization import geometry as geo
from aruco_ring_localization.gating import (ACCEPTED, INITIALIZED, REINITIALIZED, REJECTED_AMBIGUOUS, REJECTED_JUMP,
                                            REJECTED_TILT, GateParams, MotionGate)


def test_first_measurement_initialises():
    gate = MotionGate()
    d = gate.check([1.0, 2.0, 0.0], 0.0, predicted=None)
    assert d.accepted and d.reason == INITIALIZED


def test_rejects_a_1m_jump_at_rest_and_accepts_small_noise():
    gate = MotionGate()
    gate.check([1.0, 1.0, 0.0], 0.0)
    ok = gate.check([1.01, 1.0, 0.01], 0.1, predicted=[1.0, 1.0, 0.0])
    assert ok.accepted and ok.reason == ACCEPTED
    bad = gate.check([2.0, 1.0, 0.0], 0.2, predicted=[1.0, 1.0, 0.0])
    assert not bad.accepted and bad.reason == REJECTED_JUMP, f"1 m jump accepted: {bad}"
    assert bad.distance == pytest.approx(1.0) and bad.allowed_distance < 0.5
    yaw_jump = gate.check([1.0, 1.0, 0.8], 0.3, predicted=[1.0, 1.0, 0.0])
    assert not yaw_jump.accepted, f"0.8 rad yaw jump accepted: {yaw_jump}"


def test_thresholds_grow_with_time_and_speed():
    gate = MotionGate()
    d0, a0 = gate.thresholds(0.1)
    d1, a1 = gate.thresholds(2.0)
    d2, a2 = gate.thresholds(0.1, speed=1.0, yaw_rate=1.0)
    assert d1 > d0 and a1 > a0 and d2 > d0 and a2 > a0, (d0, d1, d2, a0, a1, a2)
    # A 1 m move is fine after 1 s at 1 m/s commanded.
    gate.check([0.0, 0.0, 0.0], 0.0)
    d = gate.check([1.0, 0.0, 0.0], 1.0, predicted=[0.0, 0.0, 0.0], speed=1.0)
    assert d.accepted, f"1 m after 1 s at 1 m/s rejected: {d}"


def test_yaw_jump_measured_across_pi():
    gate = MotionGate()
    gate.check([0.0, 0.0, np.pi - 0.01], 0.0)
    d = gate.check([0.0, 0.0, -np.pi + 0.01], 0.1, predicted=[0.0, 0.0, np.pi - 0.01])
    assert d.accepted and d.angle == pytest.approx(0.02, abs=1e-9), f"{d}"


def test_recovers_after_kidnap_without_lockout():
    params = GateParams(recovery_count=5)
    gate = MotionGate(params)
    gate.check([1.0, 1.0, 0.0], 0.0)
    track = np.array([1.0, 1.0, 0.0])
    rng = np.random.default_rng(0)
    decisions = []
    for k in range(1, 10):  # kidnapped to (4, 3): consistent measurements there
        z = np.array([4.0, 3.0, 1.0]) + rng.normal(0, [0.005, 0.005, 0.002])
        decisions.append(gate.check(z, 0.1 * k, predicted=track))
        if decisions[-1].accepted:
            track = z
    reasons = [d.reason for d in decisions]
    assert reasons[:4] == [REJECTED_JUMP] * 4, reasons
    assert reasons[4] == REINITIALIZED, f"no re-initialisation after 5 consistent rejections: {reasons}"
    assert all(r == ACCEPTED for r in reasons[5:]), reasons
    assert gate.reinitializations == 1


def test_inconsistent_outliers_do_not_reinitialise():
    gate = MotionGate(GateParams(recovery_count=3))
    gate.check([0.0, 0.0, 0.0], 0.0)
    for k, z in enumerate([[3, 0, 0], [0, 3, 0], [-3, 0, 0], [0, -3, 0], [3, 3, 0]]):
        d = gate.check(z, 0.1 * (k + 1), predicted=[0.0, 0.0, 0.0])
        assert not d.accepted, f"scattered outlier {z} accepted ({d.reason})"


def test_disabled_gate_accepts_everything():
    gate = MotionGate(GateParams(enabled=False))
    gate.check([0, 0, 0], 0.0)
    assert gate.check([10, 0, 0], 0.1, predicted=[0, 0, 0]).accepted


def test_bad_params():
    with pytest.raises(ConfigError, match="recovery_count"):
        GateParams(recovery_count=0)


def test_uncertain_track_widens_the_gate():
    gate = MotionGate(GateParams(sigma_factor=3.0))
    gate.check([0.0, 0.0, 0.0], 0.0)
    z, pred = [0.3, 0.0, 0.0], [0.0, 0.0, 0.0]
    tight = gate.check(z, 0.1, predicted=pred, covariance=np.diag([1e-6, 1e-6, 1e-6]))
    assert not tight.accepted, f"0.3 m jump accepted with a 1 mm track: {tight}"
    gate.reset()
    gate.check([0.0, 0.0, 0.0], 0.0)
    loose = gate.check(z, 0.1, predicted=pred, covariance=np.diag([0.01, 0.01, 1e-4]))  # 10 cm std
    assert loose.accepted and loose.allowed_distance == pytest.approx(gate.thresholds(0.1)[0] + 0.3), f"{loose}"


# --- flips: the full rotation and ambiguous measurements ------------------------------------

def _tilted(deg: float, axis=(1.0, 0.0, 0.0)) -> np.ndarray:
    return geo.rotation_from_rvec(np.radians(deg) * np.asarray(axis))


def test_a_tilted_measurement_is_rejected_even_when_x_y_yaw_fit():
    """A flipped pose whose (x, y, yaw) lands next to the prediction still tilts: rejected."""
    gate = MotionGate(GateParams(max_tilt_change_deg=5.0))
    gate.check([1.0, 1.0, 0.0], 0.0, rotation=np.eye(3))
    level = gate.check([1.01, 1.0, 0.0], 0.1, predicted=[1.0, 1.0, 0.0], rotation=_tilted(0.5))
    assert level.accepted and level.tilt == pytest.approx(np.radians(0.5), abs=1e-9), f"{level}"
    flipped = gate.check([1.02, 1.0, 0.0], 0.2, predicted=[1.0, 1.0, 0.0], rotation=_tilted(12.0, (0.0, 1.0, 0.0)))
    assert not flipped.accepted and flipped.reason == REJECTED_TILT, f"12 deg tilt accepted: {flipped}"
    # Against the track's own tilt (the last accepted one, 0.5 deg about x), not the map's z.
    assert flipped.tilt == pytest.approx(np.radians(12.0), abs=np.radians(0.6)), np.degrees(flipped.tilt)
    # Without a rotation the gate is as before (x, y, yaw only).
    assert gate.check([1.02, 1.0, 0.0], 0.3, predicted=[1.0, 1.0, 0.0]).accepted


def test_ambiguous_measurements_never_start_update_or_restart_a_track():
    gate = MotionGate(GateParams(recovery_count=3))
    first = gate.check([1.0, 1.0, 0.0], 0.0, ambiguous=True)
    assert not first.accepted and first.reason == REJECTED_AMBIGUOUS, f"an ambiguous pose started the track: {first}"
    assert gate.check([1.0, 1.0, 0.0], 0.1).reason == INITIALIZED
    near = gate.check([1.0, 1.0, 0.0], 0.2, predicted=[1.0, 1.0, 0.0], ambiguous=True)
    assert not near.accepted and near.reason == REJECTED_AMBIGUOUS, f"{near}"
    # A kidnap: consistent unambiguous measurements elsewhere re-initialise, ambiguous ones at the
    # same place neither count nor interrupt the count.
    reasons = []
    for k, amb in enumerate([False, True, True, False, True, False]):
        reasons.append(gate.check([4.0, 3.0, 1.0], 0.3 + 0.1 * k, predicted=[1.0, 1.0, 0.0], ambiguous=amb).reason)
    assert reasons == [REJECTED_JUMP, REJECTED_AMBIGUOUS, REJECTED_AMBIGUOUS, REJECTED_JUMP, REJECTED_AMBIGUOUS,
                       REINITIALIZED], reasons
    # Only ambiguous ones, however consistent: no re-initialisation ever.
    gate = MotionGate(GateParams(recovery_count=3))
    gate.check([1.0, 1.0, 0.0], 0.0)
    assert not any(gate.check([4.0, 3.0, 1.0], 0.1 * k, predicted=[1.0, 1.0, 0.0], ambiguous=True).accepted
                   for k in range(1, 20))


def test_tilted_consistent_measurements_must_agree_in_tilt_to_recover():
    gate = MotionGate(GateParams(recovery_count=3))
    gate.check([0.0, 0.0, 0.0], 0.0, rotation=np.eye(3))
    tilts = [0.0, 30.0, 0.0, 30.0, 0.0, 30.0]   # alternating flips at one place: not a new truth
    for k, t in enumerate(tilts):
        d = gate.check([3.0, 0.0, 0.0], 0.1 * (k + 1), predicted=[0.0, 0.0, 0.0], rotation=_tilted(t))
        assert not d.accepted, f"re-initialised on alternating tilts at step {k}: {d}"


def test_bad_tilt_param():
    with pytest.raises(ConfigError, match="max_tilt_change"):
        GateParams(max_tilt_change_deg=-0.1)
