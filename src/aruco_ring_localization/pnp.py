"""Camera pose from marker corners: single-marker IPPE (both solutions) and multi-point PnP.

The one place where poses are solved from corners: mapping, detection and localization call it.

All solvers work on *undistorted normalised* image coordinates (``CameraModel.normalize``), so
the three distortion models (plumb_bob, rational_polynomial, equidistant) are handled the same
way and OpenCV only ever sees an ideal pinhole camera (K = I, no distortion).

* :func:`solve_marker_ippe` — one square marker: OpenCV's IPPE_SQUARE returns the two poses of
  the planar ambiguity (a marker seen nearly face-on can "flip" about an axis in the image
  plane). Both are returned, best first, with the ambiguity ratio ``err_best / err_second``
  (close to 1: ambiguous; close to 0: the best solution is clearly right). Errors in raw
  pixels, through the full camera model. Optionally refined by Levenberg-Marquardt, and
  optionally also from the *mirror* of each IPPE pose about the line of sight (``mirror``).
* :func:`solve_marker_ippe_undistorted` — the same on corners that are already undistorted
  (e.g. the mean of several detections' normalised corners), errors in undistorted pixels (the
  ideal pinhole camera with the camera's focal lengths).
* :func:`solve_points` — any number (>= 4) of 3D-2D correspondences (several markers at once):
  SQPNP (a global solver, no initial guess needed) or ITERATIVE from ``T_init``, then a
  Levenberg-Marquardt refinement of the reprojection error.
* :func:`reprojection_errors` — per-point pixel errors of a pose.

Poses are ``T_cam_obj`` (4x4): ``p_cam = T_cam_obj @ p_obj``; the object is a marker (its own
frame, :func:`markers.marker_corners`) or the map (corners in the map frame).
"""
from __future__ import annotations

import logging
import math
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
# Mapping's refinement from IPPE and mirror seeds (more iterations: a mirror seed starts far).
_LM_CRITERIA_MIRROR = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)


@dataclass(frozen=True)
class MarkerPoseCandidates:
    """The poses of the planar ambiguity of one square marker, best first.

    Attributes:
        poses: list of (4, 4) ``T_cam_marker``, sorted by increasing reprojection error
            (one or two entries).
        errors: RMS reprojection error of each pose over the 4 corners, pixels (raw pixels from
            :func:`solve_marker_ippe`, undistorted from :func:`solve_marker_ippe_undistorted`).
        ambiguity: ``errors[0] / errors[1]`` in [0, 1] with two poses (1.0 when both fit
            exactly: the image cannot tell them apart); 0.0 with one pose (the other solution
            is behind the camera, or every refinement converged to this one). Small values are
            reliable, values near 1 mean the pose may be flipped.
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

    @property
    def T_cam_marker_alt(self) -> Optional[np.ndarray]:
        """The other pose of the ambiguity (4, 4), or None when there is only one."""
        return self.poses[1] if len(self.poses) > 1 else None


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


def undistorted_rms(T_cam_obj: np.ndarray, object_pts: np.ndarray, xy: np.ndarray, focal) -> float:
    """RMS reprojection error in undistorted pixels of ``object_pts`` (N, 3) against normalised
    observations ``xy`` (N, 2): the ideal pinhole camera with focal lengths ``focal`` (fx, fy).
    Infinite when a point is at or behind the camera."""
    p = object_pts @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    if p[:, 2].min() <= 1e-9:
        return float("inf")
    d = (p[:, :2] / p[:, 2:3] - xy) * focal
    return math.sqrt(float(np.einsum("ij,ij->", d, d)) / len(d))


def mirror_about_ray(R: np.ndarray, t: np.ndarray) -> Optional[np.ndarray]:
    """The other rotation of the planar ambiguity of a marker at ``t`` with rotation ``R``: its
    normal reflected about the line of sight (None when the normal lies along it: face-on)."""
    u = t / np.linalg.norm(t)
    n1 = R[:, 2]
    n2 = 2.0 * (n1 @ u) * u - n1
    axis = np.array([n1[1] * n2[2] - n1[2] * n2[1], n1[2] * n2[0] - n1[0] * n2[2], n1[0] * n2[1] - n1[1] * n2[0]])
    s = float(np.linalg.norm(axis))
    if s < 1e-9:
        return None
    return _rotation(axis / s * np.arctan2(s, float(n1 @ n2))) @ R


def _rotation(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a finite rotation vector (OpenCV's Rodrigues: the per-candidate work of
    the mapping's thousands of IPPE solves, where scipy's Rotation costs 10x more per call)."""
    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]


def _lm(obj: np.ndarray, pts: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, criteria) -> Tuple[np.ndarray, np.ndarray]:
    return cv2.solvePnPRefineLM(obj, pts, _EYE3, _NO_DIST, rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy(),
                                criteria=criteria)


def _marker_candidates(xy: np.ndarray, size: float, rms, refine: bool, mirror: bool, min_separation: float,
                       where: str) -> MarkerPoseCandidates:
    """IPPE on normalised corners ``xy`` (4, 2), scored by ``rms(T_cam_marker) -> px``."""
    obj = marker_corners(size)
    pts = np.ascontiguousarray(xy.reshape(-1, 1, 2))
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, pts, _EYE3, _NO_DIST, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    except cv2.error as exc:
        raise MeasurementError(f"IPPE failed on corners {where}: {exc}") from None
    if not n:
        raise MeasurementError(f"IPPE found no pose for corners {where}")
    solutions = [(r.reshape(3), t.reshape(3)) for r, t in zip(rvecs[:n], tvecs[:n])]
    if mirror:
        # Each IPPE pose and its mirror about the line of sight seed Levenberg-Marquardt: OpenCV's
        # IPPE alone can miss the exact pose of a small, off-axis, nearly face-on marker by tens
        # of degrees while reprojecting within 0.1 px.
        starts = []
        for r, t in solutions:
            starts.append((r, t))
            Rm = mirror_about_ray(_rotation(r), t)
            if Rm is not None:
                starts.append((cv2.Rodrigues(Rm)[0].reshape(3), t))
        solutions = [_lm(obj, pts, r, t, _LM_CRITERIA_MIRROR) for r, t in starts]
    elif refine:
        refined = [_lm(obj, pts, r, t, _LM_CRITERIA) for r, t in solutions]
        # On a nearly face-on marker the refinement can pull both solutions into one minimum,
        # hiding the ambiguity: then the unrefined pair is kept.
        if len(refined) < 2 or geo.rotation_angle(geo.rotation_from_rvec(refined[0][0]).T
                                                  @ geo.rotation_from_rvec(refined[1][0])) > min_separation:
            solutions = refined
    scored = []
    for rvec, tvec in solutions:
        rvec, tvec = np.asarray(rvec, dtype=np.float64).reshape(3), np.asarray(tvec, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            continue
        T = np.eye(4)
        T[:3, :3] = _rotation(rvec)
        T[:3, 3] = tvec
        if T[2, 3] <= 0.0:
            continue  # behind the camera: not a physical solution
        scored.append((rms(T), T))
    if not scored:
        raise MeasurementError(f"IPPE found no pose in front of the camera for corners {where}")
    scored.sort(key=lambda st: st[0])
    keep = scored[:1]
    for cand in scored[1:]:
        if not mirror or geo.rotation_angle(cand[1][:3, :3].T @ keep[0][1][:3, :3]) > min_separation:
            keep.append(cand)
            break
    errors = [float(e) for e, _ in keep]
    if len(keep) > 1:
        ambiguity = errors[0] / errors[1] if errors[1] > 0.0 else 1.0
    else:
        ambiguity = 0.0
    return MarkerPoseCandidates(poses=[T for _, T in keep], errors=errors, ambiguity=float(ambiguity))


def solve_marker_ippe(corners_px, size: float, model: CameraModel, refine: bool = False,
                      normalized: Optional[np.ndarray] = None, mirror: bool = False,
                      min_separation: float = np.radians(0.5)) -> MarkerPoseCandidates:
    """Both poses of one square marker from its 4 detected corners (IPPE_SQUARE).

    Args:
        corners_px: (4, 2) raw pixels in aruco_detect order (top-left, top-right,
            bottom-right, bottom-left).
        size: side of the black square, m.
        model: the camera that saw it.
        refine: polish each solution by Levenberg-Marquardt. Off by default: IPPE is already
            close to optimal for a square, and on a nearly face-on marker the refinement can
            pull both solutions into the same minimum, hiding the ambiguity; when that happens
            (solutions closer than ``min_separation``) the unrefined pair is kept.
        normalized: optional (4, 2) ``model.normalize(corners_px)`` when the caller has it.
        mirror: refine from each IPPE pose *and* its mirror about the line of sight (implies
            the refinement), keep the best and the best other pose more than ``min_separation``
            away; when every start converges to one pose, that one alone (ambiguity 0).
        min_separation: two solutions closer than this (rad) are one.

    Returns:
        :class:`MarkerPoseCandidates` with ``T_cam_marker`` poses, best first, errors in raw px.

    Raises:
        MeasurementError: malformed corners or no solution.
    """
    px = _check_pixels(corners_px, 4, "corners_px")
    xy = model.normalize(px) if normalized is None else _check_pixels(normalized, 4, "normalized")
    obj = marker_corners(size)
    return _marker_candidates(xy, size, lambda T: _rms(reprojection_errors(T, obj, px, model)),
                              refine, mirror, min_separation, str(px.tolist()))


def solve_marker_ippe_undistorted(xy, size: float, focal, refine: bool = False, mirror: bool = False,
                                  min_separation: float = np.radians(0.5)) -> MarkerPoseCandidates:
    """:func:`solve_marker_ippe` on already undistorted corners, errors in undistorted pixels.

    For corners that exist only undistorted, e.g. the mean of several detections' normalised
    corners (mapping divides the noise of a still robot's detections this way before solving).

    Args:
        xy: (4, 2) undistorted normalised corners (``CameraModel.normalize``), aruco_detect order.
        size: side of the black square, m.
        focal: (fx, fy) of the camera, px: errors are those of the ideal pinhole camera.
        refine, mirror, min_separation: as in :func:`solve_marker_ippe`.
    """
    xy = _check_pixels(xy, 4, "xy")
    f = np.asarray(focal, dtype=np.float64).reshape(2)
    obj = marker_corners(size)
    return _marker_candidates(xy, size, lambda T: undistorted_rms(T, obj, xy, f), refine, mirror, min_separation,
                              f"(normalised) {xy.tolist()}")


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
