"""Camera pose from marker corners: single-marker IPPE (both solutions) and multi-point PnP.

All solvers work on *undistorted normalised* image coordinates (``CameraModel.normalize``), so
the three distortion models (plumb_bob, rational_polynomial, equidistant) are handled the same
way and OpenCV only ever sees an ideal pinhole camera (K = I, no distortion). Reprojection
errors are always reported in raw pixels, through the full camera model.

* :func:`solve_marker_ippe` — one square marker: OpenCV's IPPE_SQUARE returns the two poses of
  the planar ambiguity (a marker seen nearly face-on can "flip" about an axis in the image
  plane). Both are returned, best first, with the ambiguity ratio ``err_best / err_second``
  (close to 1: ambiguous; close to 0: the best solution is clearly right).
* :func:`solve_points` — any number (>= 4) of 3D-2D correspondences (several markers at once):
  SQPNP (a global solver, no initial guess needed) or ITERATIVE from ``T_init``, then a
  Levenberg-Marquardt refinement of the reprojection error.
* :func:`reprojection_errors` — per-point pixel errors of a pose.

Poses are ``T_cam_obj`` (4x4): ``p_cam = T_cam_obj @ p_obj``; the object is a marker (its own
frame, :func:`markers.marker_corners`) or the map (corners in the map frame).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import List, Optional, Tuple

import cv2
import numpy as np

from . import geometry as geo
from .camera import CameraModel
from .errors import GeometryError, MeasurementError
from .markers import marker_corners

logger = logging.getLogger(__name__)

_EYE3 = np.eye(3)
_NO_DIST = np.zeros(5)
# Levenberg-Marquardt refinement on normalised coordinates: errors are ~1e-4 (0.1 px / 800 px).
_LM_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-12)


@dataclass(frozen=True)
class MarkerPoseCandidates:
    """The two IPPE poses of one square marker, best first.

    Attributes:
        poses: list of (4, 4) ``T_cam_marker``, sorted by increasing reprojection error
            (one or two entries).
        errors: RMS reprojection error of each pose over the 4 corners, raw pixels.
        ambiguity: ``errors[0] / errors[1]`` (1.0 when only one solution exists or both fit
            equally: the pose cannot be told from the image alone; small values are reliable).
    """

    poses: List[np.ndarray]
    errors: List[float]
    ambiguity: float

    @property
    def T_cam_marker(self) -> np.ndarray:
        """The best pose (4, 4)."""
        return self.poses[0]

    @property
    def error(self) -> float:
        """RMS reprojection error of the best pose, pixels."""
        return self.errors[0]


def _check_pixels(px, n: Optional[int], name: str) -> np.ndarray:
    arr = np.asarray(px, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2 or (n is not None and arr.shape[0] != n):
        want = f"({n}, 2)" if n is not None else "(N, 2)"
        raise MeasurementError(f"{name}: expected shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise MeasurementError(f"{name}: contains NaN or infinite values")
    return arr


def reprojection_errors(T_cam_obj, object_pts, image_px, model: CameraModel) -> np.ndarray:
    """Pixel distance (N,) between ``image_px`` (raw pixels) and the projection of ``object_pts``.

    Args:
        T_cam_obj: (4, 4) pose of the object frame in the camera's optical frame.
        object_pts: (N, 3) points in the object frame, m.
        image_px: (N, 2) observed raw (distorted) pixels.
        model: the camera.

    Points that fall behind the camera get an infinite error.
    """
    obj = np.asarray(object_pts, dtype=np.float64).reshape(-1, 3)
    px = np.asarray(image_px, dtype=np.float64).reshape(-1, 2)
    pred = model.project(geo.transform_points(T_cam_obj, obj))
    err = np.linalg.norm(pred - px, axis=1)
    err[~np.isfinite(err)] = np.inf
    return err


def _rms(errors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(errors ** 2))) if errors.size else 0.0


def solve_marker_ippe(corners_px, size: float, model: CameraModel, refine: bool = False,
                      normalized: Optional[np.ndarray] = None) -> MarkerPoseCandidates:
    """Both poses of one square marker from its 4 detected corners (IPPE_SQUARE).

    Args:
        corners_px: (4, 2) raw pixels in aruco_detect order (top-left, top-right,
            bottom-right, bottom-left).
        size: side of the black square, m.
        model: the camera that saw it.
        refine: polish each solution by Levenberg-Marquardt. Off by default: IPPE is already
            close to optimal for a square, and on a nearly face-on marker the refinement can
            pull both solutions into the same minimum, hiding the ambiguity; when that happens
            (solutions closer than 0.5 deg) the unrefined pair is kept.
        normalized: optional (4, 2) ``model.normalize(corners_px)`` when the caller has it.

    Returns:
        :class:`MarkerPoseCandidates` with ``T_cam_marker`` poses, best first.

    Raises:
        MeasurementError: malformed corners or no solution.
    """
    px = _check_pixels(corners_px, 4, "corners_px")
    obj = marker_corners(size)
    xy = (model.normalize(px) if normalized is None else np.asarray(normalized, dtype=np.float64)).reshape(-1, 1, 2)
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, xy, _EYE3, _NO_DIST, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    except cv2.error as exc:
        raise MeasurementError(f"IPPE failed on corners {px.tolist()}: {exc}") from None
    if not n:
        raise MeasurementError(f"IPPE found no pose for corners {px.tolist()}")
    solutions = list(zip(rvecs[:n], tvecs[:n]))
    if refine:
        refined = [cv2.solvePnPRefineLM(obj, xy, _EYE3, _NO_DIST, r.copy(), t.copy(), criteria=_LM_CRITERIA)
                   for r, t in solutions]
        if len(refined) < 2 or geo.rotation_angle(
                geo.rotation_from_rvec(refined[0][0]).T @ geo.rotation_from_rvec(refined[1][0])) > np.radians(0.5):
            solutions = refined
    poses, errors = [], []
    for rvec, tvec in solutions:
        try:
            T = geo.transform_from_rvec_tvec(rvec, tvec)
        except GeometryError:
            continue
        if T[2, 3] <= 0.0:
            continue  # behind the camera: not a physical solution
        poses.append(T)
        errors.append(_rms(reprojection_errors(T, obj, px, model)))
    if not poses:
        raise MeasurementError(f"IPPE found no pose in front of the camera for corners {px.tolist()}")
    order = np.argsort(errors)
    poses = [poses[i] for i in order]
    errors = [float(errors[i]) for i in order]
    if len(errors) > 1 and errors[1] > 0.0:
        ambiguity = errors[0] / errors[1]
    else:
        ambiguity = 1.0
    return MarkerPoseCandidates(poses=poses, errors=errors, ambiguity=float(ambiguity))


def solve_points(object_pts, image_px, model: CameraModel, T_init: Optional[np.ndarray] = None,
                 normalized: Optional[np.ndarray] = None) -> Tuple[np.ndarray, float]:
    """Camera pose from N >= 4 3D-2D correspondences (e.g. all corners of several markers).

    Args:
        object_pts: (N, 3) points in the object frame (the map), m.
        image_px: (N, 2) their raw pixels.
        model: the camera.
        T_init: optional (4, 4) initial ``T_cam_obj``; without it SQPNP (global) is used. With
            it, ITERATIVE (Levenberg-Marquardt from the guess) and no separate refinement.
        normalized: optional (N, 2) ``model.normalize(image_px)`` when the caller has it.

    Returns:
        (``T_cam_obj`` (4, 4), RMS reprojection error in pixels).

    Raises:
        MeasurementError: fewer than 4 points, malformed input or no solution.
    """
    obj = np.asarray(object_pts, dtype=np.float64)
    if obj.ndim != 2 or obj.shape[1] != 3 or not np.all(np.isfinite(obj)):
        raise MeasurementError(f"object_pts: expected finite (N, 3), got shape {obj.shape}")
    px = _check_pixels(image_px, obj.shape[0], "image_px")
    if obj.shape[0] < 4:
        raise MeasurementError(f"PnP needs at least 4 points, got {obj.shape[0]}")
    xy = (model.normalize(px) if normalized is None else np.asarray(normalized, dtype=np.float64)).reshape(-1, 1, 2)
    try:
        if T_init is not None:
            rvec0, tvec0 = geo.rvec_tvec_from_transform(T_init)
            ok, rvec, tvec = cv2.solvePnP(obj, xy, _EYE3, _NO_DIST, rvec0.reshape(3, 1).copy(),
                                          tvec0.reshape(3, 1).copy(), useExtrinsicGuess=True,
                                          flags=cv2.SOLVEPNP_ITERATIVE)
        else:
            ok, rvec, tvec = cv2.solvePnP(obj, xy, _EYE3, _NO_DIST, flags=cv2.SOLVEPNP_SQPNP)
            if ok:
                rvec, tvec = cv2.solvePnPRefineLM(obj, xy, _EYE3, _NO_DIST, rvec, tvec, criteria=_LM_CRITERIA)
        if not ok:
            raise MeasurementError(f"PnP found no pose for {obj.shape[0]} points")
    except cv2.error as exc:
        raise MeasurementError(f"PnP failed on {obj.shape[0]} points: {exc}") from None
    try:
        T = geo.transform_from_rvec_tvec(rvec, tvec)
    except GeometryError as exc:
        raise MeasurementError(f"PnP returned an invalid pose: {exc}") from None
    err = reprojection_errors(T, obj, px, model)
    return T, _rms(err)
