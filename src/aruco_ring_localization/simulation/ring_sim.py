"""The ring simulator: what the 8 cameras see from a robot pose (:class:`RingSimulator`).

Two output modes share one visibility model:

* *corners mode* (:meth:`RingSimulator.observe`): the true projections of the visible markers'
  corners through each camera's real lens model, plus Gaussian pixel noise, as a
  :class:`~aruco_ring_localization.detections.RingFrame` (what 8 detectors would publish);
* *image mode* (:meth:`RingSimulator.render`): a rendered mono8 image per camera (see
  :mod:`.render`) that goes through the real detector.

A marker is visible in a camera when all four corners are in front of it (z > ``min_depth``) and
inside the image (``margin`` px from the border), its face points toward the camera (angle
between the face normal and the ray to the camera < ``max_view_angle``), it is within
``max_range`` and at least ``min_marker_px`` pixels wide (square root of the image area), no
nearer marker's printed sheet (marker + quiet zone) overlaps its sheet in the image, and no
occluding post (``posts[].occludes`` in the scene) hides any part of it.

The simulator knows the TRUE rig (:func:`perturb_ring` of the calibrated ring file): what the
estimators are given is the calibrated one, so no result relies on a perfect calibration.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Dict, List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np

from .. import geometry as geo
from ..detections import CameraFrame, MarkerObservation, RingFrame
from ..errors import ConfigError
from ..markers import marker_corners
from ..ring import CameraRing, RingCamera
from .params import CameraParams, RenderParams, RingParams
from .scene import Scene

logger = logging.getLogger(__name__)

PoseLike = Union[np.ndarray, Sequence[float]]


def perturb_ring(ring: CameraRing, trans_std: float = RingParams.calibration_trans_std,
                 rot_std_deg: float = RingParams.calibration_rot_std_deg, seed: int = 0) -> CameraRing:
    """The 'true' rig: every camera's extrinsics moved by a seeded calibration error.

    Each camera's optical frame is displaced by a Gaussian translation (``trans_std`` m per axis)
    and rotated by a Gaussian rotation vector (``rot_std_deg`` deg per axis), both expressed in
    the camera's own frame (so a rotation does not swing the camera about base_link).
    """
    rng = np.random.default_rng(seed)
    extr = {}
    for cam in ring.cameras:
        D = np.eye(4)
        D[:3, :3] = geo.rotation_from_rvec(rng.normal(0.0, np.radians(rot_std_deg), 3))
        D[:3, 3] = rng.normal(0.0, trans_std, 3)
        extr[cam.name] = cam.T_base_cam @ D
    return ring.with_extrinsics(extr)


def as_transform(pose: PoseLike) -> np.ndarray:
    """A 4x4 ``T_world_base``, or an SE(2) ``(x, y, yaw)`` made into one (on the floor)."""
    a = np.asarray(pose, dtype=np.float64)
    if a.shape == (4, 4):
        return a
    if a.shape == (3,):
        return geo.transform_from_se2(a[0], a[1], a[2])
    raise ValueError(f"expected a 4x4 pose or (x, y, yaw), got shape {a.shape}")


@dataclass(frozen=True)
class VisibleMarker:
    """One marker as a camera sees it (noise-free).

    Attributes:
        marker_id: ArUco id.
        corners: (4, 2) true raw-pixel corners, aruco_detect order.
        distance: camera centre to marker centre, m.
        view_angle: angle between the face normal and the ray to the camera, rad.
        pixel_size: square root of the marker's image area, px.
        T_cam_marker: (4, 4) true pose of the marker in the camera optical frame.
    """

    marker_id: int
    corners: np.ndarray
    distance: float
    view_angle: float
    pixel_size: float
    T_cam_marker: np.ndarray


class RingSimulator:
    """Simulate the ring's detections (corners mode) or images (image mode) in a scene.

    Args:
        scene: the hall.
        true_ring: the true rig (e.g. ``perturb_ring(CameraRing.load(...))``).
        pixel_noise: standard deviation of the corner noise in corners mode, px.
        max_range: markers farther than this (m) are not detected.
        seed: seed of the simulator's random generator (noise, rendering).
        min_marker_px: markers smaller than this (sqrt of image area, px) are not detected.
        max_view_angle: markers seen more obliquely than this (rad) are not detected.
        margin: corners must be this many pixels inside the image.
        min_depth: corners must be at least this far in front of the camera, m.
        render: image mode: blur, noise and supersampling of the renderer.
    """

    def __init__(self, scene: Scene, true_ring: CameraRing, pixel_noise: float = CameraParams.pixel_noise,
                 max_range: float = CameraParams.max_range, seed: int = 0, min_marker_px: float = 15.0,
                 max_view_angle: float = np.radians(75.0), margin: float = 3.0, min_depth: float = 0.05,
                 render: RenderParams = RenderParams()):
        self.scene = scene
        self.ring = true_ring
        self.pixel_noise = float(pixel_noise)
        self.max_range = float(max_range)
        self.min_marker_px = float(min_marker_px)
        self.max_view_angle = float(max_view_angle)
        self.margin = float(margin)
        self.min_depth = float(min_depth)
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self.render_params = render
        self._renderer = None
        ids = [m.marker_id for m in scene.markers]
        self._ids = np.array(ids, dtype=int)
        # Per marker: corners (4, 3) and printed sheet corners (4, 3) in the world, centre, normal.
        modules = _dictionary_modules(scene.dictionary)
        sheet_scale = (modules + 2.0 * scene.quiet_zone_modules) / modules
        self._corners_w = np.stack([m.corners_world() for m in scene.markers])
        self._sheet_w = np.stack([geo.transform_points(m.T_world_marker, marker_corners(m.size * sheet_scale))
                                  for m in scene.markers])
        self._centres_w = np.stack([m.T_world_marker[:3, 3] for m in scene.markers])
        self._normals_w = np.stack([m.normal for m in scene.markers])
        self._occluders = scene.occluders
        g = np.array([-0.5, 0.0, 0.5])
        probe = np.array([[u, v, 0.0] for u in g for v in g])
        self._probe_w = np.stack([geo.transform_points(m.T_world_marker, probe * m.size) for m in scene.markers])

    def move_marker(self, marker_id: int, translation, rotation_deg=(0.0, 0.0, 0.0)) -> None:
        """Move a marker in the world (a bump in the hall: the map does not know): by ``translation``
        (3, m, world axes) and ``rotation_deg`` (3, deg, rotation vector about its centre)."""
        ids = [m.marker_id for m in self.scene.markers]
        if int(marker_id) not in ids:
            raise ConfigError(f"marker {marker_id} is not in the scene (ids {sorted(ids)})", key="events")
        k = ids.index(int(marker_id))
        m = self.scene.markers[k]
        T = m.T_world_marker.copy()
        T[:3, :3] = geo.rotation_from_rvec(np.radians(np.asarray(rotation_deg, dtype=float))) @ T[:3, :3]
        T[:3, 3] = T[:3, 3] + np.asarray(translation, dtype=float).reshape(3)
        moved = replace(m, T_world_marker=T)
        self.scene.markers[k] = moved
        self._corners_w[k] = moved.corners_world()
        modules = _dictionary_modules(self.scene.dictionary)
        sheet_scale = (modules + 2.0 * self.scene.quiet_zone_modules) / modules
        self._sheet_w[k] = geo.transform_points(T, marker_corners(moved.size * sheet_scale))
        self._centres_w[k] = T[:3, 3]
        self._normals_w[k] = moved.normal
        self._renderer = None   # image mode draws the scene's markers: rebuild

    # --- geometry --------------------------------------------------------------------------------

    def T_world_cam(self, T_world_base: PoseLike, camera: Union[str, RingCamera]) -> np.ndarray:
        """True pose of a camera's optical frame in the world."""
        cam = self.ring[camera] if isinstance(camera, str) else camera
        return as_transform(T_world_base) @ cam.T_base_cam

    def camera_view(self, T_world_base: PoseLike, camera: Union[str, RingCamera]) -> List[VisibleMarker]:
        """The markers one camera sees from the robot pose, nearest first (noise-free)."""
        cam = self.ring[camera] if isinstance(camera, str) else camera
        T_world_cam = self.T_world_cam(T_world_base, cam)
        T_cam_world = geo.inverse(T_world_cam)
        R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
        corners_c = self._corners_w @ R.T + t            # (M, 4, 3)
        sheet_c = self._sheet_w @ R.T + t
        centres_c = self._centres_w @ R.T + t            # (M, 3)
        normals_c = self._normals_w @ R.T
        dist = np.linalg.norm(centres_c, axis=1)
        # Occluders: any sheet entirely in front of the camera (seen from the back or not).
        in_front_sheet = np.all(sheet_c[:, :, 2] > self.min_depth, axis=1)
        cos_a = -np.einsum("ij,ij->i", normals_c, centres_c) / np.maximum(dist, 1e-9)
        angles = np.arccos(np.clip(cos_a, -1.0, 1.0))
        ok = (np.all(corners_c[:, :, 2] > self.min_depth, axis=1) & (dist <= self.max_range)
              & (angles < self.max_view_angle))
        candidates = []
        idx = np.flatnonzero(ok)
        if idx.size:
            pxs = cam.model.project(corners_c[idx].reshape(-1, 3)).reshape(-1, 4, 2)
            inside = cam.model.in_image(pxs.reshape(-1, 2), self.margin).reshape(-1, 4).all(axis=1)
            for k, px, good in zip(idx, pxs, inside):
                if not good:
                    continue
                size = float(np.sqrt(_polygon_area(px)))
                if size >= self.min_marker_px:
                    candidates.append((k, px, float(angles[k]), size))
        out = []
        for k, px, angle, size in candidates:
            if self._occluded(k, sheet_c, in_front_sheet, dist) or self._behind_post(k, T_world_cam):
                continue
            T_cam_marker = T_cam_world @ self.scene.markers[k].T_world_marker
            out.append(VisibleMarker(int(self._ids[k]), px, float(dist[k]), angle, size, T_cam_marker))
        out.sort(key=lambda v: v.distance)
        return out

    def _occluded(self, k: int, sheet_c: np.ndarray, in_front: np.ndarray, dist: np.ndarray) -> bool:
        """True when a nearer marker's sheet overlaps marker k's sheet (in the normalised image plane,
        where the projection of a quad in front of the camera stays convex)."""
        poly_k = (sheet_c[k, :, :2] / sheet_c[k, :, 2:3]).astype(np.float32)
        for j in np.flatnonzero(in_front & (dist < dist[k])):
            if j == k:
                continue
            poly_j = (sheet_c[j, :, :2] / sheet_c[j, :, 2:3]).astype(np.float32)
            area, _ = cv2.intersectConvexConvex(_ccw(poly_k), _ccw(poly_j))
            if area > 1e-9:
                return True
        return False

    def _behind_post(self, k: int, T_world_cam: np.ndarray) -> bool:
        """True when an occluding post (scene ``posts[].occludes``) hides any part of marker k: any of
        9 points of its square (corners, edge midpoints, centre) seen through a post."""
        if not self._occluders:
            return False
        origin = T_world_cam[:3, 3]
        d = self._probe_w[k] - origin          # segments camera -> points, t in (0, 1)
        return any(np.isfinite(post.ray_hits(origin, d, t_max=1.0 - 1e-6)).any() for post in self._occluders)

    def visible(self, T_world_base: PoseLike) -> Dict[str, List[Tuple[int, np.ndarray]]]:
        """{camera name: [(marker_id, true corners (4, 2) raw px)]} for every ring camera (nearest first)."""
        return {cam.name: [(v.marker_id, v.corners) for v in self.camera_view(T_world_base, cam)]
                for cam in self.ring.cameras}

    # --- corners mode ----------------------------------------------------------------------------

    def observe(self, T_world_base: PoseLike, stamp: float = 0.0,
                rng: Optional[np.random.Generator] = None) -> RingFrame:
        """A ring frame of noisy detections (corners mode).

        Corner noise is Gaussian (``pixel_noise`` px per coordinate), drawn from ``rng`` or from the
        simulator's own seeded generator. Every camera reports (possibly an empty list), in
        aruco_detect order within an image (ascending id is not guaranteed by aruco_detect either).
        """
        frame = RingFrame(stamp=float(stamp))
        for cam in self.ring.cameras:
            frame.cameras[cam.name] = CameraFrame(camera=cam.name, stamp=float(stamp),
                                                  observations=self.observe_camera(T_world_base, cam, rng))
        return frame

    def observe_camera(self, T_world_base: PoseLike, camera: Union[str, RingCamera],
                       rng: Optional[np.random.Generator] = None) -> List[MarkerObservation]:
        """One camera's noisy detections (corners mode) from the robot pose (see :meth:`observe`)."""
        gen = rng if rng is not None else self.rng
        obs = []
        for marker_id, corners in self.visible_camera(T_world_base, camera):
            noisy = corners + gen.normal(0.0, self.pixel_noise, corners.shape) if self.pixel_noise > 0 \
                else corners.copy()
            obs.append(MarkerObservation(marker_id, noisy))
        return obs

    def visible_camera(self, T_world_base: PoseLike, camera: Union[str, RingCamera]) -> List[Tuple[int, np.ndarray]]:
        """[(marker_id, true corners)] for one camera."""
        return [(v.marker_id, v.corners) for v in self.camera_view(T_world_base, camera)]

    # --- image mode ------------------------------------------------------------------------------

    def render(self, T_world_base: PoseLike, rng: Optional[np.random.Generator] = None,
               cameras: Optional[Sequence[str]] = None) -> Dict[str, np.ndarray]:
        """{camera name: mono8 image (height, width)} rendered from the true pose (image mode)."""
        gen = rng if rng is not None else self.rng
        names = list(cameras) if cameras is not None else self.ring.names
        T = as_transform(T_world_base)
        return {name: self.renderer.render_camera(self, T, name, gen) for name in names}

    @property
    def renderer(self):
        """The image-mode renderer (:class:`.render.RingRenderer`), made on first use."""
        if self._renderer is None:
            from .render import RingRenderer
            r = self.render_params
            self._renderer = RingRenderer(self.scene, self.ring, seed=self.seed, blur_sigma=r.blur_sigma,
                                          noise_std=r.noise_std, supersample=r.supersample)
        return self._renderer

    def render_views(self, views: Sequence[PoseLike], camera: str, photometry=None,
                     rng: Optional[np.random.Generator] = None) -> np.ndarray:
        """One camera's mono8 image averaged over several robot poses (motion blur over the exposure),
        with a gain and gradient (:meth:`.render.RingRenderer.render_views`)."""
        gen = rng if rng is not None else self.rng
        return self.renderer.render_views([as_transform(T) for T in views], camera, gen, photometry)


def _dictionary_modules(dictionary: int) -> int:
    """Modules across a marker of the dictionary, black border included (5x5 -> 7)."""
    return int(cv2.aruco.getPredefinedDictionary(dictionary).markerSize) + 2


def _polygon_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)))


def _ccw(poly: np.ndarray) -> np.ndarray:
    x, y = poly[:, 0], poly[:, 1]
    signed = float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    return poly if signed > 0 else poly[::-1].copy()
