"""pnp.py: single-marker IPPE (both solutions) and multi-point PnP on synthetic projections."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.camera import default_model_for_tests
from aruco_ring_localization.errors import MeasurementError
from aruco_ring_localization.markers import marker_corners
from aruco_ring_localization.pnp import (mirror_about_ray, reprojection_errors, solve_marker_ippe,
                                         solve_marker_ippe_undistorted, solve_points, undistorted_rms)

MODELS = ["plumb_bob", "rational_polynomial", "equidistant"]


def _marker_pose(distance: float, yaw_deg: float, off=(0.1, -0.05)) -> np.ndarray:
    """T_cam_marker: marker ``distance`` m ahead, facing the camera, turned ``yaw_deg`` about its y."""
    # Marker z points back at the camera: marker frame = camera frame rotated 180 deg about y.
    R = geo.matrix_from_rpy(0.0, np.pi + np.radians(yaw_deg), 0.0)
    return geo.make_transform(R, [off[0], off[1], distance])


def _pose_error(T_a, T_b):
    d, a = geo.pose_distance(T_a, T_b)
    return d, np.degrees(a)


@pytest.mark.parametrize("model_name", MODELS)
def test_ippe_best_solution_matches_truth(model_name):
    model = default_model_for_tests(model_name)
    T = _marker_pose(2.0, 35.0)
    px = model.project(geo.transform_points(T, marker_corners(0.2)))
    cand = solve_marker_ippe(px, 0.2, model)
    d, a = _pose_error(cand.T_cam_marker, T)
    assert d < 1e-6 and a < 1e-5, f"{model_name}: best IPPE pose off by {d:.2e} m, {a:.2e} deg"
    assert cand.error < 1e-4, f"noise-free reprojection error {cand.error:.2e} px"
    assert len(cand.poses) == 2, f"expected both IPPE solutions, got {len(cand.poses)}"
    assert cand.errors[0] <= cand.errors[1]
    assert cand.ambiguity < 0.01, f"oblique marker should be unambiguous, ratio {cand.ambiguity:.3f}"


def test_ippe_face_on_far_marker_is_ambiguous_and_second_solution_is_a_flip():
    model = default_model_for_tests()
    rng = np.random.default_rng(3)
    T = _marker_pose(3.0, 3.0, off=(0.0, 0.0))
    px = model.project(geo.transform_points(T, marker_corners(0.2))) + rng.normal(0, 0.3, (4, 2))
    cand = solve_marker_ippe(px, 0.2, model)
    assert len(cand.poses) == 2
    assert cand.ambiguity > 0.2, f"small face-on marker should be ambiguous, ratio {cand.ambiguity:.3f}"
    # The two solutions share the position (roughly) and differ by a flip of the normal.
    d, a = _pose_error(cand.poses[0], cand.poses[1])
    assert d < 0.1 and a > 2.0, f"second solution: {d:.3f} m, {a:.2f} deg from the first"
    # Face-on, the orientation is poorly observable (~10 deg here) but the position is not.
    pos_err = max(np.linalg.norm(P[:3, 3] - T[:3, 3]) for P in cand.poses)
    assert pos_err < 0.05, f"IPPE positions {pos_err:.3f} m from the truth"
    refined = solve_marker_ippe(px, 0.2, model, refine=True)
    d, a = _pose_error(refined.poses[0], refined.poses[1])
    assert a > 2.0, f"refinement merged the two solutions ({a:.2f} deg apart)"


@pytest.mark.parametrize("model_name", MODELS)
def test_solve_points_several_markers(model_name):
    model = default_model_for_tests(model_name)
    rng = np.random.default_rng(7)
    T_cam_map = geo.make_transform(geo.matrix_from_rpy(-np.pi / 2, 0.0, -np.pi / 2) @ geo.rot_z(0.2),
                                   [0.3, 0.8, 3.0])
    # Three markers on a "wall" 3 m ahead of the camera, in the map frame.
    T_map_cam = geo.inverse(T_cam_map)
    obj = []
    for dx in (-1.0, 0.0, 0.9):
        p_cam = np.array([dx, 0.1 * dx, 3.0])
        T_cam_m = geo.make_transform(geo.matrix_from_rpy(0.0, np.pi + 0.3 * dx, 0.0), p_cam)
        obj.append(geo.transform_points(T_map_cam @ T_cam_m, marker_corners(0.2)))
    obj = np.vstack(obj)
    px_true = model.project(geo.transform_points(T_cam_map, obj))
    T, rms = solve_points(obj, px_true, model)
    d, a = _pose_error(T, T_cam_map)
    assert d < 1e-6 and a < 1e-5 and rms < 1e-4, f"{model_name}: {d:.2e} m {a:.2e} deg rms {rms:.2e}"
    px = px_true + rng.normal(0, 0.3, px_true.shape)
    T_guess = geo.se3_perturb(T_cam_map, [0.02, -0.01, 0.03, 0.05, 0.05, -0.1])
    T2, rms2 = solve_points(obj, px, model, T_init=T_guess)
    # A wall of markers 3 m away: the camera position along the wall is the weak direction.
    cam_pos_err = np.linalg.norm(geo.inverse(T2)[:3, 3] - T_map_cam[:3, 3])
    a = _pose_error(T2, T_cam_map)[1]
    assert cam_pos_err < 0.05 and a < 1.0, f"{model_name}: noisy PnP off by {cam_pos_err:.4f} m {a:.3f} deg"
    assert 0.1 < rms2 < 0.5, f"rms {rms2:.3f} px for 0.3 px noise"
    errs = reprojection_errors(T2, obj, px, model)
    assert errs.shape == (12,) and np.isclose(np.sqrt(np.mean(errs ** 2)), rms2)


def test_bad_inputs_raise_measurement_error():
    model = default_model_for_tests()
    with pytest.raises(MeasurementError, match="corners_px"):
        solve_marker_ippe(np.zeros((3, 2)), 0.2, model)
    with pytest.raises(MeasurementError, match="NaN"):
        solve_marker_ippe(np.full((4, 2), np.nan), 0.2, model)
    with pytest.raises(MeasurementError, match="at least 4"):
        solve_points(np.zeros((3, 3)), np.zeros((3, 2)), model)


def test_reprojection_error_behind_camera_is_infinite():
    model = default_model_for_tests()
    err = reprojection_errors(np.eye(4), np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]),
                              np.array([[640.5, 480.5], [640.5, 480.5]]), model)
    assert np.isinf(err[0]) and err[1] < 1e-9, f"errors {err}"


# --- the single-marker API that mapping, detection and localization share ----------------------

PINHOLE = default_model_for_tests("plumb_bob", D=np.zeros(5))


def test_far_face_on_marker_returns_both_ippe_solutions_in_every_mode():
    # 0.2 m at 8 m, 2 deg off face-on, 0.3 px noise: the two poses of the planar ambiguity
    # reproject within a fraction of a pixel of each other; every mode must keep both (measured:
    # ratio 0.95, 27 deg apart, positions 3 mm apart).
    model = default_model_for_tests()
    rng = np.random.default_rng(21)
    T = _marker_pose(8.0, 2.0, off=(0.3, 0.1))
    px = model.project(geo.transform_points(T, marker_corners(0.2))) + rng.normal(0, 0.3, (4, 2))
    xy = model.normalize(px)
    for name, cand in [("plain", solve_marker_ippe(px, 0.2, model)),
                       ("refined", solve_marker_ippe(px, 0.2, model, refine=True)),
                       ("mirror", solve_marker_ippe(px, 0.2, model, mirror=True)),
                       ("undistorted", solve_marker_ippe_undistorted(xy, 0.2, [model.fx, model.fy])),
                       ("undistorted mirror", solve_marker_ippe_undistorted(xy, 0.2, [model.fx, model.fy],
                                                                            mirror=True))]:
        assert len(cand.poses) == 2, f"{name}: {len(cand.poses)} solution(s)"
        assert cand.T_cam_marker_alt is cand.poses[1]
        assert 0.3 < cand.ambiguity <= 1.0, f"{name}: ambiguity {cand.ambiguity:.3f} for a far face-on marker"
        d, a = _pose_error(cand.poses[0], cand.poses[1])
        assert d < 0.05 and a > 2.0, f"{name}: second solution {d:.3f} m, {a:.2f} deg from the first"


def test_ambiguity_is_a_ratio_in_unit_interval_and_errors_are_sorted():
    rng = np.random.default_rng(22)
    model = default_model_for_tests("rational_polynomial")
    for _ in range(60):
        T = _marker_pose(rng.uniform(0.5, 10.0), rng.uniform(-70, 70), off=rng.uniform(-0.5, 0.5, 2))
        px = model.project(geo.transform_points(T, marker_corners(0.2))) + rng.normal(0, 0.5, (4, 2))
        for cand in (solve_marker_ippe(px, 0.2, model), solve_marker_ippe(px, 0.2, model, refine=True),
                     solve_marker_ippe(px, 0.2, model, mirror=True)):
            assert 0.0 <= cand.ambiguity <= 1.0, f"ambiguity {cand.ambiguity}"
            assert list(cand.errors) == sorted(cand.errors)
            if len(cand.poses) == 2:
                assert cand.ambiguity == pytest.approx(cand.errors[0] / cand.errors[1])
            else:
                assert cand.ambiguity == 0.0 and cand.T_cam_marker_alt is None
            for P in cand.poses:
                geo.validate_transform(P)
                assert P[2, 3] > 0.0, "a pose behind the camera"


def test_undistorted_errors_equal_raw_errors_without_distortion():
    # With no lens distortion (and no skew) undistorted and raw pixels are the same pixels.
    rng = np.random.default_rng(23)
    T = _marker_pose(3.0, 25.0)
    px = PINHOLE.project(geo.transform_points(T, marker_corners(0.2))) + rng.normal(0, 0.4, (4, 2))
    raw = solve_marker_ippe(px, 0.2, PINHOLE, mirror=True)
    und = solve_marker_ippe_undistorted(PINHOLE.normalize(px), 0.2, [PINHOLE.fx, PINHOLE.fy], mirror=True)
    assert len(raw.poses) == len(und.poses)
    assert np.allclose(raw.errors, und.errors, rtol=1e-9, atol=1e-12), f"{raw.errors} vs {und.errors}"
    for a, b in zip(raw.poses, und.poses):
        assert np.abs(a - b).max() < 1e-12
    obj = marker_corners(0.2)
    assert undistorted_rms(T, obj, PINHOLE.normalize(px), [PINHOLE.fx, PINHOLE.fy]) == pytest.approx(
        np.sqrt(np.mean(reprojection_errors(T, obj, px, PINHOLE) ** 2)), rel=1e-9)
    behind = geo.make_transform(t=[0.0, 0.0, -3.0])
    assert undistorted_rms(behind, obj, PINHOLE.normalize(px), [PINHOLE.fx, PINHOLE.fy]) == float("inf")


def test_mirror_seeds_find_the_exact_pose_that_ippe_alone_misses():
    # A small marker far off-axis, nearly face-on: OpenCV's IPPE lands tens of degrees off while
    # reprojecting within 0.1 px; refined from the mirror seeds the exact pose is found.
    model = default_model_for_tests()
    T = geo.make_transform(np.diag([1.0, -1.0, -1.0]), [0.9, -0.3, 5.38])
    px = model.project(geo.transform_points(T, marker_corners(0.2)))
    plain = solve_marker_ippe(px, 0.2, model)
    mirror = solve_marker_ippe(px, 0.2, model, mirror=True, min_separation=np.radians(1.0))
    dp, dr = geo.pose_distance(mirror.T_cam_marker, T)
    assert dp < 1e-6 and dr < 1e-6, f"mirror mode: best pose off by {dp:.2e} m, {np.degrees(dr):.2e} deg"
    assert mirror.ambiguity < 0.01, f"ambiguity {mirror.ambiguity}"
    assert _pose_error(plain.T_cam_marker, T)[1] > 1.0, "plain IPPE now finds it: the mirror test lost its point"


def test_mirror_about_ray_reflects_the_normal_about_the_line_of_sight():
    rng = np.random.default_rng(24)
    for _ in range(50):
        T = _marker_pose(rng.uniform(1, 6), rng.uniform(-60, 60), off=rng.uniform(-1, 1, 2))
        R, t = T[:3, :3], T[:3, 3]
        Rm = mirror_about_ray(R, t)
        u = t / np.linalg.norm(t)
        geo.validate_rotation(Rm)
        # Same angle to the ray, the normal in the plane of the ray and the old normal.
        assert Rm[:, 2] @ u == pytest.approx(R[:, 2] @ u, abs=1e-12)
        assert abs(np.cross(R[:, 2], Rm[:, 2]) @ u) < 1e-12 or np.allclose(Rm[:, 2], R[:, 2])
        assert np.abs(mirror_about_ray(Rm, t) - R).max() < 1e-9, "mirroring twice is not the identity"
    face_on = geo.make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 3.0])
    assert mirror_about_ray(face_on[:3, :3], face_on[:3, 3]) is None


def test_undistorted_solver_rejects_malformed_corners():
    with pytest.raises(MeasurementError, match="xy"):
        solve_marker_ippe_undistorted(np.zeros((3, 2)), 0.2, [800.0, 800.0])
    with pytest.raises(MeasurementError, match="NaN"):
        solve_marker_ippe_undistorted(np.full((4, 2), np.nan), 0.2, [800.0, 800.0])
