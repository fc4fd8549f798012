"""The smoothed trajectory (smoother.py) on a simulated walk: a known map, noisy corners, an
odometry with a known bias and noise; the smoother against the per-frame estimate and against a
dense reference solve of the same problem."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import least_squares

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.bundle_adjustment import BAOptions, BAProblem, _Model, bundle_adjust
from aruco_ring_localization.camera import CameraModel
from aruco_ring_localization.detections import CameraFrame, MarkerObservation, RingFrame
from aruco_ring_localization.errors import ConfigError, GeometryError
from aruco_ring_localization.localization import LocalizationParams, RingLocalizer
from aruco_ring_localization.mapping_odometry import MappingOdometryOptions, OdometryTrack
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap
from aruco_ring_localization.markers import marker_corners
from aruco_ring_localization.ring import CameraRing, RingCamera
from aruco_ring_localization.smoother import SmootherOptions, odometry_track, smooth_trajectory, smoother_problem

SIZE = 0.15
PIXEL_NOISE = 0.8
RATE = 10.0           # ring frames per second
ODOM_RATE = 20.0      # odometry messages per second
BLACKOUT = range(30, 38)   # ring frames with no marker in view


def _ring() -> CameraRing:
    model = CameraModel(np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]]), np.zeros(5), "plumb_bob", 640, 480)
    # Optical axes in the base frame: x_opt = -y, y_opt = -z, z_opt = +x (looking forward), then a yaw.
    R_opt = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    cams = []
    for k, (yaw, y) in enumerate([(0.25, 0.1), (-0.25, -0.1)]):
        T = geo.make_transform(geo.rotation_from_rvec([0, 0, yaw]) @ R_opt, [0.1, y, 0.2])
        cams.append(RingCamera(f"cam{k}", f"cam{k}_optical", model, T, f"cam{k}"))
    return CameraRing(cams, "base_link")


def _map() -> MarkerMap:
    # A wall at x = 6 m, markers facing -x (their z axis): x_m = -y, y_m = +z.
    R = np.array([[0.0, 0, -1], [-1, 0, 0], [0, 1, 0]])
    entries = []
    for k, (y, z) in enumerate([(y, z) for y in (-2.0, -1.0, 0.0, 1.0, 2.0) for z in (0.4, 1.1)]):
        entries.append(MarkerEntry(k, geo.make_transform(R, [6.0, y, z]), SIZE))
    return MarkerMap(entries)


def _truth(t: float) -> np.ndarray:
    """The rig's true pose at t (a walk towards the wall with a sway, a little roll and pitch)."""
    R = geo.rotation_from_rvec([0.03 * np.sin(1.3 * t), 0.02 * np.sin(0.9 * t), 0.2 * np.sin(0.7 * t)])
    return geo.make_transform(R, [0.5 * t, 0.4 * np.sin(0.8 * t), 0.3 + 0.02 * np.sin(2.0 * t)])


def _frames(rng, ring, marker_map, n: int):
    frames = []
    for k in range(n):
        t = k / RATE
        T = _truth(t)
        cameras = {}
        for c in ring:
            obs = []
            if k not in BLACKOUT:
                for e in marker_map:
                    p = geo.transform_points(geo.inverse(T @ c.T_base_cam) @ e.T_map_marker, marker_corners(SIZE))
                    if np.any(p[:, 2] < 0.5):
                        continue
                    px = c.model.project(p)
                    if not np.all(c.model.in_image(px, margin=5.0)):
                        continue
                    obs.append(MarkerObservation(e.marker_id, px + rng.normal(0, PIXEL_NOISE, px.shape)))
                # Few markers per image: the per-frame estimate is weak, as on a real walk.
                if len(obs) > 2:
                    obs = [obs[i] for i in rng.choice(len(obs), 2, replace=False)]
            cameras[c.name] = CameraFrame(c.name, t, obs, c.model)
        frames.append(RingFrame(t, cameras))
    return frames


#: The odometry body's pose in the base frame (TagSLAM's T_body_odom): not the identity, so that a
#: smoother that forgot it would be off.
X_BODY = geo.make_transform(geo.rotation_from_rvec([0.0, 0.1, 1.2]), [0.05, -0.02, 0.1])


def _odometry(rng, n_frames: int):
    """The odometry body's poses at ODOM_RATE: the true increments of that body with a 3 % scale
    bias, a yaw bias of 0.02 rad/m and white noise, integrated from an arbitrary odom frame."""
    n = int((n_frames - 1) / RATE * ODOM_RATE) + 1
    stamps = np.arange(n) / ODOM_RATE
    P = [geo.make_transform(geo.rotation_from_rvec([0.1, -0.2, 0.5]), [3.0, 1.0, 0.0])]
    for k in range(1, n):
        D = geo.inverse(_truth(stamps[k - 1]) @ X_BODY) @ _truth(stamps[k]) @ X_BODY
        step = float(np.linalg.norm(D[:3, 3]))
        bias = geo.make_transform(geo.rotation_from_rvec([0, 0, 0.02 * step]), np.zeros(3))
        D = geo.make_transform(D[:3, :3], 1.03 * D[:3, 3]) @ bias
        D = geo.se3_perturb(D, np.r_[rng.normal(0, 0.002, 3), rng.normal(0, 0.002, 3)])
        P.append(P[-1] @ D)
    return stamps, np.stack(P)


def _odometry_options() -> MappingOdometryOptions:
    rvec, tvec = geo.rvec_tvec_from_transform(X_BODY)
    return MappingOdometryOptions(topic="odom", base_to_odom=tuple(float(v) for v in np.r_[tvec, rvec]),
                                  noise_model="random_walk", translation_noise=0.02, rotation_noise=0.02,
                                  rotation_per_metre=0.02)


@pytest.fixture(scope="module")
def walk():
    rng = np.random.default_rng(11)
    ring, marker_map = _ring(), _map()
    frames = _frames(rng, ring, marker_map, 60)
    stamps, poses = _odometry(rng, len(frames))
    localizer = RingLocalizer(ring, marker_map, LocalizationParams(fusion="joint"))
    per_frame = []
    for f in frames:
        r = localizer.process(f)
        per_frame.append(r.T_map_base if r.ok else None)
    return ring, marker_map, frames, OdometryTrack(stamps, poses), per_frame


def _errors_mm(poses, stamps):
    return np.array([1000.0 * geo.pose_distance(_truth(t), T)[0] for t, T in zip(stamps, poses)])


def test_smoother_beats_the_per_frame_estimate_and_bridges_the_blackout(walk):
    ring, marker_map, frames, odo, per_frame = walk
    res = smooth_trajectory(frames, ring, marker_map, odo, _odometry_options(), per_frame,
                            SmootherOptions(pixel_noise=PIXEL_NOISE))
    assert len(res.stamps) == len(frames), f"{len(res.stamps)} of {len(frames)} frames smoothed"
    assert not np.any(res.observed[list(BLACKOUT)]), "the blackout frames see no marker"
    seen = [k for k, T in enumerate(per_frame) if T is not None]
    assert len(seen) >= 45, f"the per-frame estimator posed only {len(seen)} frames"
    e_frame = _errors_mm([per_frame[k] for k in seen], [frames[k].stamp for k in seen])
    e_smooth = _errors_mm(res.T_map_base, res.stamps)
    e_seen = e_smooth[seen]
    assert np.median(e_seen) < 0.7 * np.median(e_frame), \
        f"smoothed median {np.median(e_seen):.2f} mm vs per-frame {np.median(e_frame):.2f} mm"
    assert np.max(e_seen) < np.max(e_frame), f"smoothed max {np.max(e_seen):.2f} vs per-frame {np.max(e_frame):.2f}"
    # Odometry-only poses: the biased odometry over 0.8 s, held at both ends by the markers.
    e_dark = e_smooth[list(BLACKOUT)]
    assert np.max(e_dark) < 3.0 * np.median(e_frame) + 5.0, \
        f"blackout frames {np.max(e_dark):.2f} mm max (per-frame median {np.median(e_frame):.2f} mm)"
    assert res.links == len(frames) - 1
    assert res.rms_px_after < 1.5 * PIXEL_NOISE, f"RMS {res.rms_px_after:.3f} px"


def test_smoother_equals_a_dense_reference_solve(walk):
    """The sparse solver's optimum is the optimum: the same residuals solved by scipy's dense
    least squares (its Huber loss per row at the same scale) from the same start give the same
    poses. (Every odometry link lies inside the Huber scale there, where the per-link and the
    per-row losses are both the quadratic one.)"""
    ring, marker_map, frames, odo, per_frame = walk
    built = smoother_problem(frames, ring, marker_map, odo, _odometry_options(), per_frame,
                             SmootherOptions(pixel_noise=PIXEL_NOISE))
    res = bundle_adjust(built.problem, built.options)
    model = _Model(built.problem, built.options)
    assert model.n_marker_params == 0 and model.n_params == 6 * len(frames)
    ref = least_squares(model.residuals, np.zeros(model.n_params), jac=lambda x: model.jacobian(x).toarray(),
                        method="trf", loss="huber", f_scale=built.options.robust_scale, x_scale="jac",
                        ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=200)
    (_, _, _), (_, Rs, ts, _), _ = model.poses(ref.x)
    r = model.residuals(ref.x)
    assert np.max(np.linalg.norm(r[model.n_res - model.n_odo_res:].reshape(-1, 6), axis=1)) < 3.0
    dt = np.max(np.linalg.norm(res.T_W_stations[:, :3, 3] - ts, axis=1))
    dr = max(geo.pose_distance(geo.make_transform(R, t), T)[1] for R, t, T in zip(Rs, ts, res.T_W_stations))
    # The sparse LM stops at a relative cost decrease of ftol (1e-8): equal to 1e-5 (m, rad), a
    # hundredth of a mm, far below the errors above; and its cost is the reference's to 1e-8.
    assert dt < 1e-5 and dr < 1e-5, f"smoother vs dense reference: {dt:.2e} m, {dr:.2e} rad"
    model_s = _Model(dataclasses.replace(built.problem, T_W_stations=res.T_W_stations), built.options)
    r_smooth = model_s.residuals(np.zeros(model_s.n_params))

    def cost(rr):
        c = built.options.robust_scale
        a = np.abs(rr[: model.n_obs_res])
        return float(np.sum(np.where(a <= c, a * a, 2 * c * a - c * c)) + np.sum(rr[model.n_obs_res:] ** 2))

    assert abs(cost(r_smooth) - cost(r)) <= 1e-8 * cost(r), f"costs {cost(r_smooth):.10g} vs {cost(r):.10g}"


def test_smoother_is_robust_to_flipped_starts_and_outliers(walk):
    """Start poses off by 0.3 m / 20 deg on some frames (a flip the filter let through) and a few
    corners off by 40 px: the Huber losses and the odometry bring the trajectory back."""
    ring, marker_map, frames, odo, per_frame = walk
    rng = np.random.default_rng(5)
    start = list(per_frame)
    for k in (5, 22, 45):
        if start[k] is not None:
            start[k] = start[k] @ geo.se3_perturb(np.eye(4), np.r_[0.35, 0, 0, 0.3, 0, 0])
    bad = []
    for f in frames[::7]:
        cams = {}
        for name, cf in f.cameras.items():
            obs = [MarkerObservation(o.marker_id, o.corners + (rng.normal(0, 40.0, (4, 2)) if j == 0 else 0.0))
                   for j, o in enumerate(cf.observations)]
            cams[name] = CameraFrame(name, cf.stamp, obs, cf.model)
        bad.append(RingFrame(f.stamp, cams))
    noisy = [bad[k // 7] if k % 7 == 0 else f for k, f in enumerate(frames)]
    clean = smooth_trajectory(frames, ring, marker_map, odo, _odometry_options(), per_frame,
                              SmootherOptions(pixel_noise=PIXEL_NOISE))
    res = smooth_trajectory(noisy, ring, marker_map, odo, _odometry_options(), start,
                            SmootherOptions(pixel_noise=PIXEL_NOISE))
    e_clean = _errors_mm(clean.T_map_base, clean.stamps)
    e = _errors_mm(res.T_map_base, res.stamps)
    assert np.max(e) < 2.0 * np.max(e_clean) + 5.0, f"max {np.max(e):.2f} mm vs {np.max(e_clean):.2f} mm clean"
    assert np.median(e) < 1.5 * np.median(e_clean) + 1.0, f"median {np.median(e):.2f} vs {np.median(e_clean):.2f} mm"


def test_smoother_without_odometry_or_markers_says_so(walk):
    ring, marker_map, frames, odo, per_frame = walk
    with pytest.raises(ConfigError, match="per-frame estimate"):
        odometry_track([0.0], np.eye(4)[None], topic="/odom")
    with pytest.raises(ConfigError, match="per-frame estimate"):
        smooth_trajectory(frames, ring, marker_map, OdometryTrack(), _odometry_options(), per_frame)
    far = OdometryTrack([100.0, 101.0], np.stack([np.eye(4)] * 2))
    with pytest.raises(ConfigError, match="covers no two consecutive ring frames"):
        smooth_trajectory(frames, ring, marker_map, far, _odometry_options(), per_frame)
    with pytest.raises(GeometryError, match="no ring frame sees a mapped marker"):
        smooth_trajectory(frames, ring, MarkerMap([MarkerEntry(99, np.eye(4), SIZE)]), odo, _odometry_options(),
                          per_frame)


def test_hold_markers_leaves_the_markers_and_needs_no_other_gauge():
    """BAProblem.hold_markers: no marker unknowns, the markers returned as given; without it the
    same problem (no fixed marker or station) has no gauge."""
    rng = np.random.default_rng(2)
    T_mk = np.stack([geo.make_transform(geo.rotation_from_rvec([np.pi, 0, 0]), [x, 0.3 * x, 1.5 + x])
                     for x in (-0.5, 0.5)])
    T_st = np.stack([np.eye(4), geo.make_transform(np.eye(3), [0.1, 0, 0])])
    om, os_, xy = [], [], []
    for s in range(2):
        for m in range(2):
            p = geo.transform_points(geo.inverse(T_st[s]) @ T_mk[m], marker_corners(0.2))
            om.append(m), os_.append(s), xy.append(p[:, :2] / p[:, 2:] + rng.normal(0, 1e-5, (4, 2)))
    start = np.stack([geo.se3_perturb(T, rng.normal(0, 0.02, 6)) for T in T_st])
    prob = BAProblem(T_mk, np.full(2, 0.2), start, np.eye(4)[None], np.array(om), np.array(os_), np.zeros(4, int),
                     np.array(xy), np.full((4, 2), 800.0), fixed_marker=None, hold_markers=True)
    res = bundle_adjust(prob, BAOptions(covariance=False))
    assert res.n_params == 12
    assert np.array_equal(res.T_W_markers, T_mk)
    err = max(geo.pose_distance(a, b)[0] for a, b in zip(res.T_W_stations, T_st))
    assert err < 1e-3, f"stations {err * 1000:.2f} mm from the truth"
    prob.hold_markers = False
    with pytest.raises(GeometryError, match="gauge"):
        bundle_adjust(prob, BAOptions(covariance=False))


def test_level_holds_the_poses_upright(walk):
    """``level`` (a ground robot): every pose's z axis held along the map's by a 0.5 deg prior; the
    walk tilts by up to 1.7 deg, which the corners alone follow."""
    ring, marker_map, frames, odo, per_frame = walk

    def tilts(res):
        return np.degrees(np.arccos(np.clip(res.T_map_base[:, 2, 2], -1.0, 1.0)))

    free = smooth_trajectory(frames, ring, marker_map, odo, _odometry_options(), per_frame,
                             SmootherOptions(pixel_noise=PIXEL_NOISE))
    level = smooth_trajectory(frames, ring, marker_map, odo, _odometry_options(), per_frame,
                              SmootherOptions(pixel_noise=PIXEL_NOISE, level=True))
    true_tilt = np.degrees([np.arccos(_truth(t)[2, 2]) for t in free.stamps])
    assert np.median(np.abs(tilts(free) - true_tilt)) < 0.5, "the corners alone follow the tilt"
    # The 0.5 deg prior against corners that see 1.3 deg: pulled part of the way (measured 0.96 deg).
    assert np.median(tilts(level)) < np.median(tilts(free)) - 0.2, \
        f"level: median tilt {np.median(tilts(level)):.2f} deg vs {np.median(tilts(free)):.2f} deg free"
    tight = smooth_trajectory(frames, ring, marker_map, odo, _odometry_options(), per_frame,
                              SmootherOptions(pixel_noise=PIXEL_NOISE, level=True, level_sigma_deg=0.01))
    assert np.max(tilts(tight)) < 0.05, f"level_sigma_deg 0.01: max tilt {np.max(tilts(tight)):.3f} deg"
