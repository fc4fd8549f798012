"""anchors: the file format, the weighted frame fit, and the anchors as bundle adjustment priors."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.anchors import (Anchor, AnchorSet, anchors_from_dict, check_anchor_report, fit_frame,
                                             frame_kind, load_anchors, noisy_anchors)
from aruco_ring_localization.bundle_adjustment import BAOptions, MarkerPriors, _Model, bundle_adjust
from aruco_ring_localization.errors import ConfigError, GeometryError

from test_bundle_adjustment import _problem


def _markers(seed=0, n=5, spread=6.0):
    rng = np.random.default_rng(seed)
    return {10 + k: geo.make_transform(geo.rotation_from_rvec(rng.normal(0, 0.5, 3)),
                                       [rng.uniform(-spread, spread), rng.uniform(-spread, spread),
                                        rng.uniform(0.2, 1.5)]) for k in range(n)}


def _yaw(a):
    return geo.make_transform(geo.rotation_from_rvec([0, 0, a]))


# --- file ------------------------------------------------------------------------------------------

def test_file_round_trip(tmp_path):
    text = """
frame_id: plate
anchors:
  - {marker: 3, position: [0.0, 0.0, 0.45], std: 0.001, instrument: total station}
  - {marker: 7, position: [6.0, 0.1, 0.45], std: [0.001, 0.002, 0.003]}
  - {marker: 9, position: [1.0, 4.0, 0.5], std: 0.002, rotation: [0, 0, 0, 1], rotation_std_deg: 0.1}
"""
    path = tmp_path / "anchors.yaml"
    path.write_text(text)
    a = load_anchors(str(path))
    assert a.ids == [3, 7, 9] and a.frame_id == "plate"
    assert np.allclose(a.anchors[1].position_std, [0.001, 0.002, 0.003])
    assert np.allclose(a.anchors[2].rotation, np.eye(3)) and np.isclose(np.degrees(a.anchors[2].rotation_std), 0.1)
    back = anchors_from_dict(yaml.safe_load(yaml.safe_dump(a.to_dict())))
    assert back.ids == a.ids and np.allclose(back.anchors[1].position, a.anchors[1].position)
    assert frame_kind(a) == "pose"


@pytest.mark.parametrize("body, key", [
    ("anchors: 3", "anchors"),
    ("anchors: []", "anchors"),
    ("anchors: [{marker: 3, position: [0, 0, 0], std: 0.001}]", "anchors"),          # one point: no frame
    ("anchors: [{marker: 3, position: [0, 0], std: 0.001}, {marker: 4, position: [1, 0, 0], std: 0.001}]",
     "anchors[0].position"),
    ("anchors: [{marker: 3, position: [0, 0, 0], std: -1}, {marker: 4, position: [1, 0, 0], std: 0.001}]",
     "anchors[0].std"),
    ("anchors: [{marker: 3, position: [0, 0, 0], std: 0.001}, {marker: 4, position: [1, 0, .nan], std: 0.001}]",
     "anchors[1].position"),
    ("anchors: [{marker: x, position: [0, 0, 0], std: 0.001}, {marker: 4, position: [1, 0, 0], std: 0.001}]",
     "anchors[0].marker"),
    ("anchors: [{marker: 3, position: [0, 0, 0]}, {marker: 4, position: [1, 0, 0], std: 0.001}]", "anchors[0].std"),
    ("anchors: [{marker: 3, position: [0, 0, 0], std: 0.001, rotation: [0, 0, 0, 1]}]", "anchors[0].rotation_std_deg"),
    ("anchors: [{marker: 3, position: [0, 0, 0], std: 0.001, pos: 1}, {marker: 4, position: [1, 0, 0], std: 0.001}]",
     "anchors[0].pos"),
    ("anchors: [{marker: 3, position: [0, 0, 0], std: 0.001}, {marker: 3, position: [1, 0, 0], std: 0.001}]",
     "anchors"),
    ("anker: []", "anker"),
])
def test_bad_files_name_the_file_and_key(tmp_path, body, key):
    path = tmp_path / "bad_anchors.yaml"
    path.write_text(body + "\n")
    with pytest.raises(ConfigError) as err:
        load_anchors(str(path))
    assert err.value.key == key and str(path) in str(err.value), str(err.value)


# --- fit -------------------------------------------------------------------------------------------

def test_fit_recovers_the_frame_from_three_points():
    true = _markers()
    T_map_W = geo.make_transform(geo.rotation_from_rvec([0.02, -0.01, 1.1]), [3.0, -2.0, 0.1])
    survey = noisy_anchors({m: T_map_W @ T for m, T in true.items()}, [10, 11, 12], 1e-9, seed=1)
    fit = fit_frame(survey, true)
    assert fit.kind == "points"
    assert geo.pose_distance(fit.T_map_W, T_map_W)[0] < 1e-6
    assert geo.pose_distance(fit.T_map_W, T_map_W)[1] < 1e-7


def test_two_points_fix_position_and_heading_with_the_robot_up():
    true = _markers()
    T_map_W = _yaw(0.7) @ geo.make_transform(None, [1.0, 2.0, 0.0])
    survey = noisy_anchors({m: T_map_W @ T for m, T in true.items()}, [10, 11], 1e-9, seed=1)
    fit = fit_frame(survey, true)
    assert fit.kind == "points_level"
    assert np.allclose(fit.T_map_W[:3, 2], [0, 0, 1]), "the robot's z stays up with 2 anchors"
    assert geo.pose_distance(fit.T_map_W, T_map_W)[0] < 1e-6


def test_fit_weights_by_the_survey_std():
    """A point surveyed 100x worse than the others barely moves the fit when it is wrong by 5 cm."""
    true = _markers(n=4)
    pts = {m: T.copy() for m, T in true.items()}
    survey = noisy_anchors(pts, [10, 11, 12, 13], 1e-9, seed=2)
    bad = survey.anchors[3]
    anchors = survey.anchors[:3] + [Anchor(bad.marker_id, bad.position + [0.05, 0, 0], np.full(3, 0.1))]
    fit = fit_frame(AnchorSet(anchors), true)
    assert geo.pose_distance(fit.T_map_W, np.eye(4))[0] < 2e-4, geo.pose_distance(fit.T_map_W, np.eye(4))
    equal = [Anchor(a.marker_id, a.position, np.full(3, 0.001)) for a in anchors]
    fit_eq = fit_frame(AnchorSet(equal), true)
    assert geo.pose_distance(fit_eq.T_map_W, np.eye(4))[0] > 5e-3, "with equal weights the bad point pulls"


def test_one_pose_anchor_fixes_the_frame():
    true = _markers()
    T_map_W = geo.make_transform(geo.rotation_from_rvec([0.1, 0.2, 0.3]), [1.0, 2.0, 3.0])
    T = T_map_W @ true[12]
    a = AnchorSet([Anchor(12, T[:3, 3], np.full(3, 1e-4), T[:3, :3], np.radians(0.01))])
    fit = fit_frame(a, true)
    assert geo.pose_distance(fit.T_map_W, T_map_W)[0] < 1e-9 and fit.kind == "pose"


def test_collinear_points_do_not_fix_the_plane():
    true = {m: geo.make_transform(None, [x, 0.0, 0.5]) for m, x in zip((1, 2, 3), (0.0, 2.0, 4.0))}
    a = noisy_anchors(true, [1, 2, 3], 1e-3, seed=0)
    assert frame_kind(a) == "points_level"


def test_missing_anchor_markers_are_left_out_until_too_few_remain():
    true = _markers(n=3)
    survey = noisy_anchors(true, [10, 11, 12], 1e-9, seed=0)
    fit = fit_frame(survey, {m: true[m] for m in (10, 11)})
    assert sorted(fit.residuals) == [10, 11]
    with pytest.raises(ConfigError):
        fit_frame(survey, {10: true[10]})


def test_check_flags_a_residual_beyond_the_limit():
    rep = {"source": "a.yaml", "points": [{"marker": 3, "residual": [0.01, 0, 0], "residual_sigmas": 10.0},
                                          {"marker": 4, "residual": [0.001, 0, 0], "residual_sigmas": 1.0}]}
    problems = check_anchor_report(rep, 5.0)
    assert len(problems) == 1 and "marker 3" in problems[0] and "a.yaml" in problems[0]


# --- bundle adjustment priors -----------------------------------------------------------------------

def _anchored_problem(seed=0, noise=0.0):
    prob, truth = _problem(seed=seed, noise=noise, per=200)
    prob.fixed_station = None
    return prob, truth


def test_prior_jacobian_matches_finite_differences():
    prob, (T_mk, T_st, _) = _anchored_problem()
    rng = np.random.default_rng(4)
    prob.priors = MarkerPriors(position_marker=[0, 2, 3], position=T_mk[[0, 2, 3], :3, 3] + 0.01,
                               position_std=np.full((3, 3), 0.002), rotation_marker=[1],
                               rotation=geo.rotation_from_rvec([0.01, 0.02, 0.03])[None] @ T_mk[[1], :3, :3],
                               rotation_std=[0.01], level_station=[0, 2], level_sigma=0.01)
    for refine in (False, True):
        model = _Model(prob, BAOptions(refine_extrinsics=refine))
        x = rng.normal(0, 0.05, model.n_params)
        J = model.jacobian(x).toarray()
        h = 1e-6
        Jn = np.stack([(model.residuals(x + h * e) - model.residuals(x - h * e)) / (2 * h)
                       for e in np.eye(model.n_params)], axis=1)
        err = np.max(np.abs(J - Jn)) / np.max(np.abs(J))
        assert err < 1e-6, f"relative Jacobian error {err:.2e} (refine_extrinsics {refine})"


@pytest.mark.parametrize("solver", ["lm", "trf"])
def test_priors_are_the_gauge_and_move_the_map(solver):
    """Without a fixed station, surveyed positions shifted by 2 cm (exact geometry otherwise) put the
    solution 2 cm over: the adjustment follows the priors; ignoring them it would stay put."""
    prob, (T_mk, T_st, _) = _anchored_problem()
    shift = np.array([0.02, -0.01, 0.005])
    ids = [0, 2, 4]
    prob.priors = MarkerPriors(position_marker=ids, position=T_mk[ids, :3, 3] + shift,
                               position_std=np.full((3, 3), 0.001))
    res = bundle_adjust(prob, BAOptions(solver=solver))
    moved = res.T_W_markers[:, :3, 3] - T_mk[:, :3, 3]
    assert np.allclose(moved, shift, atol=2e-4), f"marker shifts {moved} (expected {shift}, {solver})"
    assert res.rms_px_after < 1e-3, f"RMS {res.rms_px_after:.2e} px"
    assert res.marker_cov is not None and np.all(np.isfinite(res.marker_cov))


def test_no_gauge_without_priors():
    prob, _ = _anchored_problem()
    with pytest.raises(GeometryError):
        bundle_adjust(prob, BAOptions(refine_extrinsics=False))


def test_priors_weighted_against_the_images():
    """Surveyed points inconsistent with the images by 1 cm: their residuals share the misfit by
    weight (a loose survey point ends up far from its survey value, tight ones near theirs)."""
    prob, (T_mk, _, _) = _anchored_problem()
    ids = [0, 2, 4, 5]
    pos = T_mk[ids, :3, 3].copy()
    pos[3] += [0.01, 0.0, 0.0]
    std = np.array([[0.001] * 3, [0.001] * 3, [0.001] * 3, [0.02] * 3])
    prob.priors = MarkerPriors(position_marker=ids, position=pos, position_std=std)
    res = bundle_adjust(prob, BAOptions())
    r = res.T_W_markers[ids, :3, 3] - pos
    assert np.linalg.norm(r[3]) > 0.008, f"the loose point kept its misfit: {r[3]}"
    assert np.max(np.linalg.norm(r[:3], axis=1)) < 0.002, f"the tight points stay near their survey: {r[:3]}"
