"""Hostile input into the localization pipeline, without ROS (issue 14, findings F1-F5, F7).

Each test replays one reproduction of the issue as events (``on_detections``, ``on_motion``,
``on_initial_pose``, ``poll``) with the node's clock ``now`` as a live node would see it, and
asserts the policy: what is dropped, that it never reaches the filter or the output, that each
problem is said once per throttle period (and counted every time), and that tracking goes on.
The same reproductions run through a real master in test/integration/hostile_*.test.
"""
from __future__ import annotations

import logging

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization import pipeline as pl
from aruco_ring_localization.config import with_overrides
from aruco_ring_localization.detections import MarkerObservation
from aruco_ring_localization.errors import MeasurementError
from aruco_ring_localization.pipeline import LocalizationPipeline, MappingPipeline, feed_ring_frame
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.schemas import LocalizerConfig, MapperConfig
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene
from aruco_ring_localization.throttle import WARN_PERIOD

from helpers import RING_YAML

OFFLINE = {"input.use_tf": False, "input.camera_info_fallback": True}
RATE = 10.0
T0 = 1000.0          # the node's clock at the start (s): a live node's clock is never near 0
TRACK_TOL = 0.03     # m: clean tracking here is 0.3-1 cm (0.3 px noise, miscalibrated rig)


@pytest.fixture(scope="module")
def world():
    scene = Scene.default()
    ring = CameraRing.load(str(RING_YAML))
    sim = RingSimulator(scene, perturb_ring(ring, seed=1), pixel_noise=0.3, seed=2)
    return scene, ring, sim


def _pipeline(world, **overrides) -> LocalizationPipeline:
    scene, ring, _ = world
    config = with_overrides(LocalizerConfig(), {**OFFLINE, **{k.replace("__", "."): v for k, v in overrides.items()}})
    return LocalizationPipeline(config, ring, scene.truth_map())


def _truth(t: float) -> np.ndarray:
    """A slow drive on the plate (0.1 m/s), t in s from T0."""
    return np.array([4.5 + 0.1 * t, 4.0 + 0.05 * t, 0.2 + 0.05 * t])


def _frame(world, k: int, delay: float = 0.01):
    """Ring frame k (stamp T0 + k / RATE) and the node's clock when it arrives."""
    scene, _, sim = world
    t = k / RATE
    return sim.observe(scene.T_world_base(_truth(t)), T0 + t), T0 + t + delay


def _err(out: pl.PoseOutput) -> float:
    return float(np.hypot(*(out.T_map_base[:2, 3] - _truth(out.stamp - T0)[:2])))


def _track(p, world, ks, **kw):
    outs = []
    for k in ks:
        frame, now = _frame(world, k)
        outs += feed_ring_frame(p, frame, now=now, **kw)
    return outs


def _lines(caplog, needle: str):
    return [r.getMessage() for r in caplog.records if needle in r.getMessage()]


# --- F1: stamps against the node's clock ----------------------------------------------------------

def test_one_future_stamped_empty_message_is_dropped_and_never_published(world, caplog):
    p = _pipeline(world)
    _track(p, world, range(10))
    resets = p.filter.resets
    with caplog.at_level(logging.WARNING, logger="aruco_ring_localization.pipeline"):
        now = T0 + 1.0
        assert p.on_detections("cam0", 2e9, [], now) == []
    assert p.input.skipped["cam0"] == {pl.SKIP_FUTURE_STAMP: 1}
    (line,) = _lines(caplog, "future stamp")
    assert "ring/cam0/fiducial_vertices" in line and f"+{2e9 - now:.3f} s" in line, line
    outs = _track(p, world, range(10, 30)) + p.poll(T0 + 3.05)
    assert outs and max(o.stamp for o in outs) <= T0 + 3.05, "a pose went out at a stamp after the clock"
    assert p.filter.stamp <= T0 + 3.05 and p.filter.resets == resets, "the future stamp reached the filter"
    assert max(_err(o) for o in outs) < TRACK_TOL


def test_every_cam0_message_100s_ahead_for_5s_changes_nothing(world, caplog):
    p = _pipeline(world)
    _track(p, world, range(10))
    resets = p.filter.resets
    outs = []
    with caplog.at_level(logging.WARNING, logger="aruco_ring_localization.pipeline"):
        for k in range(10, 60):   # 5 s: cam0's copy stamped +100 s beside the real messages
            frame, now = _frame(world, k)
            p.on_detections("cam0", frame.stamp + 100.0, frame.cameras["cam0"].observations, now)
            outs += feed_ring_frame(p, frame, now=now)
    assert p.input.skipped["cam0"][pl.SKIP_FUTURE_STAMP] == 50
    assert p.filter.resets == resets and p.time_jumps == 0
    assert len(outs) == 50 and max(_err(o) for o in outs) < TRACK_TOL
    # 50 drops in 4.9 s of the node's clock: one line (the next one is due at 5 s).
    assert len(_lines(caplog, "future stamp")) == 1 and p.warn.counts["cam0.future stamp"] == 50


def test_stamps_at_zero_or_not_finite_are_dropped_where_they_enter(world):
    p = _pipeline(world)
    _track(p, world, range(10))
    frame, now = _frame(world, 10)
    for stamp, reason in ((0.0, pl.SKIP_STALE_STAMP), (float("nan"), pl.SKIP_BAD_STAMP),
                          (float("inf"), pl.SKIP_BAD_STAMP)):
        assert p.on_detections("cam0", stamp, frame.cameras["cam0"].observations, now) == []
        assert p.input.skipped["cam0"][reason] >= 1
    assert p.time_jumps == 0 and p.input.assembler.time_jumps == 0
    assert len(feed_ring_frame(p, frame, now=now)) == 1


def test_a_late_camera_message_neither_resets_the_assembly_nor_the_filter(world):
    p = _pipeline(world)
    _track(p, world, range(20))
    frames_before = p.frames
    # cam3 lags 1.5 s behind (within timing/max_frame_age): its old messages must not pass for a
    # clock jump, which would throw away the other cameras' pending frames and reset the track.
    outs = []
    for k in range(20, 40):
        frame, now = _frame(world, k)
        old, _ = _frame(world, k - 15)
        p.on_detections("cam3", old.stamp, old.cameras["cam3"].observations, now)
        for name, cf in frame.cameras.items():
            if name != "cam3":
                outs += p.on_detections(name, cf.stamp, cf.observations, now)
        outs += p.poll(now + 0.3)
    assert p.time_jumps == 0 and p.input.assembler.time_jumps == 0
    assert p.frames - frames_before == 20 and len(outs) == 20
    assert max(_err(o) for o in outs) < TRACK_TOL


def test_a_ring_frame_behind_the_track_is_dropped_not_a_time_jump(world):
    p = _pipeline(world, timing__max_frame_age=5.0)
    _track(p, world, range(30))
    late, _ = _frame(world, 10)   # 2 s behind the track, 3 s old by the clock: not a clock jump
    assert feed_ring_frame(p, late, now=T0 + 3.0) == []
    assert p.time_jumps == 0 and p.filter.stamp == pytest.approx(T0 + 2.9)
    assert p.input.assembler.dropped_late == len(late.cameras)
    assert dict(p.diagnostics(T0 + 3.0)[-1].values)["camera_frames_late"] == str(len(late.cameras))


def test_the_clock_going_back_still_restarts_the_track(world):
    p = _pipeline(world)
    _track(p, world, range(20))
    scene, _, sim = world
    out = feed_ring_frame(p, sim.observe(scene.T_world_base(_truth(0.0)), T0 - 30.0), now=T0 - 29.99)
    assert p.time_jumps == 1 and len(out) == 1 and out[0].track.time_jump
    assert out[0].track.decision.reason == "initialized"


# --- F2: motion inputs ------------------------------------------------------------------------------

def _gate_after(p, world, k):
    """The gate's decision on ring frame k with the robot carried 35 cm away (only possible at speed)."""
    scene, _, sim = world
    moved = _truth(k / RATE) + [0.35, 0.0, 0.0]
    (out,) = feed_ring_frame(p, sim.observe(scene.T_world_base(moved), T0 + k / RATE), now=T0 + k / RATE + 0.01)
    return out.track.decision.reason


@pytest.mark.parametrize("twist,stamp_offset,key", [
    ((float("nan"), 0.0, 0.0), 1e6, "non-finite"),     # NaN twist stamped +1e6 s (the issue's)
    ((1e6, 0.0, 0.0), 100.0, "beyond limits"),         # 1e6 m/s with a future stamp
    ((3.0, 0.0, 0.0), 100.0, "future stamp"),          # a plausible speed, stamped in the future
    ((0.1, 0.0, 1e3), 0.0, "beyond limits"),           # yaw rate
    ((0.0, float("inf"), 0.0), 0.0, "non-finite"),
])
def test_bad_odometry_never_opens_or_blinds_the_gate(world, caplog, twist, stamp_offset, key):
    p = _pipeline(world, gate__sigma_factor=0.0)
    _track(p, world, range(10))
    now = T0 + 1.0
    with caplog.at_level(logging.WARNING, logger="aruco_ring_localization.pipeline"):
        assert p.on_motion("odom", now + stamp_offset, twist[:2], twist[2], now) == []
    assert p.warn.counts == {f"odom.{key}": 1}, p.warn.counts
    assert len(_lines(caplog, "odom:")) == 1
    assert p._speeds(now) == (0.0, 0.0), "a refused motion input reached the gate"
    assert _gate_after(p, world, 10) == "jump", "a 35 cm step at rest got through the gate"
    # ... and the gate is not blinded either: good frames go on being accepted.
    outs = _track(p, world, range(11, 20))
    assert [o.track.decision.reason for o in outs].count("accepted") >= 8


def test_continuous_nan_cmd_vel_leaves_the_localizer_seeing(world, caplog):
    p = _pipeline(world)
    outs = []
    with caplog.at_level(logging.WARNING, logger="aruco_ring_localization.pipeline"):
        for k in range(100):   # 10 s of NaN cmd_vel at 50 Hz beside the frames
            for j in range(5):
                p.on_motion("cmd_vel", None, (float("nan"), 0.0), float("nan"), T0 + k / RATE + 0.02 * j)
            frame, now = _frame(world, k)
            outs += feed_ring_frame(p, frame, now=now)
    assert len(outs) == 100 and max(_err(o) for o in outs[5:]) < TRACK_TOL
    assert all(o.track.decision.accepted for o in outs)
    # 500 drops over 10 s: a line at 0 s and one at 5 s (throttle period), every one counted.
    assert p.warn.counts["cmd_vel.non-finite"] == 500 and p.warn.said["cmd_vel.non-finite"] == 2
    assert len(_lines(caplog, "cmd_vel: non-finite")) == 2


def test_motion_input_is_stale_by_the_nodes_clock_not_its_stamp(world):
    p = _pipeline(world, gate__sigma_factor=0.0)
    _track(p, world, range(10))
    # An odometry twist stamped 0.2 s ahead (within input/max_stamp_ahead), then silence: 0.6 s
    # later by the node's clock it is stale (timing/motion_timeout 0.5 s), whatever its stamp says.
    now = T0 + 0.95
    p.on_motion("odom", now + 0.2, (3.0, 0.0), 0.0, now)
    assert p._speeds(now + 0.1) == (3.0, 0.0)
    assert p._speeds(now + 0.6) == (0.0, 0.0)
    p.on_motion("odom", now, (3.0, 0.0), 0.0, now)
    assert _gate_after(p, world, 10) == "accepted", "a fresh 3 m/s twist should allow 35 cm in 0.1 s"


# --- F3: bounded work per message ------------------------------------------------------------------

def test_a_flood_of_quads_is_dropped_whole_and_the_others_localize(world, caplog):
    p = _pipeline(world)
    _track(p, world, range(10))
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 1200, (3000, 2))
    quads = [MarkerObservation(int(i), np.array([[x, y], [x + 20, y], [x + 20, y + 20], [x, y + 20]]))
             for i, (x, y) in zip(rng.integers(0, 1000, 3000), xy)]
    outs = []
    with caplog.at_level(logging.WARNING, logger="aruco_ring_localization.pipeline"):
        for k in range(10, 60):   # 5 s at 10 Hz on cam0
            frame, now = _frame(world, k)
            frame.cameras["cam0"].observations = quads
            outs += feed_ring_frame(p, frame, now=now)
    assert p.input.skipped["cam0"] == {pl.SKIP_FLOOD: 50}
    assert p.input.rejected["cam0"] == {}, "the flood was sanitized quad by quad"
    assert len(outs) == 50 and max(_err(o) for o in outs) < TRACK_TOL
    (line,) = _lines(caplog, pl.SKIP_FLOOD)
    assert "input/max_detections 200" in line


# --- F4: a pause ----------------------------------------------------------------------------------

def test_a_paused_node_restarts_the_track_instead_of_jumping(world, caplog):
    p = _pipeline(world)
    outs = []
    for k in range(30):       # the poll timer runs between frames
        outs += _track(p, world, [k])
        p.poll(T0 + k / RATE + 0.05)
    last = outs[-1]
    # SIGSTOP for 10 s: the first event afterwards is the poll timer, 10 s later; then the
    # cameras' backlog (stale) and fresh frames.
    with caplog.at_level(logging.WARNING, logger="aruco_ring_localization.pipeline"):
        assert p.poll(T0 + 12.95) == [], "a pose was predicted across the pause"
        old, _ = _frame(world, 30)
        assert feed_ring_frame(p, old, now=T0 + 12.96) == []
        after = _track(p, world, range(130, 140))
    assert p.pauses == 1 and _lines(caplog, "timing/max_pause")
    assert after[0].track.decision.reason == "initialized"
    assert max(_err(o) for o in after) < TRACK_TOL
    # The step from the last pose before the pause is the robot's motion meanwhile, no more.
    step = np.hypot(*(after[0].T_map_base[:2, 3] - last.T_map_base[:2, 3]))
    moved = np.hypot(*(_truth(13.0)[:2] - _truth(last.stamp - T0)[:2]))
    assert abs(step - moved) < TRACK_TOL


def test_cameras_silent_with_the_node_running_still_predict(world):
    p = _pipeline(world)
    _track(p, world, range(20))
    preds = [p.poll(T0 + 1.9 + 0.05 * j) for j in range(1, 60)]   # 3 s of silence, timer at 20 Hz
    assert p.pauses == 0 and sum(len(o) for o in preds) > 30


# --- F5: initialpose --------------------------------------------------------------------------------

@pytest.mark.parametrize("x", [1e9, 1e300, -25.0])
def test_initialpose_outside_the_map_is_refused(world, x):
    p = _pipeline(world)
    _track(p, world, range(10))
    pose = p.filter.pose.copy()
    with pytest.raises(MeasurementError, match="outside the map"):
        p.on_initial_pose(geo.transform_from_se2(x, 4.0, 0.0), T0 + 1.0)
    assert np.array_equal(p.filter.pose, pose)
    p.on_initial_pose([3.0, 4.0, 0.0], T0 + 1.0)   # inside: accepted
    assert np.allclose(p.filter.pose, [3.0, 4.0, 0.0])


# --- F7: negative ids; every drop counted and said once per period ---------------------------------

def test_negative_ids_are_dropped_and_said(world, caplog):
    p = _pipeline(world)
    frame, now = _frame(world, 0)
    cf = frame.cameras["cam1"]
    cf.observations = cf.observations + [MarkerObservation(-5, np.array([[100.0, 100], [200, 100], [200, 200],
                                                                              [100, 200]]))]
    with caplog.at_level(logging.WARNING, logger="aruco_ring_localization.pipeline"):
        feed_ring_frame(p, frame, now=now)
    assert p.input.rejected["cam1"] == {"negative id": 1}
    assert any("negative id" in m for m in _lines(caplog, "cam1"))


def test_every_dropped_input_is_said_once_per_period_and_counted(world, caplog):
    p = _pipeline(world)
    seconds = 12.0
    n = int(seconds * RATE)
    with caplog.at_level(logging.WARNING, logger="aruco_ring_localization.pipeline"):
        for k in range(n):
            frame, now = _frame(world, k)
            p.on_detections("cam2", now + 50.0, [], now)                       # future stamp
            p.on_motion("odom", now, (float("nan"), 0.0), 0.0, now)            # NaN twist
            p.on_motion("cmd_vel", None, (99.0, 0.0), 0.0, now)                # beyond limits
            feed_ring_frame(p, frame, now=now)
    expected_lines = int(np.ceil((n - 1) / RATE / WARN_PERIOD + 1e-9))          # at 0, 5, 10 s
    for key in ("cam2.future stamp", "odom.non-finite", "cmd_vel.beyond limits"):
        assert p.warn.counts[key] == n, (key, p.warn.counts)
        assert p.warn.said[key] == expected_lines, (key, p.warn.said)
    assert len(caplog.records) == 3 * expected_lines, [r.getMessage() for r in caplog.records]


def test_the_mapper_keeps_no_age_limit_but_refuses_future_stamps(world):
    scene, ring, sim = world
    m = MappingPipeline(with_overrides(MapperConfig(), OFFLINE), ring)
    frame = sim.observe(scene.T_world_base(_truth(0.0)), T0)
    # A bag replayed without its clock: stamps far in the past of the node's clock still map ...
    assert feed_ring_frame(m, frame, now=T0 + 3600.0) == 1
    # ... but a future stamp is refused there too.
    assert m.on_detections("cam0", T0 + 7200.0, [], T0 + 3600.0) == 0
    assert m.input.skipped["cam0"] == {pl.SKIP_FUTURE_STAMP: 1}
