"""Odometry (relative-pose) factors of the bundle adjustment: analytic Jacobian, normal equations,
robustness to a glitch, and a synthetic chain whose drift the factor removes."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.bundle_adjustment import (BAOptions, BAProblem, RelativePoseFactors, _Model,
                                                       bundle_adjust)
from aruco_ring_localization.errors import GeometryError
from aruco_ring_localization.markers import marker_corners

from helpers import ba_jacobian_rows


def _rel(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    return geo.inverse(T_a) @ T_b


def _small_problem(seed: int = 3, fixed_station=0):
    """3 stations, 4 markers, 2 cameras; odometry between consecutive stations and one skip."""
    rng = np.random.default_rng(seed)
    T_cams = np.stack([geo.make_transform(geo.rotation_from_rvec([0, 0.3 * k, 0]), [0.1 * k, 0, 0]) for k in range(2)])
    T_st = np.stack([geo.make_transform(geo.rotation_from_rvec(rng.normal(0, 0.2, 3)), rng.normal(0, 0.5, 3))
                     for _ in range(3)])
    T_mk = np.stack([geo.make_transform(geo.rotation_from_rvec([np.pi + rng.normal(0, 0.2), rng.normal(0, 0.2), 0]),
                                        [rng.uniform(-1, 1), rng.uniform(-0.5, 0.5), rng.uniform(3, 5)])
                     for _ in range(4)])
    om, os_, oc, xy = [], [], [], []
    for m in range(4):
        for s in range(3):
            for c in range(2):
                p = geo.transform_points(geo.inverse(T_cams[c]) @ geo.inverse(T_st[s]) @ T_mk[m], marker_corners(0.2))
                if np.all(p[:, 2] > 0.3):
                    om.append(m), os_.append(s), oc.append(c)
                    xy.append(p[:, :2] / p[:, 2:])
    n = len(om)
    pairs = [(0, 1), (1, 2), (0, 2)]
    odo = RelativePoseFactors([a for a, _ in pairs], [b for _, b in pairs],
                              [geo.se3_perturb(_rel(T_st[a], T_st[b]), rng.normal(0, 0.02, 6)) for a, b in pairs],
                              rng.uniform(0.005, 0.05, (3, 6)), robust_scale=2.0)
    return BAProblem(T_mk, np.full(4, 0.2), T_st, T_cams, np.array(om), np.array(os_), np.array(oc), np.array(xy),
                     np.full((n, 2), 800.0), fixed_marker=None, fixed_station=fixed_station, odometry=odo)


@pytest.mark.parametrize("fixed_station", [0, 1, None])
def test_odometry_jacobian_matches_finite_differences(fixed_station):
    prob = _small_problem(fixed_station=fixed_station)
    if fixed_station is None:
        prob.fixed_marker = 0
    model = _Model(prob, BAOptions(refine_extrinsics=True))
    assert model.n_odo_res == 18
    J, Jn = ba_jacobian_rows(model, slice(model.n_res - model.n_odo_res, model.n_res))
    err = np.max(np.abs(J - Jn)) / np.max(np.abs(J))
    assert err < 1e-6, f"relative Jacobian error of the odometry rows {err:.2e}"
    assert np.max(np.abs(J - Jn)) / np.max(np.abs(J)) < 1e-6


def test_odometry_normal_equations_match_the_jacobian():
    prob = _small_problem()
    model = _Model(prob, BAOptions(refine_extrinsics=True))
    rng = np.random.default_rng(2)
    x = rng.normal(0, 0.02, model.n_params)
    r = model.residuals(x)
    w = rng.uniform(0.1, 2.0, model.n_res)
    H, g = model.normal_equations(x, r, w)
    J = model.jacobian(x).toarray()
    assert np.max(np.abs(H.toarray() - J.T @ (w[:, None] * J))) <= 1e-9 * np.max(np.abs(J.T @ J))
    assert np.max(np.abs(g - J.T @ (w * r))) <= 1e-9 * np.max(np.abs(J.T @ r))


def test_odometry_residual_is_zero_for_the_measured_motion():
    prob = _small_problem()
    T = prob.T_W_stations
    prob.odometry = RelativePoseFactors([0, 1], [1, 2], [_rel(T[0], T[1]), _rel(T[1], T[2])], np.full((2, 6), 0.01))
    model = _Model(prob, BAOptions())
    r = model.residuals(np.zeros(model.n_params))
    assert np.max(np.abs(r[model.n_res - model.n_odo_res:])) < 1e-12


def test_huber_weight_of_a_glitch():
    """A factor 10 sigma off gets weight scale/10 on all its rows; one inside the scale keeps 1."""
    prob = _small_problem()
    T = prob.T_W_stations
    glitch = T[1] @ geo.make_transform(np.eye(3), [0.0, 0.0, 0.0])
    Z = [_rel(T[0], T[1]), geo.make_transform(np.eye(3), [0.1, 0, 0]) @ _rel(glitch, T[2])]
    sig = np.full((2, 6), 0.01)
    prob.odometry = RelativePoseFactors([0, 1], [1, 2], Z, sig, robust_scale=3.0)
    model = _Model(prob, BAOptions())
    r = model.residuals(np.zeros(model.n_params))
    w = model.odometry_weights(r)
    norm = np.linalg.norm(r[model.n_res - 6:])
    assert np.allclose(w[:6], 1.0)
    assert np.allclose(w[6:], 3.0 / norm) and norm > 9.0


def test_bad_factors_are_refused():
    with pytest.raises(GeometryError):
        RelativePoseFactors([0], [0], [np.eye(4)], [np.full(6, 0.01)])
    with pytest.raises(GeometryError):
        RelativePoseFactors([0], [1], [np.eye(4)], [np.zeros(6)])
    prob = _small_problem()
    prob.odometry = RelativePoseFactors([0], [7], [np.eye(4)], [np.full(6, 0.01)])
    with pytest.raises(GeometryError, match="station"):
        _Model(prob, BAOptions())


def _corridor(seed: int, n_st: int = 40):
    """A rig walking 0.5 m per station down a corridor (x), one marker pair per station on the
    walls, each pair seen only from its own station and the next: a chain. Returns the truth and
    the problem started from a drifted chain (each link off by a small rotation)."""
    rng = np.random.default_rng(seed)
    # Two cameras looking sideways (optical z along +y and -y of the base).
    cam = np.stack([geo.make_transform(geo.rotation_from_rvec([-np.pi / 2, 0, 0]), [0, 0, 0]),
                    geo.make_transform(geo.rotation_from_rvec([np.pi / 2, 0, 0]), [0, 0, 0])])
    T_st = np.stack([geo.make_transform(geo.rot_z(0.02 * np.sin(s / 5.0)), [0.5 * s, 0.02 * np.cos(s / 3.0), 0])
                     for s in range(n_st)])
    mk, side = [], []
    for s in range(n_st):
        for sgn in (1.0, -1.0):
            # on the wall at y = +-2 m, facing the corridor
            R = geo.rotation_from_rvec([sgn * np.pi / 2, 0, 0])
            mk.append(geo.make_transform(R, [0.5 * s + 0.25, 2.0 * sgn, 0.0]))
            side.append(0 if sgn > 0 else 1)
    T_mk = np.stack(mk)
    om, os_, oc, xy = [], [], [], []
    for m, T_m in enumerate(T_mk):
        for s in range(n_st):
            if abs(T_m[0, 3] - T_st[s][0, 3]) > 0.6:
                continue
            for c in range(2):
                p = geo.transform_points(geo.inverse(cam[c]) @ geo.inverse(T_st[s]) @ T_m, marker_corners(0.2))
                if np.all(p[:, 2] > 0.3):
                    om.append(m), os_.append(s), oc.append(c)
                    xy.append(p[:, :2] / p[:, 2:] + rng.normal(0, 0.3 / 800.0, (4, 2)))
    n = len(om)
    # Drifted start: chain the stations with a bias of 0.3 deg of yaw per link.
    start = [T_st[0]]
    for s in range(1, n_st):
        start.append(start[-1] @ geo.make_transform(geo.rot_z(np.radians(0.3)), [0, 0, 0]) @ _rel(T_st[s - 1], T_st[s]))
    start = np.stack(start)
    T_mk0 = np.stack([start[max(0, min(n_st - 1, int(T[0, 3] / 0.5)))] @ _rel(T_st[max(0, min(n_st - 1, int(T[0, 3] / 0.5)))], T)
                      for T in T_mk])
    prob = BAProblem(T_mk0, np.full(len(T_mk), 0.2), start, cam, np.array(om), np.array(os_), np.array(oc),
                     np.array(xy), np.full((n, 2), 800.0), fixed_marker=None, fixed_station=0)
    return prob, T_st, T_mk


def test_odometry_removes_the_drift_of_a_weak_chain():
    """Markers seen in pairs along a corridor only link neighbouring stations weakly: the chain's
    far end drifts with the pixel noise (the start: 0.3 deg of yaw bias per link). Odometry (1 mm /
    0.1 mrad per link, each link drawn with that noise) holds it: the worst marker ends 4x closer to
    the truth with the factors than without. An odometry glitch (one link 0.5 m off) does not undo
    it with the Huber loss; plain least squares follows the glitch by metres."""
    prob, T_st, T_mk = _corridor(seed=7)
    rng = np.random.default_rng(11)
    opts = BAOptions(covariance=False)
    without = bundle_adjust(prob, opts)
    n_st = len(T_st)
    sig = np.tile(np.r_[np.full(3, 1e-4), np.full(3, 1e-3)], (n_st - 1, 1))
    Z = [geo.se3_perturb(_rel(T_st[s], T_st[s + 1]), rng.normal(0, 1.0, 6) * sig[s]) for s in range(n_st - 1)]

    def far_error(res) -> float:
        return float(np.max(np.linalg.norm(res.T_W_markers[:, :3, 3] - T_mk[:, :3, 3], axis=1)))

    links = (np.arange(n_st - 1), np.arange(1, n_st))
    prob.odometry = RelativePoseFactors(*links, Z, sig)
    with_odo = bundle_adjust(prob, opts)
    Zg = list(Z)
    Zg[n_st // 2] = geo.make_transform(np.eye(3), [0.5, 0.0, 0.0]) @ Zg[n_st // 2]
    prob.odometry = RelativePoseFactors(*links, Zg, sig)
    glitch = bundle_adjust(prob, opts)
    prob.odometry = RelativePoseFactors(*links, Zg, sig, robust_scale=0.0)
    glitch_ls = bundle_adjust(prob, opts)
    e0, e1, e2, e3 = far_error(without), far_error(with_odo), far_error(glitch), far_error(glitch_ls)
    assert e0 > 0.06, f"the chain alone should drift (worst marker {1000 * e0:.1f} mm)"
    assert e1 < 0.25 * e0, f"without {1000 * e0:.1f} mm, with odometry {1000 * e1:.1f} mm"
    assert e2 < 0.3 * e0, f"a 0.5 m glitch moved the worst marker to {1000 * e2:.1f} mm (Huber)"
    assert e3 > 10 * e2, f"plain least squares with the glitch: {1000 * e3:.1f} mm"


@pytest.mark.parametrize("offset", [False, True])
def test_odometry_links_a_station_no_marker_links(ring, scene, offset):
    """A marker seen only from a station 27 m away, with nothing in common with the mapped set, is
    'not linked' without odometry; with the robot's odometry (exact here, 20 Hz) the station is
    placed by it and the marker mapped where it is. ``offset``: the odometry reports a body frame
    that is not the ring's base (a VIO's IMU), declared by ``base_to_odom``."""
    from aruco_ring_localization.evaluation.maps import map_error
    from aruco_ring_localization.mapping import MapBuilder, MappingOptions
    from aruco_ring_localization.mapping_odometry import MappingOdometryOptions
    from aruco_ring_localization.markers import MarkerSizes
    from aruco_ring_localization.simulation.ring_sim import RingSimulator
    from aruco_ring_localization.simulation.scene import Scene, SceneMarker, marker_pose

    far = SceneMarker(999, marker_pose([30.0, 4.5, 1.0], np.pi), 0.2)
    big = Scene(**{**scene.__dict__, "markers": list(scene.markers) + [far]})
    big.room = type(scene.room)(origin=(0.0, 0.0), size=(40.0, 9.0), height=3.0)
    sim = RingSimulator(big, ring, pixel_noise=0.0, seed=0, max_range=8.0)
    start, end = np.array(scene.mapping_pose, dtype=float), np.array([27.0, 4.5, 0.0])
    X = geo.make_transform(geo.rotation_from_rvec([0.02, -0.01, 3.1]), [0.03, 0.02, -0.02]) if offset else np.eye(4)
    rvec, tvec = geo.rvec_tvec_from_transform(X)
    opts = MappingOptions(odometry=MappingOdometryOptions(topic="odom", base_to_odom=tuple(np.r_[tvec, rvec])))

    def build(with_odometry: bool) -> MapBuilder:
        b = MapBuilder(ring, MarkerSizes(0.2), options=opts)
        if with_odometry:
            t = np.arange(0.0, 10.3, 0.05)
            s = np.clip((t - 0.2) / 9.8, 0.0, 1.0)
            poses = [Scene.T_world_base(tuple((1 - a) * start + a * end)) @ X for a in s]
            b.set_odometry(t, np.stack(poses))
        for k, pose in enumerate([tuple(start), tuple(end)]):
            for f in range(2):
                b.add_frame(sim.observe(Scene.T_world_base(pose), stamp=10.0 * k + 0.1 * f))
        return b

    alone = build(False)
    assert alone.unlinked_markers() == [999]
    b = build(True)
    assert b.unlinked_markers() == []
    m = b.build("refined")
    assert 999 in m
    err = map_error(m, big.truth_map(), best_fit=True)
    assert err["per_marker"][999][0] < 1.0, f"marker 999 {err['per_marker'][999][0]:.2f} mm off"
    assert err["position_rms_mm"] < 1.0, f"RMS {err['position_rms_mm']:.2f} mm"


def test_a_station_between_slow_odometry_messages_widens_its_links():
    """Odometry at 4 Hz (test_22's tracking camera) interpolated at stations between its messages
    misses what the motion did in between: each such station widens its two links by
    ``max_acceleration * (t - t0) * (t1 - t) / 2`` (rotation: ``max_angular_acceleration``), a
    station at a message's stamp (tests 11, 12, 21: odometry stamped with the frames) not at all."""
    from aruco_ring_localization.mapping_odometry import MappingOdometryOptions, OdometryTrack

    stamps = np.arange(0.0, 2.01, 0.25)
    poses = np.stack([geo.make_transform(geo.rot_z(0.1 * t), [0.3 * t, 0.0, 0.0]) for t in stamps])
    track = OdometryTrack(stamps, poses)
    opts = MappingOdometryOptions(topic="odom", max_acceleration=4.0, max_angular_acceleration=2.0,
                                  noise_model="random_walk")
    on = track.links({0: 0.25, 1: 0.5, 2: 0.75}, opts)
    between = track.links({0: 0.25, 1: 0.625, 2: 0.75}, opts)       # station 1 midway between messages
    assert track.interpolation_error(0.5, 4.0, 2.0) == (0.0, 0.0)
    et, er = track.interpolation_error(0.625, 4.0, 2.0)
    assert et == pytest.approx(4.0 * 0.125 * 0.125 / 2) and er == pytest.approx(2.0 * 0.125 * 0.125 / 2)
    for k in range(2):
        # Same motion model otherwise: the variance grows by the interpolation error's square.
        d_on = np.linalg.norm(on.T_ij[k][:3, 3])
        d_bw = np.linalg.norm(between.T_ij[k][:3, 3])
        base_t = np.sqrt(opts.min_translation ** 2 + opts.translation_noise ** 2 * d_bw)
        assert between.sigma[k, 3] == pytest.approx(np.sqrt(base_t ** 2 + et ** 2), rel=1e-6)
        assert on.sigma[k, 3] == pytest.approx(np.sqrt(opts.min_translation ** 2 + opts.translation_noise ** 2 * d_on),
                                               rel=1e-6)
        assert between.sigma[k, 0] > on.sigma[k, 0] + 0.5 * er
