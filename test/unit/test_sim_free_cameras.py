"""Free-running cameras in the simulator (cameras.trigger): phases, jitter, per-camera stamps, and the
ground truth at any stamp (SimulatorCore.true_pose_at)."""
from __future__ import annotations

import os

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.config import load_config, with_overrides
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.params import SimulatorConfig
from aruco_ring_localization.simulation.ring_sim import RingSimulator
from aruco_ring_localization.simulation.scene import Scene
from aruco_ring_localization.simulation.simulator import MAX_OFFSET, SimulatorCore, interpolate_se2

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
DT = 0.1


@pytest.fixture(scope="module")
def scene_ring():
    return Scene.default(), CameraRing.load(os.path.join(REPO, "config", "ring.yaml"))


def core_for(scene_ring, **dotted) -> SimulatorCore:
    base = {"robot.waypoints": "test_positions", "robot.hold_time": 0.5, "rate": 1.0 / DT}
    base.update(dotted)
    return SimulatorCore(with_overrides(SimulatorConfig(), base), *scene_ring)


def run(core: SimulatorCore, frames: int):
    """Step ``frames`` frames; yields (t, stamps) per frame."""
    for k in range(1, frames + 1):
        t = round(1.0 + k * DT, 9)
        core.step(t, DT)
        yield t, dict(core.stamps)


@pytest.mark.parametrize("values, key", [
    ({"cameras": {"trigger": "random"}}, "cameras.trigger"),
    ({"cameras": {"phase_spread": 1.5}}, "cameras.phase_spread"),
    ({"cameras": {"jitter_std": -0.001}}, "cameras.jitter_std")])
def test_bad_trigger_params_name_the_key(values, key):
    with pytest.raises(ConfigError) as info:
        load_config(SimulatorConfig, values, source="simulator.yaml")
    assert info.value.key == key


def test_synchronized_cameras_expose_at_the_frame_time_and_see_what_they_did_before(scene_ring):
    scene, _ = scene_ring
    core = core_for(scene_ring)
    # The synchronized simulator: every camera at the frame's time, the same draws as one RingSimulator
    # observing the robot's pose (what the simulator did before free cameras).
    ref = RingSimulator(scene, core.true_ring, pixel_noise=0.3, seed=0)
    for t, stamps in run(core, 30):
        assert set(stamps.values()) == {t}
        dets = core.detections()
        frame = ref.observe(Scene.T_world_base(core.state.pose), t)
        for cam, obs in dets.items():
            want = frame.cameras[cam].observations
            assert [o.marker_id for o in obs] == [o.marker_id for o in want]
            for a, b in zip(obs, want):
                assert np.array_equal(a.corners, b.corners)


def test_free_cameras_have_spread_phases_and_a_per_frame_jitter_within_one_period(scene_ring):
    core = core_for(scene_ring, **{"cameras.trigger": "free", "cameras.jitter_std": 0.002})
    offsets = {c: [] for c in core.cameras}
    for t, stamps in run(core, 200):
        for c, s in stamps.items():
            offsets[c].append(t - s)
    phases = np.array([np.median(v) for v in offsets.values()])
    all_off = np.concatenate([np.asarray(v) for v in offsets.values()])
    assert np.all(all_off >= -1e-9) and np.all(all_off <= MAX_OFFSET * DT + 1e-9)
    assert np.ptp(phases) > 0.3 * DT, phases            # spread over the frame period (8 uniform draws)
    assert len(np.unique(np.round(phases, 6))) == len(phases)
    # The jitter: each camera's offset moves from frame to frame by about jitter_std (away from the clip).
    inner = [np.asarray(v) for v in offsets.values() if 0.01 < np.median(v) < 0.09]
    assert inner
    for v in inner:
        assert 0.001 < np.std(v) < 0.004, np.std(v)
    # Seeded: the same config gives the same stamps, another seed others.
    again = [s for _, s in run(core_for(scene_ring, **{"cameras.trigger": "free"}), 5)]
    first = [s for _, s in run(core_for(scene_ring, **{"cameras.trigger": "free"}), 5)]
    other = [s for _, s in run(core_for(scene_ring, **{"cameras.trigger": "free", "seed": 3}), 5)]
    assert again == first and other != first


def test_phase_spread_zero_without_jitter_is_synchronized(scene_ring):
    core = core_for(scene_ring, **{"cameras.trigger": "free", "cameras.phase_spread": 0.0,
                                   "cameras.jitter_std": 0.0})
    for t, stamps in run(core, 5):
        assert set(stamps.values()) == {t}


def test_ground_truth_at_any_stamp_interpolates_the_trajectory(scene_ring):
    core = core_for(scene_ring)
    steps = []
    for t, _ in run(core, 40):
        steps.append((t, core.state.pose.copy()))
    # At a step's time: the step's pose; between: the interpolation of its neighbours; moving at some point.
    speeds = [np.hypot(*(b[1][:2] - a[1][:2])) / DT for a, b in zip(steps, steps[1:])]
    k = int(np.argmax(speeds))
    assert speeds[k] > 0.1
    (t0, p0), (t1, p1) = steps[k], steps[k + 1]
    assert np.array_equal(core.true_se2_at(t1), p1)
    mid = core.true_se2_at(t0 + 0.3 * DT)
    assert np.allclose(mid[:2], p0[:2] + 0.3 * (p1[:2] - p0[:2]))
    assert abs(geo.angle_diff(mid[2], p0[2] + 0.3 * geo.angle_diff(p1[2], p0[2]))) < 1e-12
    assert np.allclose(core.true_pose_at(t0 + 0.3 * DT), Scene.T_world_base(mid))
    # Held at the ends.
    assert np.array_equal(core.true_se2_at(steps[-1][0] + 5.0), steps[-1][1])


def test_interpolation_takes_the_short_way_round():
    a, b = np.array([0.0, 0.0, np.radians(179.0)]), np.array([1.0, 0.0, np.radians(-179.0)])
    m = interpolate_se2(a, b, 0.5)
    assert abs(abs(m[2]) - np.pi) < 1e-9 and m[0] == 0.5


def test_free_camera_sees_the_robot_at_its_own_exposure_time(scene_ring):
    scene, _ = scene_ring
    core = core_for(scene_ring, **{"cameras.trigger": "free", "cameras.pixel_noise": 0.0,
                                   "robot.limits.max_speed": 0.5})
    ref = RingSimulator(scene, core.true_ring, pixel_noise=0.0)
    checked = moved = 0
    for t, stamps in run(core, 60):
        dets = core.detections()
        for cam, obs in dets.items():
            if not obs:
                continue
            at_stamp = dict(ref.visible_camera(core.true_pose_at(stamps[cam]), cam))
            at_frame = dict(ref.visible_camera(core.true_pose_at(t), cam))
            for o in obs:
                assert np.allclose(o.corners, at_stamp[o.marker_id], atol=1e-9)
                checked += 1
                if o.marker_id in at_frame and np.abs(o.corners - at_frame[o.marker_id]).max() > 0.5:
                    moved += 1
    assert checked > 100 and moved > 10, (checked, moved)
