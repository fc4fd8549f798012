"""Ring calibration with a declared wiggle (ring_calibration.py's wiggle stage): a camera that moves
on the ring from frame to frame about a fixed pose, the ring file saying so."""
from __future__ import annotations

import os
from dataclasses import replace

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization import ring_calibration as rc
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.markers import MarkerSizes
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.calibration_run import calibration_poses, rough_ring
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene

RING = os.path.join(os.path.dirname(__file__), "..", "..", "config", "ring.yaml")
WIGGLING = "cam0"
PAN_DEG = 0.1          # cam0 pans by +-0.1 deg about its fixed pose, frame by frame
DECLARED = (np.radians(0.5), 0.005)


@pytest.fixture(scope="module")
def recording():
    """The lab ring turning on the spot; cam0 pans +0.1 deg in the half of the frames where it sees
    the most markers and -0.1 deg in the other half (seeded tie-break): its fixed pose (the mean of
    its per-frame poses) is the true one, but a rigid fit weighs the frames by what they see and is
    pulled towards +. The rough ring declares cam0's wiggle."""
    ring = CameraRing.load(RING)
    true = perturb_ring(ring, seed=1)
    scene = Scene.default()
    sim = RingSimulator(scene, true, pixel_noise=0.3, seed=0)
    poses = calibration_poses(scene.mapping_stations[:1], turn_step_deg=5.0)
    cam = true[WIGGLING]
    Ts = [Scene.T_world_base(p) for p in poses]
    counts = [len(sim.visible_camera(T, cam)) for T in Ts]
    rng = np.random.default_rng(0)
    seen = sorted((k for k in range(len(Ts)) if counts[k] > 0), key=lambda k: (counts[k], rng.random()))
    sign = np.zeros(len(Ts))
    sign[seen[len(seen) // 2:]] = 1.0
    sign[seen[:len(seen) // 2]] = -1.0
    sign[seen[len(seen) // 2]] = 0.0 if len(seen) % 2 else 1.0
    frames = []
    for k, T in enumerate(Ts):
        f = sim.observe(T, stamp=0.1 * k)
        moved = replace(cam, T_base_cam=cam.T_base_cam @ geo.make_transform(geo.so3_exp(np.radians([0, sign[k] * PAN_DEG, 0])),
                                                                           np.zeros(3)))
        f.cameras[WIGGLING].observations = sim.observe_camera(T, moved)
        frames.append(f)
    assert abs(sign.sum()) <= 1.0
    rough = rough_ring(true, seed=5)
    declared = CameraRing([replace(c, wiggle=DECLARED if c.name == WIGGLING else None) for c in rough],
                          rough.base_frame)
    cal = rc.calibrate_ring(frames, declared, MarkerSizes(scene.markers[0].size))
    return true, rough, declared, frames, scene, cal


def _error(true: CameraRing, est: CameraRing):
    """(mm, deg) of the wiggling camera against its true fixed pose, the ring aligned on the others."""
    others = [c for c in true.names if c != WIGGLING]
    G = geo.average_transforms([true[c].T_base_cam @ geo.inverse(est[c].T_base_cam) for c in others])
    D = geo.inverse(true[WIGGLING].T_base_cam) @ G @ est[WIGGLING].T_base_cam
    return 1000 * float(np.linalg.norm(D[:3, 3])), float(np.degrees(geo.rotation_angle(D[:3, :3])))


def test_a_declared_wiggle_recovers_the_fixed_pose_where_a_rigid_fit_is_biased(recording):
    true, _, declared, _, _, cal = recording
    assert cal.wiggle is not None and cal.wiggle.wiggling == [WIGGLING]
    assert cal.wiggle.sigma == pytest.approx(DECLARED)
    assert cal.rigid_ring is not None
    rigid = _error(true, cal.rigid_ring)
    fixed = _error(true, cal.ring)
    # The rigid answer is pulled by several mm; the fixed pose of the declared model is not.
    assert rigid[0] > 3.0, rigid
    assert fixed[0] < 1.5 and fixed[1] < 0.05, (fixed, rigid)
    # The alternation lowers the model's cost.
    costs = [r["cost"] for r in cal.wiggle.rounds]
    assert costs[-1] < costs[0], costs
    # The ring written keeps the declaration; the wiggling camera's std adds the wiggle over the
    # square root of its frames, the others' are the rigid adjustment's.
    assert cal.ring[WIGGLING].wiggle == pytest.approx(DECLARED)
    n = cal.wiggle.camera_frames[WIGGLING]
    expected = np.sqrt(np.square(cal.rigid_ring[WIGGLING].extrinsics_std)
                       + np.square([DECLARED[0]] * 3 + [DECLARED[1]] * 3) / n)
    assert np.allclose(cal.std[WIGGLING], expected), (cal.std[WIGGLING], expected)
    for c in true.names[1:]:
        assert np.allclose(cal.std[c], cal.rigid_ring[c].extrinsics_std), c


def test_wiggle_off_is_the_rigid_calibration(recording):
    _, rough, declared, frames, scene, cal = recording
    off = rc.calibrate_ring(frames, declared, MarkerSizes(scene.markers[0].size),
                            options=rc.CalibrationOptions(wiggle="off"))
    assert off.wiggle is None and off.rigid_ring is None
    for c in rough.names:
        assert np.allclose(off.ring[c].T_base_cam, cal.rigid_ring[c].T_base_cam, atol=1e-9), c
    # A ring that declares nothing: rigid, as before.
    plain = rc.calibrate_ring(frames, rough, MarkerSizes(scene.markers[0].size))
    assert plain.wiggle is None and plain.rigid_ring is None
    for c in rough.names:
        assert np.allclose(plain.ring[c].T_base_cam, off.ring[c].T_base_cam, atol=1e-9), c


def test_declared_wiggle_and_its_option():
    ring = CameraRing.load(RING)
    assert rc.declared_wiggle(ring) is None
    mixed = CameraRing([replace(c, wiggle=(0.01, 0.02) if c.name in ("cam1", "cam2") else
                                (0.03, 0.04) if c.name == "cam3" else None) for c in ring], ring.base_frame)
    flags, rot, trans = rc.declared_wiggle(mixed)
    assert flags == [c in ("cam1", "cam2", "cam3") for c in ring.names]
    assert (rot, trans) == (0.01, 0.02)         # the median of the declared values
    with pytest.raises(ConfigError, match="auto or off"):
        rc.CalibrationOptions(wiggle="on")
    with pytest.raises(ConfigError, match="wiggle_max_frames"):
        rc.CalibrationOptions(wiggle_max_frames=1)
    with pytest.raises(ConfigError, match="wiggle_max_poses"):
        rc.CalibrationOptions(wiggle_max_poses=2)
