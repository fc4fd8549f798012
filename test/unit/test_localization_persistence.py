"""The window's test of whether the cameras' disagreement is a calibration error
(localization.CalibrationPersistence, ``estimator/persistence_window``): its statistic against a
direct computation, and the rule on seeded simulated rigs: a well-calibrated ring whose map is off
(a marker-tied error the per-frame F-test rejects) is solved with the extrinsics as exact, a
miscalibrated ring with an exact map keeps the calibration-aware model."""
from __future__ import annotations

import dataclasses
from typing import List, Tuple

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.localization import CalibrationPersistence, LocalizationParams, RingLocalizer
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene

from helpers import RING_YAML

SIGMA = 0.3


@pytest.fixture(scope="module")
def lab():
    scene = Scene.default()
    poses = [Scene.T_world_base(p) for p in list(scene.test_positions) + list(scene.test_orientations)]
    return scene, CameraRing.load(str(RING_YAML)), scene.truth_map(), poses


def _direct(frames: List[List[Tuple[str, set, np.ndarray, np.ndarray]]]) -> Tuple[float, int]:
    """rho written out pair by pair (the docstring's formula), for the frames of one window."""
    num = den = 0.0
    pairs = 0
    names = {n for f in frames for n, *_ in f}
    for name in names:
        items = [(ids, G, b) for f in frames for n, ids, G, b in f if n == name]
        Ap = np.linalg.pinv(sum(G for _, G, _ in items), hermitian=True)
        for i in range(len(items)):
            for j in range(i + 1, len(items)):
                (si, _, bi), (sj, _, bj) = items[i], items[j]
                if si & sj:
                    continue
                num += bi @ Ap @ bj
                den += np.sqrt((bi @ Ap @ bi) * (bj @ Ap @ bj))
                pairs += 1
    return (num / den if den > 0 else float("nan")), pairs


# (window, frames, how often a camera is in a frame): the long runs move each camera's frames to
# its buffers' start several times (2 (window + 1) rows), and the rare camera leaves the window
# altogether and comes back: a stale row, column or sum there changes rho or the pairs.
@pytest.mark.parametrize("window, n_frames, p_in", [(7, 12, 0.8), (3, 60, 0.8), (5, 80, 0.3)])
def test_persistence_statistic_is_the_pairwise_formula_over_the_window(window, n_frames, p_in):
    rng = np.random.default_rng(3)
    cp = CalibrationPersistence(window)
    frames = []
    for k in range(n_frames):
        cams = [c for c in ("a", "b", "c") if rng.random() < p_in] or ["a"]
        frame = []
        for c in cams:
            M = rng.normal(size=(6, 10))
            ids = set(int(i) for i in rng.choice(8, size=int(rng.integers(1, 3)), replace=False))
            frame.append((c, ids, M @ M.T, rng.normal(size=6)))
        frames.append(frame)
        cp.add([f[0] for f in frame], [sorted(f[1]) for f in frame], np.stack([f[2] for f in frame]),
               np.stack([f[3] for f in frame]))
        rho, pairs = cp.correlation()
        rho_d, pairs_d = _direct(frames[-window:])
        assert pairs == pairs_d
        if pairs:
            assert rho == pytest.approx(rho_d, rel=1e-9, abs=1e-12)
        else:
            assert np.isnan(rho)
        # Each marker's list of frames holds the window's frames that saw it, and only them (a
        # left-over one changes nothing now but grows with every frame).
        window_frames = frames[-window:]
        for name, cam in cp._cams.items():
            seen = {}
            for f in window_frames:
                for n, ids, _, _ in f:
                    if n == name:
                        for i in ids:
                            seen[i] = seen.get(i, 0) + 1
            assert {i: len(v) for i, v in cam.seen.items()} == seen
    assert len(cp) == window


def test_a_constant_error_correlates_and_noise_does_not():
    rng = np.random.default_rng(4)
    eta = rng.normal(size=(2, 6))
    # Each camera's information changes between frames (other markers, other distances) about its
    # own mean; a constant error in directions it weighs differently gives rho below 1 even alone.
    G0 = np.stack([(lambda M: M @ M.T)(rng.normal(size=(6, 12))) for _ in range(2)])
    # rho grows with the constant part: none, about as large as the noise in b, ten times larger.
    for scale, lo, hi in ((0.0, -0.3, 0.3), (3.0, 0.5, 1.0), (30.0, 0.9, 1.0)):
        cp = CalibrationPersistence(40)
        for k in range(40):
            G = G0 + 0.3 * np.stack([(lambda M: M @ M.T)(rng.normal(size=(6, 12))) for _ in range(2)])
            b = np.einsum("cab,cb->ca", G, scale * eta) + np.stack(
                [np.linalg.cholesky(Gc) @ rng.normal(size=6) for Gc in G])
            cp.add(["a", "b"], [[k], [100 + k]], G, b)
        rho, pairs = cp.correlation()
        assert pairs == 2 * 40 * 39 // 2
        assert lo < rho < hi, (scale, rho)


def _off_map(truth: MarkerMap, pos: float, rot_deg: float, seed: int) -> MarkerMap:
    """The map with every marker moved by a seeded error in its own frame (a map's error: it follows
    the marker, not the camera)."""
    rng = np.random.default_rng(seed)
    return MarkerMap([MarkerEntry(e.marker_id, e.T_map_marker @ geo.se3_perturb(
        np.eye(4), np.r_[rng.normal(0, np.radians(rot_deg), 3), rng.normal(0, pos, 3)]), e.size) for e in truth],
        frame_id=truth.frame_id)


def _run(ring, marker_map, frames, poses, **kw):
    """Each frame's result, the window's (rho, pairs) after it and the pixel noise it was solved at.
    The declared vibration is kept (``estimate_vibration`` off unless given): these tests compare the
    window's calibration verdict with ``persistence_window: 0``, which has no vibration estimate
    (test_localization_vibration.py tests it)."""
    loc = RingLocalizer(ring, marker_map, LocalizationParams(pixel_noise=SIGMA, **{"estimate_vibration": False, **kw}))
    out = []
    for T, f in zip(poses, frames):
        guess = loc.pixel_noise_guess
        res = loc.process(f, prediction=T)
        assert res.ok and res.method == "joint"
        out.append((res, loc.last_persistence, guess))
    return out, loc


RIGID = {"extrinsic_jitter_deg": 0.0, "extrinsic_jitter_m": 0.0}


@pytest.mark.parametrize("vibration", [True, False])
def test_well_calibrated_ring_with_a_map_error_is_solved_without_the_calibration(lab, vibration):
    scene, ring, truth, poses = lab
    poses = poses * 2
    sim = RingSimulator(scene, ring, pixel_noise=SIGMA, seed=7)   # the ring is what its file says
    frames = [sim.observe(T, 0.1 * k) for k, T in enumerate(poses)]
    off = _off_map(truth, 0.003, 0.3, seed=5)
    kw = {} if vibration else RIGID
    alone, _ = _run(ring, off, frames, poses, persistence_window=0, **kw)
    rule, loc = _run(ring, off, frames, poses, **kw)
    multi = [k for k, (r, *_) in enumerate(alone) if len(r.used_cameras) > 1]
    # The map's error makes the cameras disagree in every frame: the per-frame test rejects them all.
    assert multi and not any(alone[k][0].extrinsics_consistent for k in multi)
    p = LocalizationParams()
    # Over the window it does not follow the cameras: once the window has its pairs, the ring's
    # calibration is cleared for every later frame.
    first = next(k for k, (_, (rho, pairs), _) in enumerate(rule) if pairs >= p.persistence_min_pairs)
    assert first < len(rule) // 2
    assert all(rho <= p.persistence_max for _, (rho, _), _ in rule[first:])
    cleared = [k for k, (r, *_) in enumerate(rule) if r.calibration_cleared]
    assert cleared == list(range(first + 1, len(rule)))
    assert len(loc.persistence) == p.persistence_window   # the window goes on while cleared
    # A cleared frame is the vibration-only model's pose (no vibration declared: the exact one).
    for k in cleared[::5]:
        res, _, guess = rule[k]
        ref = RingLocalizer(ring.with_extrinsics_std(0.0, 0.0), off,
                            LocalizationParams(pixel_noise=SIGMA, persistence_window=0, **kw))
        ref.pixel_noise_guess = guess
        res_ref = ref.process(frames[k], prediction=poses[k])
        assert geo.pose_distance(res.T_map_base, res_ref.T_map_base)[0] < 1e-9
        assert res.extrinsics_consistent == (not vibration)
        # The covariance still carries the calibration's declared error (the window cannot see
        # the cameras' common part): larger than the vibration-only model's.
        assert np.linalg.eigvalsh(res.covariance - res_ref.covariance).min() > 0.0
    # Before the window's verdict the frames are as without it.
    for k in range(first + 1):
        assert np.allclose(rule[k][0].T_map_base, alone[k][0].T_map_base, atol=1e-9)


def test_miscalibrated_ring_keeps_the_calibration_aware_model(lab):
    scene, ring, truth, poses = lab
    poses = poses * 2
    sim = RingSimulator(scene, perturb_ring(ring, seed=1), pixel_noise=SIGMA, seed=7)   # 2 mm / 0.2 deg off
    frames = [sim.observe(T, 0.1 * k) for k, T in enumerate(poses)]
    alone, _ = _run(ring, truth, frames, poses, persistence_window=0)
    rule, _ = _run(ring, truth, frames, poses)
    p = LocalizationParams()
    decided = [k for k, (_, (rho, pairs), _) in enumerate(rule) if pairs >= p.persistence_min_pairs]
    assert len(decided) >= len(rule) // 2
    assert all(rule[k][1][0] > p.persistence_max for k in decided)
    for (a, *_), (r, *_) in zip(alone, rule):
        assert not r.calibration_cleared
        assert r.extrinsics_consistent == a.extrinsics_consistent
        assert np.allclose(r.T_map_base, a.T_map_base, atol=1e-9)


def test_a_wiggling_camera_is_never_cleared_by_the_window(lab):
    scene, ring, truth, poses = lab
    wiggling = CameraRing([dataclasses.replace(c, wiggle=(0.01, 0.01)) if k == 0 else c
                           for k, c in enumerate(ring.cameras)], base_frame=ring.base_frame)
    sim = RingSimulator(scene, ring, pixel_noise=SIGMA, seed=7)
    frames = [sim.observe(T, 0.1 * k) for k, T in enumerate(poses)]
    off = _off_map(truth, 0.003, 0.3, seed=5)
    loc = RingLocalizer(wiggling, off, LocalizationParams(pixel_noise=SIGMA))
    ref = RingLocalizer(wiggling, off, LocalizationParams(pixel_noise=SIGMA, persistence_window=0))
    names = set()
    for T, f in zip(poses, frames):
        a, r = loc.process(f, prediction=T), ref.process(f, prediction=T)
        names |= set(a.used_cameras)
        assert not a.calibration_cleared
        assert a.extrinsics_consistent == r.extrinsics_consistent
        assert np.allclose(a.T_map_base, r.T_map_base, atol=1e-9)
    assert ring.cameras[0].name in names
    # No frame with the wiggling camera is recorded.
    assert ring.cameras[0].name not in loc.persistence._cams


def test_the_window_starts_anew_with_other_extrinsics_only(lab):
    _, ring, truth, _ = lab
    loc = RingLocalizer(ring, truth, LocalizationParams())
    loc.persistence.add(["cam0", "cam1"], [[1], [2]], np.stack([np.eye(6)] * 2), np.zeros((2, 6)))
    loc.set_ring(ring)
    assert len(loc.persistence) == 1
    loc.set_ring(perturb_ring(ring, seed=2))
    assert len(loc.persistence) == 0


@pytest.mark.parametrize("key, value", [("persistence_window", -1), ("persistence_min_pairs", -2),
                                        ("persistence_max", 1.5)])
def test_persistence_parameters_are_checked(key, value):
    with pytest.raises(ConfigError) as exc:
        LocalizationParams(**{key: value})
    assert key in str(exc.value)


def test_the_maps_covariance_of_refined_extrinsics_is_not_cleared(lab):
    """The window clears the ring file's extrinsics_std (a declaration); the map's covariance of its
    refined extrinsics is the mapping's own estimate from the data, and stays."""
    scene, ring, truth, poses = lab
    sim = RingSimulator(scene, ring, pixel_noise=SIGMA, seed=7)
    frames = [sim.observe(T, 0.1 * k) for k, T in enumerate(poses * 2)]
    off = _off_map(truth, 0.003, 0.3, seed=5)
    off.ring_extrinsics = {c.name: c.T_base_cam for c in ring.cameras}
    off.ring_covariance_cameras = ring.names
    off.ring_extrinsics_covariance = np.eye(6 * len(ring)) * 1e-6
    off.ring_base_frame = ring.base_frame
    rule, loc = _run(ring, off, frames, poses * 2)
    assert set(loc.extrinsics_source.values()) == {"map"}
    alone, _ = _run(ring, off, frames, poses * 2, persistence_window=0)
    p = LocalizationParams()
    # The window's verdict is the same as with the ring file's std: borne out ...
    assert any(pairs >= p.persistence_min_pairs and rho <= p.persistence_max for _, (rho, pairs), _ in rule)
    # ... and changes nothing here.
    for (a, *_), (r, *_) in zip(alone, rule):
        assert not r.calibration_cleared
        assert np.allclose(r.T_map_base, a.T_map_base, atol=1e-9)


def test_a_ring_declared_exact_has_nothing_to_clear(lab):
    scene, ring, truth, poses = lab
    exact = ring.with_extrinsics_std(0.0, 0.0)
    sim = RingSimulator(scene, ring, pixel_noise=SIGMA, seed=7)
    frames = [sim.observe(T, 0.1 * k) for k, T in enumerate(poses * 2)]
    off = _off_map(truth, 0.003, 0.3, seed=5)
    rule, _ = _run(exact, off, frames, poses * 2)
    alone, _ = _run(exact, off, frames, poses * 2, persistence_window=0)
    for (a, *_), (r, *_) in zip(alone, rule):
        assert not r.calibration_cleared
        assert np.allclose(r.T_map_base, a.T_map_base, atol=1e-9)
        assert np.allclose(r.covariance, a.covariance, rtol=1e-9, atol=1e-15)
