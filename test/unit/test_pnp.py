"""pnp.py: single-marker IPPE (both solutions) and multi-point PnP on synthetic projections."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.camera import default_model_for_tests
from aruco_ring_localization.errors import MeasurementError
from aruco_ring_localization.markers import marker_corners
from aruco_ring_localization.pnp import reprojection_errors, solve_marker_ippe, solve_points

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
