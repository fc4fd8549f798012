"""mapping_odometry's per_message noise model (TagSLAM's odometry noise): a sigma per odometry
message, summed over the messages a link between two stations spans."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.errors import ConfigError
from aruco_ring_localization.mapping_odometry import MappingOdometryOptions, OdometryTrack


def _track(accelerate_at: float = 1.0):
    """Odometry at 10 Hz moving along x at 0.5 m/s, turning at 0.2 rad/s, speeding up to 1 m/s at
    ``accelerate_at`` s."""
    stamps = np.round(np.arange(0.0, 2.001, 0.1), 6)
    x = np.where(stamps <= accelerate_at, 0.5 * stamps, 0.5 * accelerate_at + 1.0 * (stamps - accelerate_at))
    poses = np.stack([geo.make_transform(geo.rot_z(0.2 * t), [xi, 0.0, 0.0]) for t, xi in zip(stamps, x)])
    return stamps, OdometryTrack(stamps, poses)


def test_a_message_sigma_is_its_departure_from_constant_velocity_clamped():
    stamps, track = _track()
    opts = MappingOdometryOptions(topic="odom", noise_model="per_message", message_acceleration=1.0,
                                  message_acceleration_max=30.0, message_angular_acceleration=0.5)
    var = track.message_variances(np.eye(4), opts)
    dt = 0.1
    assert var[0].tolist() == [0.0, 0.0]
    # First motion: TagSLAM starts from zero velocity, so its whole step departs (0.05 m; 0.02 rad).
    assert np.sqrt(var[1, 0]) == pytest.approx(0.05, rel=1e-3)
    assert np.sqrt(var[1, 1]) == pytest.approx(0.02, rel=1e-3)
    # Constant velocity: the floor, message_acceleration x dt^2 (message_angular_acceleration's for the turn).
    assert np.sqrt(var[5, 0]) == pytest.approx(1.0 * dt ** 2, rel=1e-6)
    assert np.sqrt(var[5, 1]) == pytest.approx(0.5 * dt ** 2, rel=1e-6)
    # Speeding up from 0.5 to 1 m/s after t = 1 s: the step to 1.1 s departs by 0.05 m (the turn
    # changes its direction a little), the next one is at constant velocity again.
    k = int(np.argmin(np.abs(stamps - 1.1)))
    assert np.sqrt(var[k, 0]) == pytest.approx(0.05, rel=0.02)
    assert np.sqrt(var[k + 1, 0]) == pytest.approx(1.0 * dt ** 2, rel=1e-6)
    # The ceiling: message_acceleration_max x dt^2.
    tight = MappingOdometryOptions(topic="odom", noise_model="per_message", message_acceleration=1.0,
                                   message_acceleration_max=2.0)
    assert np.sqrt(track.message_variances(np.eye(4), tight)[k, 0]) == pytest.approx(2.0 * dt ** 2, rel=1e-6)


def test_fixed_noise_replaces_the_adaptive_one_only_with_both():
    _, track = _track()
    both = MappingOdometryOptions(topic="odom", noise_model="per_message", message_translation_noise=0.02,
                                  message_rotation_noise=0.01)
    var = track.message_variances(np.eye(4), both)
    assert np.allclose(var[1:, 0], 0.02 ** 2) and np.allclose(var[1:, 1], 0.01 ** 2)
    one = MappingOdometryOptions(topic="odom", noise_model="per_message", message_translation_noise=0.02)
    assert not np.allclose(track.message_variances(np.eye(4), one)[1:, 0], 0.02 ** 2)


def test_a_link_sums_the_messages_it_spans():
    stamps, track = _track()
    opts = MappingOdometryOptions(topic="odom", noise_model="per_message", message_acceleration=1.0,
                                  message_angular_acceleration=0.5, robust_scale=0.0)
    X = geo.make_transform(geo.rot_z(0.3), [0.1, 0.05, 0.0])      # the odometry's body off the base frame
    var = track.message_variances(X, opts)
    f = track.links({0: 0.3, 1: 0.8, 2: 1.5}, opts)
    for k, (a, b) in enumerate([(0.3, 0.8), (0.8, 1.5)]):
        inside = (stamps > a + 1e-9) & (stamps <= b + 1e-9)
        assert f.sigma[k, 3] == pytest.approx(np.sqrt(var[inside, 0].sum()), rel=1e-6)
        assert f.sigma[k, 0] == pytest.approx(np.sqrt(var[inside, 1].sum()), rel=1e-6)
    # A station between two messages takes the part of the message's interval it spans (plus the
    # interpolation's own term, as in the random-walk model).
    half = track.links({0: 0.3, 1: 0.35}, opts)
    it = opts.max_acceleration * 0.05 * 0.05 / 2
    assert half.sigma[0, 3] == pytest.approx(np.sqrt(0.5 * var[4, 0] + it ** 2), rel=1e-6)
    # The random-walk model of the same links is another noise.
    rw = track.links({0: 0.3, 1: 0.8, 2: 1.5}, MappingOdometryOptions(topic="odom", robust_scale=0.0))
    assert not np.allclose(rw.sigma, f.sigma)


def test_bad_noise_options_are_refused():
    with pytest.raises(ConfigError, match="noise_model"):
        MappingOdometryOptions(noise_model="tagslam")
    with pytest.raises(ConfigError, match="message_acceleration"):
        MappingOdometryOptions(message_acceleration=0.0)
    with pytest.raises(ConfigError, match="message_rotation_noise"):
        MappingOdometryOptions(message_rotation_noise=-1.0)


def test_jumps_are_judged_on_the_steps_not_on_the_positions():
    """A smooth turn at constant speed far from the odom frame's origin has no jump (the steps are
    equal in the body frame); one step displaced by 0.3 m is one, of that size less the allowance.
    (A product of the 4x4 poses' transposes puts R^T t, the position, where the step belongs, and
    flags every message of a turn 20 m from the origin.)"""
    stamps = np.arange(0.0, 3.001, 0.05)
    centre = np.array([20.0, 5.0, 0.0])
    poses = np.stack([geo.make_transform(geo.rot_z(0.3 * t), centre + [0.5 * np.cos(0.3 * t), 0.5 * np.sin(0.3 * t), 0])
                      for t in stamps])
    track = OdometryTrack(stamps, poses)
    assert np.all(track.jumps(5.0, 5.0) == 0.0)
    poses[30, :3, 3] += [0.3, 0.0, 0.0]
    j = OdometryTrack(stamps, poses).jumps(5.0, 5.0)
    assert np.count_nonzero(j[:, 0]) >= 1 and j[30, 0] == pytest.approx(0.3 - 5.0 * 0.05 ** 2, abs=0.01)


def _fast_track(rate: float = 30.0, seconds: float = 2.0):
    """Odometry at ``rate`` Hz at constant velocity along x (0.5 m/s) turning at 0.2 rad/s."""
    stamps = np.round(np.arange(0.0, seconds + 1e-9, 1.0 / rate), 9)
    poses = np.stack([geo.make_transform(geo.rot_z(0.2 * t), [0.5 * t, 0.0, 0.0]) for t in stamps])
    return stamps, OdometryTrack(stamps, poses)


def test_sampled_track_is_the_interpolated_odometry():
    _, track = _fast_track()
    at = [0.0, 0.01, 0.5, 0.51234, 1.9999, 2.0, 2.5, -0.1]
    sampled = track.sampled(at, max_gap=0.5)
    assert len(sampled) == 6                          # 2.5 and -0.1 are outside the track
    t, P, _ = sampled._sorted()
    for s, T in zip(t, P):
        assert np.allclose(T, track.pose_at(float(s), 0.5), atol=1e-12)
    # A stamp in a gap longer than max_gap is left out.
    gappy = OdometryTrack([0.0, 2.0], np.stack([np.eye(4), np.eye(4)]))
    assert len(gappy.sampled([0.0, 1.0, 2.0], max_gap=0.5)) == 2


def test_frames_sampling_judges_one_message_per_frame():
    """TagSLAM pairs one odometry message with each frame: a 30 Hz odometry under 5 Hz frames is
    judged on the 5 Hz steps (the floor a x dt^2 with dt = 0.2 s), not summed over six 1/30 s steps
    (a link sqrt(6) x a / 900: 15x tighter)."""
    _, track = _fast_track(rate=30.0)
    frames = np.round(np.arange(0.0, 2.0 + 1e-9, 0.2), 9)
    stations = {k: float(t) for k, t in enumerate(frames[2:8:2])}         # 0.4, 0.8, 1.2 s
    base = dict(topic="odom", noise_model="per_message", message_acceleration=1.0, message_angular_acceleration=0.5,
                robust_scale=0.0)
    msgs = track.links(stations, MappingOdometryOptions(**base))
    per_frame = track.links(stations, MappingOdometryOptions(**base, message_sampling="frames"), frame_stamps=frames)
    assert np.allclose(msgs.T_ij, per_frame.T_ij, atol=1e-9)
    # Each link spans two frame steps of 0.2 s at constant velocity: two floors.
    assert per_frame.sigma[0, 3] == pytest.approx(np.sqrt(2) * 1.0 * 0.2 ** 2, rel=1e-6)
    assert per_frame.sigma[0, 0] == pytest.approx(np.sqrt(2) * 0.5 * 0.2 ** 2, rel=1e-6)
    # ... where every 30 Hz message is one floor of its own: twelve of (1/30)^2.
    assert msgs.sigma[0, 3] == pytest.approx(np.sqrt(12) * 1.0 / 30 ** 2, rel=1e-6)
    # The frames themselves are the messages: the same as an odometry that came at the frames.
    at_frames = OdometryTrack(frames, np.stack([track.pose_at(float(t), 0.5) for t in frames]))
    same = at_frames.links(stations, MappingOdometryOptions(**base))
    assert np.allclose(per_frame.sigma, same.sigma, rtol=1e-9)


def test_frames_sampling_changes_nothing_for_an_odometry_at_the_frames():
    stamps, track = _fast_track(rate=20.0)
    stations = {0: 0.25, 1: 0.6, 2: 1.45}
    base = dict(topic="odom", noise_model="per_message", message_acceleration=1.0, robust_scale=0.0)
    a = track.links(stations, MappingOdometryOptions(**base))
    b = track.links(stations, MappingOdometryOptions(**base, message_sampling="frames"), frame_stamps=stamps)
    assert np.allclose(a.sigma, b.sigma, rtol=1e-9) and np.allclose(a.T_ij, b.T_ij, atol=1e-12)
    with pytest.raises(ConfigError, match="message_sampling"):
        MappingOdometryOptions(message_sampling="odometry")


def test_the_builder_judges_its_odometry_at_every_frame_it_was_given(ring, scene):
    """MapBuilder with ``message_sampling: frames``: the messages are the odometry at every ring frame
    added (also those that made no station), so its links are those of the track sampled there; the
    default judges the 30 Hz messages themselves (tighter)."""
    from aruco_ring_localization.mapping import MapBuilder, MappingOptions
    from aruco_ring_localization.markers import MarkerSizes
    from aruco_ring_localization.simulation.ring_sim import RingSimulator
    from aruco_ring_localization.simulation.scene import Scene

    sim = RingSimulator(scene, ring, pixel_noise=0.0, seed=0)
    x0, y0, yaw0 = scene.mapping_pose

    def pose(t: float):
        return (x0 + 0.25 * t, y0, yaw0 + 0.1 * t)

    t_odo = np.round(np.arange(0.0, 3.0 + 1e-9, 1.0 / 30.0), 9)
    odo = np.stack([Scene.T_world_base(pose(t)) for t in t_odo])
    t_frames = np.round(np.arange(0.0, 2.81, 0.2), 9)
    out = {}
    for sampling in ("messages", "frames"):
        opts = MappingOptions(min_station_motion_px=40.0, keep_linking_frames=False,
                              odometry=MappingOdometryOptions(topic="odom", robust_scale=0.0,
                                                              message_sampling=sampling))
        b = MapBuilder(ring, MarkerSizes(0.2), options=opts)
        b.set_odometry(t_odo, odo)
        kept = [b.add_frame(sim.observe(Scene.T_world_base(pose(t)), stamp=float(t))) for t in t_frames]
        stations = list(range(b.station_count))
        assert len(stations) >= 2 and kept.count(-1) > 0       # some frames made no station
        out[sampling] = (b._odometry_factors(stations, {s: s for s in stations}), b)
    frames_f, b = out["frames"]
    assert np.allclose(b._frame_stamps, t_frames)
    expect = b.odometry.links({s: b._station_stamps[s] for s in range(b.station_count)}, b.options.odometry,
                              frame_stamps=t_frames)
    assert np.allclose(frames_f.sigma, expect.sigma, rtol=1e-9)
    # Sampled at 5 Hz the floor is 5 x 0.2^2 per frame step; the 30 Hz messages sum six of 5 x (1/30)^2.
    assert np.all(frames_f.sigma[:, 3] > 5.0 * out["messages"][0].sigma[:, 3])
