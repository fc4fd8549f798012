"""bundle_adjustment: analytic Jacobian, convergence to the truth, covariance, gauge."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.bundle_adjustment import BAOptions, _Model, bundle_adjust
from aruco_ring_localization.errors import GeometryError

from helpers import ba_dense_reference, synthetic_ba_problem as _problem


def _random_pose(rng, rot=0.3, trans=1.0):
    return geo.make_transform(geo.rotation_from_rvec(rng.normal(0, rot, 3)), rng.normal(0, trans, 3))


@pytest.mark.parametrize("refine_extrinsics", [False, True])
def test_analytic_jacobian_matches_finite_differences(refine_extrinsics):
    prob, _ = _problem(seed=3, M=4, S=3, C=2, per=12)
    model = _Model(prob, BAOptions(refine_extrinsics=refine_extrinsics))
    rng = np.random.default_rng(1)
    x = rng.normal(0, 0.05, model.n_params)
    J = model.jacobian(x).toarray()
    h = 1e-6
    Jn = np.stack([(model.residuals(x + h * e) - model.residuals(x - h * e)) / (2 * h)
                   for e in np.eye(model.n_params)], axis=1)
    err = np.max(np.abs(J - Jn)) / np.max(np.abs(J))
    assert err < 1e-6, f"relative Jacobian error {err:.2e}"


def _anchored_problem(seed=3, S=3):
    """A problem with every kind of prior row: extrinsics refined, surveyed positions and rotations,
    a level station (no fixed pose: the priors hold the gauge)."""
    from aruco_ring_localization.bundle_adjustment import MarkerPriors

    prob, (T_mk, _, _) = _problem(seed=seed, M=5, S=S, C=2, per=40 * S // 3)
    prob.fixed_station = None
    prob.priors = MarkerPriors(position_marker=[0, 1, 2], position=T_mk[:3, :3, 3], position_std=np.full((3, 3), 0.01),
                               rotation_marker=[1], rotation=T_mk[1:2, :3, :3], rotation_std=[0.01],
                               level_station=[0], level_sigma=0.001)
    return prob


@pytest.mark.parametrize("case", ["fixed_station", "fixed_marker", "priors", "priors_many_stations", "many_stations"])
def test_normal_equations_match_the_jacobian(case):
    """H and g assembled from the per-observation blocks equal J^T W J and J^T W r of the sparse
    Jacobian (itself checked against finite differences above), with arbitrary row weights; the
    damped solve through the Schur complement (on the markers, or on the stations when they
    outnumber the markers: a calibration recording) equals a dense solve."""
    if case.startswith("priors"):
        prob = _anchored_problem(S=12 if case == "priors_many_stations" else 3)
    elif case == "many_stations":
        prob, _ = _problem(seed=3, M=3, S=12, C=2, per=120)
    else:
        prob, _ = _problem(seed=3, M=5, S=3, C=2, per=40)
        if case == "fixed_marker":
            prob.fixed_station, prob.fixed_marker = None, 2
    model = _Model(prob, BAOptions(refine_extrinsics=True))
    ref = ba_dense_reference(model)
    H, H_ref, d = ref.H, ref.H_ref, ref.d
    assert np.max(np.abs(H.toarray() - H_ref)) <= 1e-9 * np.max(np.abs(H_ref))
    assert np.max(np.abs(ref.g - ref.g_ref)) <= 1e-9 * np.max(np.abs(ref.g_ref))
    # The Schur-complement solve of the damped system equals a dense solve (the stations
    # eliminated when they outnumber the markers).
    assert model._station_elimination() == case.endswith("many_stations")
    assert np.max(np.abs(ref.dx - ref.dx_ref)) <= 1e-7 * np.max(np.abs(ref.dx_ref))
    # The cameras' marginal information is the inverse of their block of the (damped) H's inverse.
    cols = np.concatenate([model.col_c[k] + np.arange(6) for k in range(model.C)])
    Hd = H.copy()
    Hd.data[model._h_diag] += d
    cov_ref = np.linalg.inv(H_ref + np.diag(d))[np.ix_(cols, cols)]
    cov = np.linalg.inv(model.marginal_information(Hd, cols))
    assert np.max(np.abs(cov - cov_ref)) <= 1e-7 * np.max(np.abs(cov_ref))


def test_solvers_agree_on_the_solution():
    """lm (Schur complement) and trf (scipy's trust region, exact steps) reach the same minimum
    (within 10 um; the stds are millimetres) and the same covariance (quadratic loss: with a robust
    one scipy's loss-scaled Jacobian and the reweighting differ by design, 2 % on the stds here)."""
    prob, _ = _problem(seed=1, noise=0.5, per=150)
    rng = np.random.default_rng(4)
    prob.obs_xy = prob.obs_xy + rng.normal(0, 0.5 / 800.0, prob.obs_xy.shape)
    a = bundle_adjust(prob, BAOptions(refine_extrinsics=True, loss="linear"))
    b = bundle_adjust(prob, BAOptions(refine_extrinsics=True, loss="linear", solver="trf"))
    assert np.max(np.abs(a.T_W_markers[:, :3, 3] - b.T_W_markers[:, :3, 3])) < 1e-5
    sa = np.sqrt(np.stack([np.diag(c[3:, 3:]) for c in a.marker_cov]))
    sb = np.sqrt(np.stack([np.diag(c[3:, 3:]) for c in b.marker_cov]))
    assert np.max(np.abs(sa / sb - 1.0)) < 1e-3


def test_converges_to_truth_from_perturbed_start():
    prob, (T_mk, T_st, _) = _problem(seed=0, per=200)
    rng = np.random.default_rng(5)
    prob.T_W_markers = np.stack([geo.se3_perturb(T, np.r_[rng.normal(0, 0.03, 3), rng.normal(0, 0.03, 3)])
                                 for T in T_mk])
    prob.T_W_stations = np.stack([T_st[0]] + [geo.se3_perturb(T, np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.03, 3)])
                                              for T in T_st[1:]])
    res = bundle_adjust(prob, BAOptions())
    worst = max(geo.pose_distance(a, b)[0] for a, b in zip(res.T_W_markers, T_mk))
    assert worst < 1e-6, f"worst marker position error {worst:.2e} m"
    assert res.rms_px_after < 1e-5 < res.rms_px_before, f"RMS {res.rms_px_before:.3f} -> {res.rms_px_after:.2e} px"


def test_covariance_matches_monte_carlo_spread():
    """The reported position std agrees with the spread of solutions over noise draws (within 35 %)."""
    pos = []
    for seed in range(25):
        prob, (T_mk, _, _) = _problem(seed=0, noise=0.5, per=150)
        rng = np.random.default_rng(100 + seed)
        prob.obs_xy = prob.obs_xy + rng.normal(0, 0.5 / 800.0, prob.obs_xy.shape)
        res = bundle_adjust(prob, BAOptions(pixel_noise=0.5, covariance=seed == 0))
        if seed == 0:
            cov = res.marker_cov
        pos.append(res.T_W_markers[:, :3, 3])
    emp = np.std(np.array(pos), axis=0)                    # (M, 3)
    rep = np.sqrt(np.stack([np.diag(c[3:, 3:]) for c in cov]))
    ratio = np.median(rep / emp)
    assert 0.65 < ratio < 1.5, f"median reported/empirical std ratio {ratio:.2f}"


def test_needs_observations_and_gauge():
    prob, _ = _problem()
    prob.fixed_station = None
    with pytest.raises(GeometryError, match="gauge"):
        bundle_adjust(prob)
    prob2, _ = _problem(per=0)
    with pytest.raises(GeometryError, match="observation"):
        bundle_adjust(prob2)


def test_adjustment_runs_with_one_blas_thread_and_restores_the_count(monkeypatch):
    import aruco_ring_localization.bundle_adjustment as ba
    from threadpoolctl import threadpool_info

    def blas_threads():
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    before = blas_threads()
    assert before, "no BLAS library found by threadpoolctl: the thread limit would do nothing"
    seen = []
    monkeypatch.setattr(ba, "_bundle_adjust", lambda prob, opts=None: seen.append(blas_threads()))
    ba.bundle_adjust(None)
    assert seen == [[1] * len(before)], f"BLAS threads inside the adjustment: {seen} (outside: {before})"
    assert blas_threads() == before, "the thread count was not restored"


def test_camera_covariance_keeps_the_prior_only_direction_at_its_prior():
    """A turn of the whole rig against the base is fixed by the extrinsics' priors alone (the
    stations and markers absorb it), so the information on it must be the priors' whatever the
    pixel noise; the cameras' relative motion, which the corners fix, must shrink with the noise.
    With the variance factor scaling the whole covariance (as before), both scaled by it."""
    o = BAOptions()

    def run(noise):
        prob, _ = _problem(seed=0, per=200)
        rng = np.random.default_rng(7)
        prob.obs_xy = prob.obs_xy + rng.normal(0, noise / 800.0, prob.obs_xy.shape)
        res = bundle_adjust(prob, BAOptions(pixel_noise=0.5, refine_extrinsics=True))
        C = res.camera_cov
        assert C.shape == (18, 18) and np.linalg.eigvalsh(0.5 * (C + C.T))[0] > 0, "not a covariance"
        # The common turn about base z, in the adjustment's (w, dt) per camera: w = e_z, dt = e_z x t0.
        d = np.concatenate([np.r_[0, 0, 1.0, np.cross([0, 0, 1.0], T[:3, 3])] for T in prob.T_base_cams])
        prior_info = sum(1.0 / o.extrinsics_rot_sigma ** 2 + np.sum(np.cross([0, 0, 1.0], T[:3, 3]) ** 2)
                         / o.extrinsics_trans_sigma ** 2 for T in prob.T_base_cams)
        r = np.zeros(18)  # camera 1 turned against camera 0 about z
        r[2], r[8] = -1.0, 1.0
        return d @ np.linalg.solve(C, d) / prior_info, r @ C @ r, res.variance_factor

    turn_lo, rel_lo, vf_lo = run(0.1)
    turn_hi, rel_hi, vf_hi = run(0.5)
    assert vf_lo < 0.1 < 0.5 < vf_hi, (vf_lo, vf_hi)
    for turn, vf in ((turn_lo, vf_lo), (turn_hi, vf_hi)):
        # measured 1.0016 and 1.0000 (the linearisation point); the variance factor alone would give 1/vf = 25.
        assert turn == pytest.approx(1.0, rel=0.02), f"information on the turn / the priors' = {turn:.4f} (vf {vf:.3f})"
    assert rel_lo < 0.2 * rel_hi, f"the data-fixed relative turn did not shrink: {rel_lo:.3e} vs {rel_hi:.3e}"


@pytest.mark.parametrize("shape,mode", [(dict(M=3, S=8, C=3), "stations"), (dict(M=3, S=8, C=3), "markers"),
                                        (dict(M=12, S=2, C=2), "markers")])
def test_eliminations_and_dense_reduced_system_agree(monkeypatch, shape, mode):
    """The stations eliminated (more stations than markers), or the markers with a dense reduced
    system (Cholesky), take the same steps as the markers eliminated with a sparse reduced system
    (SuperLU), and give the same covariances as the pseudo-inverse of that reduced system (through
    the Cholesky factor: the reduced system's inverse with the stations eliminated; triangular
    solves with fewer markers' unknowns than stations', its inverse with more)."""
    from aruco_ring_localization import bundle_adjustment as ba

    prob, _ = _problem(seed=2, noise=0.5, per=120, **shape)
    rng = np.random.default_rng(6)
    prob.obs_xy = prob.obs_xy + rng.normal(0, 0.5 / 800.0, prob.obs_xy.shape)
    opts = BAOptions(refine_extrinsics=True)
    if mode == "markers":
        monkeypatch.setattr(ba, "STATION_ELIMINATION_MAX_KEPT", 0)
    model = _Model(prob, opts)
    assert model._station_elimination() == (mode == "stations")
    assert model._reduced_is_dense()
    fast = bundle_adjust(prob, opts)
    monkeypatch.setattr(ba, "STATION_ELIMINATION_MAX_KEPT", 0)
    monkeypatch.setattr(ba, "DENSE_REDUCED_FILL", 2.0)       # never dense
    monkeypatch.setattr(ba, "_cholesky", lambda S: None)      # the pseudo-inverse
    model = _Model(prob, opts)
    assert not model._reduced_is_dense() and not model._station_elimination()
    ref = bundle_adjust(prob, opts)
    assert fast.nfev == ref.nfev
    assert np.max(np.abs(fast.T_W_markers - ref.T_W_markers)) < 1e-9
    assert np.max(np.abs(fast.marker_cov - ref.marker_cov)) <= 1e-6 * np.max(np.abs(ref.marker_cov))
    assert np.max(np.abs(fast.camera_cov - ref.camera_cov)) <= 1e-6 * np.max(np.abs(ref.camera_cov))


@pytest.mark.parametrize("fixed_station", [0, 4])
def test_stations_linked_by_odometry_eliminated_through_their_band(monkeypatch, fixed_station):
    """Odometry links consecutive stations (and some two apart): the stations' block is banded,
    eliminated by banded Cholesky; the same steps and covariances as with the markers eliminated.
    A link farther apart than STATION_ELIMINATION_MAX_BAND keeps the markers' elimination."""
    from aruco_ring_localization import bundle_adjustment as ba
    from aruco_ring_localization.bundle_adjustment import RelativePoseFactors

    prob, (_, T_st, _) = _problem(seed=4, noise=0.5, per=150, M=3, S=10, C=2)
    prob.fixed_station = fixed_station
    rng = np.random.default_rng(7)
    prob.obs_xy = prob.obs_xy + rng.normal(0, 0.5 / 800.0, prob.obs_xy.shape)
    pairs = [(s, s + 1) for s in range(9)] + [(s, s + 2) for s in range(0, 8, 3)]
    prob.odometry = RelativePoseFactors([a for a, _ in pairs], [b for _, b in pairs],
                                        [geo.se3_perturb(geo.inverse(T_st[a]) @ T_st[b], rng.normal(0, 0.003, 6))
                                         for a, b in pairs], np.full((len(pairs), 6), 0.01))
    opts = BAOptions(refine_extrinsics=True)
    model = _Model(prob, opts)
    assert model._station_elimination() and model._station_band == 6 * 2 + 5
    fast = bundle_adjust(prob, opts)
    monkeypatch.setattr(ba, "STATION_ELIMINATION_MAX_KEPT", 0)
    ref = bundle_adjust(prob, opts)
    assert fast.nfev == ref.nfev
    assert np.max(np.abs(fast.T_W_stations - ref.T_W_stations)) < 1e-9
    assert np.max(np.abs(fast.marker_cov - ref.marker_cov)) <= 1e-6 * np.max(np.abs(ref.marker_cov))
    assert np.max(np.abs(fast.camera_cov - ref.camera_cov)) <= 1e-6 * np.max(np.abs(ref.camera_cov))
    monkeypatch.undo()
    prob.odometry = RelativePoseFactors([0], [ba.STATION_ELIMINATION_MAX_BAND + 1], [np.eye(4)], [np.full(6, 0.01)])
    assert not _Model(prob, opts)._station_elimination()


def test_per_camera_extrinsics_prior():
    """``BAProblem.extrinsics_sigma`` gives each camera its own prior (a ring file's extrinsics_std):
    the Jacobian stays exact; the default (None) is the options' sigma on every camera; a camera
    whose calibration is off by 3 mm and 0.3 deg moves to the truth under a loose prior and stays
    at its calibration under a tight one (the other cameras keep the options' prior)."""
    import dataclasses

    prob, (_, _, T_cams) = _problem(seed=5, M=5, S=4, C=3, per=200)
    opts = BAOptions(refine_extrinsics=True, loss="linear")
    sig = np.tile(np.r_[np.full(3, opts.extrinsics_rot_sigma), np.full(3, opts.extrinsics_trans_sigma)], (3, 1))
    x = np.random.default_rng(3).normal(0, 0.01, _Model(prob, opts).n_params)
    r_default = _Model(prob, opts).residuals(x)
    r_same = _Model(dataclasses.replace(prob, extrinsics_sigma=sig), opts).residuals(x)
    assert np.array_equal(r_default, r_same)
    sig[1] = [1e-3, 2e-3, 3e-3, 1e-3, 2e-3, 4e-3]
    model = _Model(dataclasses.replace(prob, extrinsics_sigma=sig), opts)
    assert not np.allclose(model.residuals(x), r_default)
    J = model.jacobian(x).toarray()
    h = 1e-6
    Jn = np.stack([(model.residuals(x + h * e) - model.residuals(x - h * e)) / (2 * h)
                   for e in np.eye(model.n_params)], axis=1)
    assert np.max(np.abs(J - Jn)) / np.max(np.abs(J)) < 1e-6
    # Camera 1's calibration off; the corners are the true rig's.
    wrong = T_cams.copy()
    wrong[1] = geo.se3_perturb(T_cams[1], np.r_[np.radians([0.3, -0.2, 0.1]), 0.003, -0.002, 0.001])
    off = dataclasses.replace(prob, T_base_cams=wrong)

    def moved(std_cam1):
        s = np.tile(np.r_[np.full(3, opts.extrinsics_rot_sigma), np.full(3, opts.extrinsics_trans_sigma)], (3, 1))
        s[1] = std_cam1
        res = bundle_adjust(dataclasses.replace(off, extrinsics_sigma=s), opts)
        # Camera 1 relative to camera 0 (the common motion is the priors' alone).
        rel = geo.inverse(res.T_base_cams[0]) @ res.T_base_cams[1]
        return (geo.pose_distance(rel, geo.inverse(T_cams[0]) @ T_cams[1]),
                geo.pose_distance(res.T_base_cams[1], wrong[1]))

    (to_truth_mm, _), _ = moved(np.r_[np.full(3, 0.1), np.full(3, 0.1)])
    _, (from_calib_m, from_calib_rad) = moved(np.full(6, 1e-7))
    assert to_truth_mm < 1e-4, f"a loosely held camera did not reach the truth: {to_truth_mm * 1e3:.3f} mm off"
    assert from_calib_m < 1e-6 and from_calib_rad < 1e-6, (from_calib_m, from_calib_rad)
    with pytest.raises(GeometryError, match="extrinsics_sigma"):
        _Model(dataclasses.replace(prob, extrinsics_sigma=np.zeros((3, 6))), opts)
