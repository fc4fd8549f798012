"""pipeline.py without ROS: the way in (calibration in force, sanitizing once, assembly), the time
policy (stale frames, time jumps, silent cameras), motion input, initialpose, reset, determinism,
and the mapping pipeline."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization import pipeline as pl
from aruco_ring_localization.config import with_overrides
from aruco_ring_localization.detections import MarkerObservation
from aruco_ring_localization.errors import ConfigError, MeasurementError
from aruco_ring_localization.marker_map import MarkerMap
from aruco_ring_localization.markers import MarkerSizes
from aruco_ring_localization.pipeline import (SKIP_NO_CAMERA_INFO, SKIP_NO_EXTRINSICS, LocalizationPipeline,
                                              MappingPipeline, RingInput, feed_ring_frame)
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.schemas import LocalizerConfig, MapperConfig, RingInputParams
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene
from aruco_ring_localization.throttle import ThrottledWarnings

from helpers import RING_YAML

#: The node's configuration with the ring file's calibration (no tf, no camera_info needed).
OFFLINE = {"input.use_tf": False, "input.camera_info_fallback": True}


@pytest.fixture(scope="module")
def setup():
    scene = Scene.default()
    ring = CameraRing.load(str(RING_YAML))
    sim = RingSimulator(scene, perturb_ring(ring, seed=1), pixel_noise=0.3, seed=2)
    return scene, ring, sim


def _config(**overrides) -> LocalizerConfig:
    return with_overrides(LocalizerConfig(), {**OFFLINE, **{k.replace("__", "."): v for k, v in overrides.items()}})


def _pose(t):
    return np.array([4.5 + 0.2 * t, 4.0 + 0.1 * t, geo.wrap_angle(0.3 * t)])


def _err(out, truth) -> float:
    return float(np.hypot(*(out.T_map_base[:2, 3] - truth[:2])))


def _square(cx=640.0, cy=480.0, s=40.0) -> np.ndarray:
    return np.array([[cx - s, cy - s], [cx + s, cy - s], [cx + s, cy + s], [cx - s, cy + s]])


# --- the way in ---------------------------------------------------------------------------------

def _input(ring, cameras, **params) -> RingInput:
    return RingInput(ring, RingInputParams(cameras=tuple(cameras), **params), ThrottledWarnings(lambda _m: None))


def test_camera_skipped_without_camera_info_unless_fallback(setup):
    _, ring, _ = setup
    core = _input(ring, ["cam0"], use_tf=False)
    assert core.add_detections("cam0", 1.0, [MarkerObservation(1, _square())], now=1.0) == []
    assert core.skipped["cam0"] == {SKIP_NO_CAMERA_INFO: 1}
    core_fb = _input(ring, ["cam0"], use_tf=False, camera_info_fallback=True)
    frames = core_fb.add_detections("cam0", 1.0, [MarkerObservation(1, _square())], now=1.0)
    assert len(frames) == 1 and frames[0].cameras["cam0"].model is ring["cam0"].model, frames
    assert core_fb.skipped["cam0"] == {}


def test_camera_skipped_until_extrinsics_then_ring_updated(setup):
    _, ring, _ = setup
    core = _input(ring, ["cam0", "cam1"], camera_info_fallback=True)
    core.add_detections("cam0", 1.0, [], now=1.0)
    assert core.skipped["cam0"] == {SKIP_NO_EXTRINSICS: 1}
    T = geo.compose(ring["cam0"].T_base_cam, geo.make_transform(t=[0.001, 0.0, 0.0]))
    core.set_extrinsics("cam0", T)
    assert np.allclose(core.ring["cam0"].T_base_cam, T)
    assert np.allclose(core.ring["cam1"].T_base_cam, ring["cam1"].T_base_cam)
    core.add_detections("cam0", 1.0, [], now=1.0)
    assert core.skipped["cam0"] == {SKIP_NO_EXTRINSICS: 1}, "skipped again although the extrinsics are known"
    core.set_extrinsics("cam1")  # None: the ring file's
    assert np.array_equal(core.ring["cam1"].T_base_cam, ring["cam1"].T_base_cam)


def test_silent_camera_does_not_stall_and_is_reported(setup):
    _, ring, _ = setup
    core = _input(ring, ["cam0", "cam1"], timeout=0.2, camera_info_fallback=True, use_tf=False, silent_after=0.5)
    assert core.add_detections("cam0", 5.0, [MarkerObservation(3, _square())], now=10.0) == []
    assert core.poll(10.1) == []
    out = core.poll(10.25)
    assert len(out) == 1 and out[0].missing == ["cam1"], f"got {out}"
    assert core.silent_cameras(10.25) == ["cam1"]


def test_malformed_detections_dropped_and_counted_once(setup):
    _, ring, _ = setup
    core = _input(ring, ["cam0"], camera_info_fallback=True, use_tf=False, ignore_fiducials="9")
    bad = _square()
    bad[2, 0] = np.nan
    obs = [MarkerObservation(1, bad), MarkerObservation(2, _square(300)), MarkerObservation(2, _square(900)),
           MarkerObservation(9, _square(500)), MarkerObservation(4, _square(200, 200))]
    frames = core.add_detections("cam0", 1.0, obs, now=1.0)
    kept = [o.marker_id for o in frames[0].cameras["cam0"].observations]
    assert kept == [4], f"kept {kept}"
    assert core.rejected["cam0"] == {"non-finite": 1, "duplicate id": 2, "ignored": 1}, core.rejected


def test_unknown_camera_name_is_a_config_error(setup):
    _, ring, _ = setup
    with pytest.raises(ConfigError, match="cam9"):
        _input(ring, ["cam9"])
    assert pl.resolve_camera_names(ring, ["ring/cam3", "cam1"]) == ["cam3", "cam1"]


def test_sanitizing_happens_once_for_the_whole_path(setup, monkeypatch):
    """One sanitize_observations call per camera message, none in the estimator or the map builder."""
    scene, ring, sim = setup
    calls = []
    real = pl.sanitize_observations
    monkeypatch.setattr(pl, "sanitize_observations", lambda *a, **k: calls.append(1) or real(*a, **k))
    import aruco_ring_localization.localization as loc_mod
    import aruco_ring_localization.mapping as map_mod
    assert not hasattr(loc_mod, "sanitize_observations") and not hasattr(map_mod, "sanitize_observations")
    frame = sim.observe(scene.T_world_base(_pose(0.0)), 0.0)
    p = LocalizationPipeline(_config(), ring, scene.truth_map())
    feed_ring_frame(p, frame)
    m = MappingPipeline(with_overrides(MapperConfig(), OFFLINE), ring)
    feed_ring_frame(m, frame)
    assert len(calls) == 2 * len(frame.cameras), f"{len(calls)} sanitize calls for 2 x {len(frame.cameras)} messages"


# --- localization -----------------------------------------------------------------------------------

def test_follows_then_recovers_from_kidnap_then_resets_on_time_jump(setup):
    scene, ring, sim = setup
    p = LocalizationPipeline(_config(), ring, scene.truth_map())
    for k in range(30):
        t = 0.1 * k
        truth = _pose(t)
        assert p.on_motion("cmd_vel", None, (0.22, 0.0), 0.3, t) == []
        (out,) = feed_ring_frame(p, sim.observe(scene.T_world_base(truth), t))
        assert _err(out, truth) < 0.03, f"t={t:.1f}: tracking error {_err(out, truth) * 100:.2f} cm"
    # Kidnap: the robot is carried 1.5 m away and stops.
    kidnapped = np.array([6.0, 5.0, 1.0])
    reasons = []
    for k in range(30, 45):
        (out,) = feed_ring_frame(p, sim.observe(scene.T_world_base(kidnapped), 0.1 * k))
        reasons.append(out.track.decision.reason)
    assert "jump" in reasons and "reinitialized" in reasons, f"gate decisions after the kidnap: {reasons}"
    assert _err(out, kidnapped) < 0.02, f"not recovered: {out.T_map_base[:2, 3]}"
    # Bag loop: time goes back to 0.
    (out,) = feed_ring_frame(p, sim.observe(scene.T_world_base(_pose(0.0)), 0.0))
    assert out.track.time_jump and p.time_jumps == 1
    assert _err(out, _pose(0.0)) < 0.02, f"after the time jump: {out.T_map_base[:2, 3]}"


@pytest.mark.parametrize("reason, key", [("jump", "gate"), ("ambiguous", "ambiguous"), ("pending", None)])
def test_a_rejected_measurement_is_reported_for_what_it_is(setup, monkeypatch, reason, key):
    """A jump is the gate's; an ambiguous pose is said to be ambiguous (not "rejected by the gate,
    jump 0.00 m, allowed inf m"); the 6-DOF tracker waiting for its first consistent poses says nothing."""
    from aruco_ring_localization.gating import GateDecision
    scene, ring, sim = setup
    p = LocalizationPipeline(_config(), ring, scene.truth_map())
    said = []
    monkeypatch.setattr(p, "warn", lambda k, message, now=None: said.append((k, message)))
    real = p._track

    def track(frame):
        out = real(frame)
        out.decision = (GateDecision(False, reason, 0.7, 0.1, 0.2, 0.05) if reason == "jump"
                        else GateDecision(False, reason))
        return out

    monkeypatch.setattr(p, "_track", track)
    feed_ring_frame(p, sim.observe(scene.T_world_base(_pose(0.0)), 0.0))
    assert [k for k, _ in said if k in ("gate", "ambiguous")] == ([key] if key else []), said
    if key == "gate":
        assert "jump 0.70 m" in said[0][1] and "allowed 0.20 m" in said[0][1]
    if key == "ambiguous":
        assert "inf" not in said[0][1] and "ambiguous" in said[0][1]


def test_no_markers_predicts_only(setup):
    scene, ring, sim = setup
    p = LocalizationPipeline(_config(), ring, scene.truth_map())
    T = scene.T_world_base(_pose(0.0))
    feed_ring_frame(p, sim.observe(T, 0.0))
    c0 = np.trace(p.filter.covariance)
    empty = sim.observe(T, 0.5)
    for f in empty.cameras.values():
        f.observations.clear()
    (out,) = feed_ring_frame(p, empty)
    assert out.track.decision is None and not out.track.localization.ok
    assert np.trace(out.track.covariance) > c0


def test_stale_and_overtaken_frames_are_dropped(setup):
    scene, ring, sim = setup
    p = LocalizationPipeline(_config(timing__max_frame_age=0.5), ring, scene.truth_map())
    T = scene.T_world_base(_pose(0.0))
    frame = sim.observe(T, 10.0)
    assert feed_ring_frame(p, frame, now=10.6) == [], "a frame 0.6 s old went through"
    # Refused message by message where they enter (the stamp policy), before any assembly.
    assert sum(p.input.skipped[c].get(pl.SKIP_STALE_STAMP, 0) for c in frame.cameras) == len(frame.cameras)
    assert p.dropped_stale == 0 and p.frames == 0
    assert len(feed_ring_frame(p, sim.observe(T, 11.0), now=11.4)) == 1
    # Two incomplete ring frames flushed at once: only the newer one is processed.
    for stamp in (12.0, 12.1):
        for name in ring.names[:3]:
            assert p.on_detections(name, stamp, sim.observe(T, stamp).cameras[name].observations, 12.2) == []
    out = p.flush(12.2)
    assert len(out) == 1 and out[0].stamp == pytest.approx(12.1), [o.stamp for o in out]
    assert p.dropped_stale == 1 and p.frames == 2


def test_every_camera_silent_gives_predictions_with_growing_covariance(setup):
    scene, ring, sim = setup
    p = LocalizationPipeline(_config(input__silent_after=1.0), ring, scene.truth_map())
    for k in range(5):
        feed_ring_frame(p, sim.observe(scene.T_world_base(_pose(0.1 * k)), 0.1 * k))
    assert p.poll(1.0) == [], "predicted before the cameras were silent for input/silent_after"
    outs = [p.poll(1.5), p.poll(2.0)]
    assert all(len(o) == 1 and o[0].predicted_only for o in outs), outs
    assert outs[0][0].stamp == 1.5 and outs[1][0].stamp == 2.0
    assert np.trace(outs[1][0].covariance[:2, :2]) > np.trace(outs[0][0].covariance[:2, :2])
    assert p.poll(2.0) == [], "a paused clock must not publish again"
    assert p.predicted_only == 2


def test_motion_input_widens_the_gate_and_goes_stale(setup):
    scene, ring, sim = setup
    truth0 = np.array([5.0, 4.2, 0.2])
    moved = truth0 + [0.35, 0.0, 0.0]  # 35 cm in 0.1 s: only possible at speed

    def run(speed_stamp):
        p = LocalizationPipeline(_config(gate__sigma_factor=0.0), ring, scene.truth_map())
        for k in range(10):
            feed_ring_frame(p, sim.observe(scene.T_world_base(truth0), 0.1 * k))
        if speed_stamp is not None:
            p.on_motion("odom", speed_stamp, (3.0, 0.0), 0.0, 1.0)
        (out,) = feed_ring_frame(p, sim.observe(scene.T_world_base(moved), 1.0))
        return out.track.decision.reason

    assert run(None) == "jump"
    assert run(0.95) == "accepted", "a fresh 3 m/s odometry twist should allow a 35 cm step in 0.1 s"
    assert run(0.2) == "jump", "an odometry twist 0.8 s old (timing/motion_timeout 0.5 s) must count as zero"


def test_motion_input_rejects_nonsense(setup, caplog):
    scene, ring, _ = setup
    p = LocalizationPipeline(_config(), ring, scene.truth_map())
    with caplog.at_level(logging.WARNING, logger="aruco_ring_localization.pipeline"):
        for k in range(20):
            p.on_motion("cmd_vel", None, (float("nan"), 0.0), 0.0, 0.01 * k)
    assert p._speeds(0.2) == (0.0, 0.0)
    assert sum("non-finite" in r.message for r in caplog.records) == 1, caplog.text  # throttled: one line
    with pytest.raises(ValueError, match="motion source"):
        p.on_motion("imu", None, (0.0, 0.0), 0.0, 0.0)


def test_initial_pose_restarts_the_track_there(setup):
    scene, ring, sim = setup
    p = LocalizationPipeline(_config(), ring, scene.truth_map())
    truth = np.array([5.5, 4.0, 0.5])
    for k in range(5):
        feed_ring_frame(p, sim.observe(scene.T_world_base(truth), 0.1 * k))
    assert p.on_initial_pose(geo.transform_from_se2(7.0, 3.0, 1.0), now=0.45) == []
    assert np.allclose(p.filter.pose, [7.0, 3.0, 1.0])
    # The measurements disagree with the given pose: the gate re-initialises on them (no lock-out).
    outs = [feed_ring_frame(p, sim.observe(scene.T_world_base(truth), 0.5 + 0.1 * k))[0] for k in range(6)]
    reasons = [o.track.decision.reason for o in outs]
    assert reasons == ["jump"] * 4 + ["reinitialized", "accepted"], reasons
    assert _err(outs[-1], truth) < 0.02
    with pytest.raises(MeasurementError):
        p.on_initial_pose([np.nan, 0.0, 0.0], now=1.0)


def test_reset_makes_the_next_measurement_initialise(setup):
    scene, ring, sim = setup
    p = LocalizationPipeline(_config(), ring, scene.truth_map())
    T = scene.T_world_base(_pose(0.0))
    feed_ring_frame(p, sim.observe(T, 0.0))
    assert feed_ring_frame(p, sim.observe(T, 0.1))[0].track.decision.reason == "accepted"
    p.reset()
    assert not p.filter.initialized
    assert feed_ring_frame(p, sim.observe(T, 0.2))[0].track.decision.reason == "initialized"


def test_the_same_events_give_the_same_poses_exactly(setup):
    scene, ring, sim = setup
    frames = [sim.observe(scene.T_world_base(_pose(0.1 * k)), 0.1 * k) for k in range(15)]
    runs = []
    for _ in range(2):
        p = LocalizationPipeline(_config(), ring, scene.truth_map())
        out = []
        for k, f in enumerate(frames):
            p.on_motion("cmd_vel", None, (0.2, 0.0), 0.3, 0.1 * k)
            out += feed_ring_frame(p, f, flush=False)
            out += p.poll(0.1 * k + 0.05)
        runs.append(np.array([np.r_[o.stamp, o.T_map_base.ravel(), o.covariance.ravel()] for o in out]))
    assert runs[0].shape == (15, 1 + 16 + 36) and np.array_equal(runs[0], runs[1])


def test_warnings_are_throttled_and_counted(setup, caplog):
    scene, ring, sim = setup
    p = LocalizationPipeline(with_overrides(LocalizerConfig(), {"input.use_tf": False}), ring, scene.truth_map())
    frame = sim.observe(scene.T_world_base(_pose(0.0)), 0.0)
    with caplog.at_level(logging.WARNING, logger="aruco_ring_localization.pipeline"):
        for k in range(50):  # 50 messages in 2.5 s of the node's clock, no camera_info
            p.on_detections("cam0", 0.05 * k, frame.cameras["cam0"].observations, 0.05 * k)
    lines = [r for r in caplog.records if "no camera_info" in r.message]
    assert len(lines) == 1, [r.message for r in lines]
    assert p.warn.counts["cam0.no camera_info"] == 50


def test_refined_extrinsics_of_the_map_are_the_fallback(setup):
    scene, ring, _ = setup
    m = scene.truth_map()
    T = geo.compose(ring["cam2"].T_base_cam, geo.make_transform(t=[0.004, 0.0, 0.0]))
    m.ring_extrinsics = {"cam2": T}
    m.ring_base_frame = ring.base_frame
    p = LocalizationPipeline(_config(), ring, m)
    assert np.allclose(p.ring["cam2"].T_base_cam, T) and np.allclose(p.localizer.ring["cam2"].T_base_cam, T)
    with pytest.raises(ConfigError, match="no markers"):
        LocalizationPipeline(_config(), ring, type(m)([], frame_id="map"))


# --- mapping ----------------------------------------------------------------------------------------

def test_mapping_pipeline_drops_malformed_detections_with_a_warning(setup, caplog):
    scene, ring, _ = setup
    sim = RingSimulator(scene, ring, pixel_noise=0.0, seed=0)
    m = MappingPipeline(with_overrides(MapperConfig(), OFFLINE), ring)
    frame = sim.observe(Scene.T_world_base(scene.mapping_pose))
    cam, cf = next((n, f) for n, f in frame.cameras.items() if len(f.observations) >= 1)
    good = cf.observations[0]
    nan = good.corners.copy()
    nan[1, 1] = np.nan
    cf.observations = [MarkerObservation(good.marker_id, nan), MarkerObservation(4000, good.corners),
                       MarkerObservation(4000, good.corners + 50.0)] + cf.observations[1:]
    with caplog.at_level(logging.WARNING, logger="aruco_ring_localization.pipeline"):
        assert feed_ring_frame(m, frame) == 1
    assert m.input.rejected[cam] == {"non-finite": 1, "duplicate id": 2}, m.input.rejected
    assert "non-finite" in caplog.text and "duplicate id" in caplog.text, caplog.text
    assert 4000 not in m.build("paper")


def test_mapping_pipeline_gives_the_builder_the_extrinsics_in_force(setup):
    scene, ring, _ = setup
    m = MappingPipeline(with_overrides(MapperConfig(), {"input.camera_info_fallback": True}), ring)
    T = geo.compose(ring["cam1"].T_base_cam, geo.make_transform(t=[0.0, 0.003, 0.0]))
    m.on_extrinsics("cam1", T)
    assert np.array_equal(m.builder.ring["cam1"].T_base_cam, T)
    assert m.builder.sizes(7) == MarkerSizes(0.2)(7)


@dataclass(frozen=True)
class _Params:
    map_file: str = field(default="", metadata={"doc": "where to save"})
    slop: float = 0.03
    count: int = 3
    enabled: bool = True
    cameras: tuple = ()


def test_flat_params_coercion_and_errors():
    from aruco_ring_localization.ros.params import params_from_dict

    p = params_from_dict(_Params, {"slop": 1, "cameras": "cam0, cam1", "enabled": False})
    assert p.slop == 1.0 and isinstance(p.slop, float)
    assert p.cameras == ("cam0", "cam1") and p.enabled is False and p.count == 3
    with pytest.raises(ConfigError, match="enabled"):
        params_from_dict(_Params, {"enabled": "false"})
    with pytest.raises(ConfigError, match="count"):
        params_from_dict(_Params, {"count": 2.5})


def test_save_answer_names_the_map_frame_once_and_the_robot_pose_is_the_station(setup, tmp_path):
    """~save_map's answer (issue 15, item 6: it said 'fixed to marker 777' and '(reference 580)' in one
    line) and the robot's pose the mapper puts on tf (item 5)."""
    scene, ring, _ = setup
    sim = RingSimulator(scene, ring, pixel_noise=0.2, seed=3)
    m = MappingPipeline(with_overrides(MapperConfig(), {**OFFLINE, "map.method": "paper"}), ring)
    assert m.robot_pose(MarkerMap([], frame_id="map")) is None, "no frame yet: no pose"
    pose = np.array(scene.mapping_pose)
    for k in range(5):
        frame = sim.observe(Scene.T_world_base(pose), stamp=0.1 * k)
        feed_ring_frame(m, frame)
    path = str(tmp_path / "map.yaml")
    saved = m.save(path)
    text = m.format_saved(saved, path)
    assert text.startswith(f"saved {len(saved)} markers (paper) to {path}; map frame on marker {saved.reference_marker}")
    assert "reference " not in text and "fixed to" not in text, text
    assert "WARNING" not in text, "every detected marker is mapped from the plate's centre"
    stamp, T_map_base = m.robot_pose(saved)
    assert stamp == pytest.approx(0.4)
    # in the robot's frame, every mapped marker is where it truly is (the map frame is the map's own)
    truth = {sm.marker_id: sm.T_world_marker for sm in scene.markers}
    T_base_world = geo.inverse(Scene.T_world_base(pose))
    for e in saved:
        seen = geo.inverse(T_map_base) @ e.T_map_marker
        true = T_base_world @ truth[e.marker_id]
        assert np.linalg.norm(seen[:2, 3] - true[:2, 3]) < 0.03, (e.marker_id, seen[:3, 3], true[:3, 3])


def test_camera_estimates_read_late_are_those_of_their_frame(setup):
    """The per-camera estimates are computed when first read (issue 16): read after later frames
    have gone through, they are the same numbers as read at once, and a copy or a pickle is a dict."""
    import copy
    import pickle

    scene, ring, sim = setup
    frames = [sim.observe(scene.T_world_base(_pose(0.1 * k)), 0.1 * k) for k in range(12)]
    at_once, later = [], []
    for read_now, sink in ((True, at_once), (False, later)):
        p = LocalizationPipeline(_config(), ring, scene.truth_map())
        outs = []
        for k, f in enumerate(frames):
            p.on_motion("cmd_vel", None, (0.2, 0.0), 0.3, 0.1 * k)
            (out,) = feed_ring_frame(p, f)
            outs.append(out)
            if read_now:
                sink.append({n: T.copy() for n, T in out.camera_estimates.items()})
        if not read_now:
            sink += [{n: T.copy() for n, T in o.camera_estimates.items()} for o in outs]
    assert len(at_once) == len(later) == len(frames)
    assert sum(len(e) for e in at_once) >= 2 * len(frames), "too few camera estimates to compare"
    for a, b in zip(at_once, later):
        assert sorted(a) == sorted(b)
        for n in a:
            assert np.array_equal(a[n], b[n]), n
    est = outs[-1].track.localization.estimates
    for c in (copy.copy(est), copy.deepcopy(est), pickle.loads(pickle.dumps(est))):
        assert type(c) is dict and sorted(c) == sorted(est)
