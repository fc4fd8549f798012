"""bundle_adjustment: survey measurements (distances between marker points, points on a plane)."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization.bundle_adjustment import BAOptions, MarkerPriors, _Model, bundle_adjust
from aruco_ring_localization.markers import marker_corners

from helpers import ba_dense_reference, synthetic_ba_problem as _scene


def _point(T, X):
    return T[:3, :3] @ X + T[:3, 3]


def _measured(T_mk, pairs, std=0.001, plane=(), plane_std=0.002):
    """Priors with the true distances between corner 0 of the first marker and the centre of the
    second of each pair, and the true plane offsets of marker ``plane``'s corners along z."""
    c0 = marker_corners(0.2)[0]
    pts = np.array([[c0, np.zeros(3)] for _ in pairs]).reshape(-1, 2, 3)
    dist = [float(np.linalg.norm(_point(T_mk[a], c0) - T_mk[b][:3, 3])) for a, b in pairs]
    n = np.array([0.0, 0.0, 1.0])
    pm = [m for m in plane for _ in range(4)]
    pp = [marker_corners(0.2)[k] for _ in plane for k in range(4)]
    off = [float(n @ _point(T_mk[m], X)) for m, X in zip(pm, pp)]
    return MarkerPriors(distance_marker=np.array(pairs, dtype=int).reshape(-1, 2), distance_point=pts,
                        distance=dist, distance_std=np.full(len(pairs), std), plane_marker=pm, plane_point=pp,
                        plane_normal=np.tile(n, (len(pm), 1)), plane_offset=off, plane_std=np.full(len(pm), plane_std))


@pytest.mark.parametrize("fixed_marker", [None, 1])
def test_measurement_jacobian_matches_finite_differences(fixed_marker):
    """Distance and plane rows (a fixed marker's columns left out) against central differences."""
    prob, (T_mk, _, _) = _scene(seed=3, M=4, S=3, C=2, per=12)
    prob.priors = _measured(T_mk, [(0, 1), (2, 3), (1, 2)], plane=[1, 3])
    if fixed_marker is not None:
        prob.fixed_station, prob.fixed_marker = None, fixed_marker
    model = _Model(prob, BAOptions())
    rng = np.random.default_rng(1)
    x = rng.normal(0, 0.05, model.n_params)
    J = model.jacobian(x).toarray()
    h = 1e-6
    Jn = np.stack([(model.residuals(x + h * e) - model.residuals(x - h * e)) / (2 * h)
                   for e in np.eye(model.n_params)], axis=1)
    rows = slice(model.n_obs_res, model.n_res)
    err = np.max(np.abs(J[rows] - Jn[rows])) / np.max(np.abs(J[rows]))
    assert err < 1e-6, f"relative Jacobian error of the measurement rows {err:.2e}"
    assert np.count_nonzero(np.abs(Jn[rows]) > 1e-9) <= np.count_nonzero(J[rows])


@pytest.mark.parametrize("case", ["markers", "stations"])
def test_coupled_solve_equals_dense_solve(case):
    """Distances couple two free markers: the damped step through the Schur complement (markers
    eliminated: with the Woodbury correction; stations eliminated: exact as it is) equals a dense
    solve of J^T W J."""
    if case == "stations":
        prob, (T_mk, _, _) = _scene(seed=3, M=3, S=12, C=2, per=120)
    else:
        prob, (T_mk, _, _) = _scene(seed=3, M=5, S=3, C=2, per=40)
    prob.priors = _measured(T_mk, [(0, 1), (1, 2), (0, 2)], std=1e-4, plane=[0])
    model = _Model(prob, BAOptions(refine_extrinsics=True))
    assert model._dist_coupled
    assert model._station_elimination() == (case == "stations")
    ref = ba_dense_reference(model)
    H, H_ref = ref.H, ref.H_ref
    assert np.max(np.abs(H.toarray() - H_ref)) <= 1e-9 * np.max(np.abs(H_ref))
    assert np.max(np.abs(ref.dx - ref.dx_ref)) <= 1e-7 * np.max(np.abs(ref.dx_ref))


def test_lm_and_trf_agree_with_distances():
    """The LM steps with the Woodbury correction reach scipy's trust-region minimum."""
    prob, (T_mk, _, _) = _scene(seed=1, noise=0.5, per=150)
    pri = _measured(T_mk, [(0, 3), (1, 4)], std=2e-4)
    pri.distance = pri.distance * 1.002          # a survey that disagrees slightly with the images
    prob.priors = pri
    a = bundle_adjust(prob, BAOptions(loss="linear"))
    b = bundle_adjust(prob, BAOptions(loss="linear", solver="trf"))
    assert np.max(np.abs(a.T_W_markers[:, :3, 3] - b.T_W_markers[:, :3, 3])) < 1e-5


def test_a_distance_fixes_the_scale_the_images_leave_loose():
    """One camera, small far markers, 1 px noise: the images fix the scale only through the
    markers' apparent size (seeded: 2 % off here). A 1 mm tape measurement between two markers
    brings the whole map to scale: the distances of the other pairs, not measured, too."""
    prob, (T_mk, _, _) = _scene(seed=8, M=6, S=6, C=1, per=400, size=0.05, focal=600.0)
    rng = np.random.default_rng(11)
    prob.obs_xy = prob.obs_xy + rng.normal(0, 1.0 / 600.0, prob.obs_xy.shape)
    centres = T_mk[:, :3, 3]
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    a, b = np.unravel_index(np.argmax(d), d.shape)              # the farthest pair is measured
    others = [(i, j) for i in range(6) for j in range(i + 1, 6) if {i, j} != {a, b} and d[i, j] > 1.0]
    opts = BAOptions(pixel_noise=1.0, loss="linear")

    def scale_error(res):
        """|s - 1| of the least-squares scale of the other pairs' mapped distances to the true ones."""
        P = res.T_W_markers[:, :3, 3]
        got = np.array([np.linalg.norm(P[i] - P[j]) for i, j in others])
        true = np.array([d[i, j] for i, j in others])
        return abs(float(got @ true / (true @ true)) - 1.0)

    free = bundle_adjust(prob, opts)
    prob.priors = MarkerPriors(distance_marker=[[a, b]], distance_point=np.zeros((1, 2, 3)), distance=[d[a, b]],
                               distance_std=[0.001])
    fixed = bundle_adjust(prob, opts)
    P = fixed.T_W_markers[:, :3, 3]
    assert abs(np.linalg.norm(P[a] - P[b]) - d[a, b]) < 3e-3
    assert scale_error(free) > 0.005, scale_error(free)               # the images alone: loose
    assert scale_error(fixed) < scale_error(free) / 3.0, (scale_error(free), scale_error(fixed))
