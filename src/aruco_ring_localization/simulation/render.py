"""Image mode: render what each ring camera sees (:class:`RingRenderer`).

Per camera image (mono8, the camera's size):

1. a textured background: a seeded 360-degree panorama of the hall (smooth shading, grey
   shelves and pipes, no pure black or white blocks) sliced by the camera's heading, so the
   background moves when the robot turns;
2. every marker whose printed sheet is in front of the camera and faces it, far to near (nearer
   markers are drawn over farther ones): the marker image from ``cv2.aruco.generateImageMarker``
   plus its white quiet zone, warped into the RAW (distorted) image exactly: for each pixel of
   the sheet's bounding box the undistorted viewing ray (precomputed once per camera with
   :meth:`CameraModel.normalize`) is intersected with the marker plane and the texture is
   sampled there (``cv2.remap``, from a mip level that matches the marker's size on the image,
   so small markers are area-filtered rather than aliased); each pixel averages 2 x 2 such
   samples (``supersample``), so an edge's sub-pixel position survives in the grey level;
3. the scene's occluding posts (``posts[].occludes``), painted with the markers in distance order
   where each pixel's ray hits the column;
4. with :meth:`RingRenderer.render_views`: the mean of several such images along the exposure
   (motion blur);
5. optical blur (Gaussian, ``blur_sigma`` px), then with :meth:`RingRenderer.render_views` a gain
   and brightness gradient (:mod:`.conditions`), then sensor noise (Gaussian, ``noise_std`` grey
   levels, drawn from a seeded bank at a random offset per image), and only then the clip at 255
   and the rounding: a camera saturates after its lens and with its noise (a bright frame's white
   reads 255). An unlit still image (no gain, one view) is blurred and noised as mono8.

Each marker gets its own seeded print contrast (black 15..45, white 200..235), like real prints
under uneven light. Pixel centres are at integer coordinates, as in OpenCV and
:meth:`CameraModel.project`, so rendered corners agree with the projected ones.
"""
from __future__ import annotations

import logging
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from .. import geometry as geo
from ..camera import CameraModel
from ..ring import CameraRing
from .params import RenderParams
from .scene import Scene

logger = logging.getLogger(__name__)

_MODULE_PX = 48          # texture pixels per marker module at the finest mip level
_GRID_STEP = 8           # the ray grid is computed exactly every 8 px and interpolated (< 0.002 px error)
_SEAM_PX = 256           # width of the cross-fade that makes the background panorama periodic


def ray_grid(model: CameraModel, step: int = _GRID_STEP) -> Tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates (x/z, y/z) of every raw pixel: two (height, width) float32 arrays.

    Computed exactly on a coarse grid and bilinearly interpolated; the distortion is smooth, so
    the error is far below a thousandth of a pixel for ordinary lenses.
    """
    w, h = model.width, model.height
    uc, vc = np.meshgrid(np.arange(0, w + step, step, dtype=np.float64),
                         np.arange(0, h + step, step, dtype=np.float64))
    xy = model.normalize(np.stack([uc.ravel(), vc.ravel()], axis=1)).reshape(uc.shape + (2,)).astype(np.float32)
    mx, my = np.meshgrid(np.arange(w, dtype=np.float32) / step, np.arange(h, dtype=np.float32) / step)
    xn = cv2.remap(np.ascontiguousarray(xy[..., 0]), mx, my, cv2.INTER_LINEAR)
    yn = cv2.remap(np.ascontiguousarray(xy[..., 1]), mx, my, cv2.INTER_LINEAR)
    return xn, yn


def background_panorama(height: int, period: int, width: int, seed: int) -> np.ndarray:
    """A seeded (height, period + width) uint8 panorama, periodic in x with ``period``.

    Smooth shading plus grey rectangles and lines (shelves, doors, pipes) of moderate contrast;
    values stay within about 45..215 so nothing looks like a black-bordered marker.
    The field is drawn ``_SEAM_PX`` columns wider than one period and its first columns are
    cross-faded with the columns past the period, so the panorama has no seam where it wraps
    (a vertical step there would be an edge that turns with the robot).
    """
    rng = np.random.default_rng(seed)
    wide = period + _SEAM_PX
    low = rng.normal(0.0, 1.0, (6, max(4, period // 160)))
    pano = cv2.resize(low.astype(np.float32), (wide, height), interpolation=cv2.INTER_CUBIC)
    pano = 125.0 + 25.0 * pano / max(float(np.std(pano)), 1e-6)
    mid = rng.normal(0.0, 1.0, (height // 24, wide // 24)).astype(np.float32)
    pano += 8.0 * cv2.resize(mid, (wide, height), interpolation=cv2.INTER_CUBIC)
    for _ in range(max(8, period // 90)):
        x0 = int(rng.integers(0, period))
        w = int(rng.integers(20, 260))
        y0 = int(rng.integers(0, height))
        hh = int(rng.integers(10, height // 2))
        level = float(rng.uniform(-35.0, 35.0))
        x1 = min(wide, x0 + w)
        pano[y0:y0 + hh, x0:x1] += level
    for _ in range(max(4, period // 400)):
        y = int(rng.integers(0, height))
        pano[y:y + int(rng.integers(2, 6)), :] += float(rng.uniform(-25.0, 25.0))
    pano = cv2.GaussianBlur(pano, (0, 0), 1.2)
    # Column 0 becomes column `period` (which follows column period - 1 smoothly), fading back to
    # the field's own column _SEAM_PX: periodic and continuous.
    a = np.linspace(0.0, 1.0, _SEAM_PX, dtype=np.float32)[None, :]
    pano[:, :_SEAM_PX] = a * pano[:, :_SEAM_PX] + (1.0 - a) * pano[:, period:wide]
    pano = pano[:, :period]
    pano += rng.normal(0.0, 3.0, pano.shape).astype(np.float32)
    pano = np.clip(pano, 45.0, 215.0).astype(np.uint8)
    return np.concatenate([pano, pano[:, :width]], axis=1)


class RingRenderer:
    """Renders mono8 images of a scene for the cameras of a (true) ring.

    Args:
        scene: the hall.
        ring: the TRUE rig (the simulator's).
        seed: seed of the background and the markers' print contrast.
        blur_sigma: optical blur, px (Gaussian sigma).
        noise_std: sensor noise, grey levels (Gaussian sigma).
        min_depth: sheets with a corner closer than this (m) in front of the camera are not drawn.
        supersample: samples per pixel along each axis on the markers (area sampling; 1 = point
            sampling, edges then snap to pixel boundaries).
    """

    def __init__(self, scene: Scene, ring: CameraRing, seed: int = 0, blur_sigma: float = RenderParams.blur_sigma,
                 noise_std: float = RenderParams.noise_std, min_depth: float = 0.05,
                 supersample: int = RenderParams.supersample):
        self.scene = scene
        self.supersample = max(1, int(supersample))
        self.ring = ring
        self.blur_sigma = float(blur_sigma)
        self.noise_std = float(noise_std)
        self.min_depth = float(min_depth)
        rng = np.random.default_rng([int(seed), 0x7e11])
        dictionary = cv2.aruco.getPredefinedDictionary(scene.dictionary)
        modules = int(dictionary.markerSize) + 2
        quiet = float(scene.quiet_zone_modules)
        self.sheet_scale = (modules + 2.0 * quiet) / modules
        self._rays: Dict[str, Tuple[np.ndarray, np.ndarray, Tuple[float, float, float, float]]] = {}
        self._ray_extents: Dict[int, Tuple[np.ndarray, ...]] = {}
        self._textures: Dict[int, List[np.ndarray]] = {}
        for m in scene.markers:
            # Seeded per id, so a marker looks the same whatever else is in the scene.
            mrng = np.random.default_rng([int(seed), int(m.marker_id)])
            black = float(mrng.uniform(15.0, 45.0))
            white = float(mrng.uniform(200.0, 235.0))
            self._textures[m.marker_id] = _marker_mips(dictionary, m.marker_id, modules, quiet, black, white)
        fmax = max(c.model.fx for c in ring.cameras)
        self._period = int(round(2.0 * np.pi * fmax))
        wmax = max(c.model.width for c in ring.cameras)
        hmax = max(c.model.height for c in ring.cameras)
        self._pano = background_panorama(hmax, self._period, wmax, int(rng.integers(2 ** 31)))
        pad = 16
        self._noise = np.clip(np.round(rng.normal(0.0, self.noise_std, (hmax + pad, wmax + pad)) + 128.0),
                              0, 255).astype(np.uint8)
        self._noise_pad = pad

    def rays(self, name: str) -> Tuple[np.ndarray, np.ndarray, Tuple[float, float, float, float]]:
        """The camera's ray grid and its normalised field-of-view box (computed on first use)."""
        if name not in self._rays:
            xn, yn = ray_grid(self.ring[name].model)
            self._rays[name] = (xn, yn, _fov_box(xn, yn))
        return self._rays[name]

    def render_camera(self, sim, T_world_base: np.ndarray, name: str, rng: np.random.Generator) -> np.ndarray:
        """One camera's mono8 image for the robot at ``T_world_base`` (4x4, world frame).

        ``sim`` is the :class:`RingSimulator` (unused beyond the scene today; kept so a renderer
        can share the simulator's visibility cache). ``rng`` draws the noise offsets.
        """
        return self.render_views([T_world_base], name, rng)

    def render_views(self, views: Sequence[np.ndarray], name: str, rng: np.random.Generator,
                     photometry: Optional[Tuple[float, float, float]] = None) -> np.ndarray:
        """One camera's mono8 image averaged over the robot poses ``views`` (4x4 each: the exposure's
        motion blur), blurred by the lens, times ``photometry`` (gain, gradient, direction:
        :class:`conditions.Photometry`), with the sensor's noise, then clipped at 255 and rounded.
        One view without photometry is :meth:`render_camera`."""
        img = self._scene_image(views[0], name)
        if len(views) == 1 and photometry is None:
            # (the still, unlit image: blurred and noised as mono8, as before)
            H, W = img.shape
            if self.blur_sigma > 0:
                img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma)
            if self.noise_std > 0:
                img = cv2.addWeighted(img, 1.0, self._noise_tile(rng, H, W), 1.0, -128.0)
            return img
        # As a camera forms it: the exposure's views, the lens blur, the light on the sensor (gain,
        # gradient), the sensor's noise, and only then its full scale (clipped) and the rounding.
        acc = img.astype(np.float32)
        for T in views[1:]:
            acc += self._scene_image(T, name)
        if len(views) > 1:
            acc *= np.float32(1.0 / len(views))
        H, W = acc.shape
        if self.blur_sigma > 0:
            acc = cv2.GaussianBlur(acc, (0, 0), self.blur_sigma)
        if photometry is not None:
            from .conditions import lit
            acc = lit(acc, photometry)
        if self.noise_std > 0:
            acc = acc + (self._noise_tile(rng, H, W).astype(np.float32) - 128.0)
        return cv2.convertScaleAbs(acc)   # saturate_cast: rounds, clips to 0..255

    def _noise_tile(self, rng: np.random.Generator, H: int, W: int) -> np.ndarray:
        """An (H, W) tile of the seeded noise bank (mono8, 128 = no noise) at a random offset."""
        oy, ox = (int(v) for v in rng.integers(0, self._noise_pad, 2))
        return self._noise[oy:oy + H, ox:ox + W]

    def _scene_image(self, T_world_base: np.ndarray, name: str) -> np.ndarray:
        """The background, the markers and the occluding posts (far to near), before blur and noise."""
        cam = self.ring[name]
        model = cam.model
        W, H = model.width, model.height
        T_world_cam = T_world_base @ cam.T_base_cam
        T_cam_world = geo.inverse(T_world_cam)
        z_world = T_world_cam[:3, 2]
        heading = float(np.arctan2(z_world[1], z_world[0]))
        off = int(round((-heading % (2.0 * np.pi)) / (2.0 * np.pi) * self._period)) % self._period
        img = self._pano[:H, off:off + W].copy()
        xn, yn, fov = self.rays(name)
        draw = []
        for m in self.scene.markers:
            T_cam_marker = T_cam_world @ m.T_world_marker
            half = 0.5 * m.size * self.sheet_scale
            p0, n = T_cam_marker[:3, 3], T_cam_marker[:3, 2]
            if float(n @ p0) >= 0.0:      # seen from the back (or edge on)
                continue
            sheet = geo.transform_points(T_cam_marker, np.array(
                [[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]]))
            if np.any(sheet[:, 2] <= self.min_depth):
                continue
            draw.append((float(np.linalg.norm(p0)), m, T_cam_marker, half))
        centre = T_world_cam[:3, 3]
        for post in self.scene.occluders:   # painted in distance order with the markers (a post is convex)
            draw.append((float(np.hypot(*(np.asarray(post.centre) - centre[:2]))), post, None, 0.0))
        draw.sort(key=lambda d: -d[0])
        for _, m, T_cam_marker, half in draw:
            if T_cam_marker is None:
                self._draw_post(img, model, xn, yn, m, T_world_cam)
            else:
                self._draw_marker(img, model, xn, yn, fov, m.marker_id, T_cam_marker, half)
        return img

    def _extents(self, xn: np.ndarray, yn: np.ndarray):
        """Per column the range of x/z, per row the range of y/z of the image's rays (cached)."""
        key = id(xn)
        if key not in self._ray_extents:
            self._ray_extents[key] = (xn.min(axis=0), xn.max(axis=0), yn.min(axis=1), yn.max(axis=1))
        return self._ray_extents[key]

    def _draw_post(self, img: np.ndarray, model: CameraModel, xn: np.ndarray, yn: np.ndarray, post,
                   T_world_cam: np.ndarray) -> None:
        """Paint an occluding post (a grey column, its faces shaded by their direction) where each
        pixel's ray hits it; only within the bounding box of its projection (the whole image when a
        part of it is behind the camera)."""
        h = post.side / 2.0
        cx, cy = post.centre
        pts = np.array([[cx + sx * h, cy + sy * h, z] for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, post.height)])
        pc = geo.transform_points(geo.inverse(T_world_cam), pts)
        if np.all(pc[:, 2] <= 0.0):
            return
        if np.all(pc[:, 2] > 1e-3):
            # The column is convex: in normalised (x/z, y/z) coordinates it lies within its vertices' box;
            # the columns and rows of the raw image whose rays reach that box bound it (lens included).
            nx, ny = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
            col_lo, col_hi, row_lo, row_hi = self._extents(xn, yn)
            cols = np.flatnonzero((col_hi >= nx.min()) & (col_lo <= nx.max()))
            rows = np.flatnonzero((row_hi >= ny.min()) & (row_lo <= ny.max()))
            if not cols.size or not rows.size:
                return
            x0, x1, y0, y1 = int(cols[0]), int(cols[-1]) + 1, int(rows[0]), int(rows[-1]) + 1
        else:
            x0, y0, x1, y1 = 0, 0, model.width, model.height
        rx, ry = xn[y0:y1, x0:x1], yn[y0:y1, x0:x1]
        R = T_world_cam[:3, :3].astype(np.float32)
        o = T_world_cam[:3, 3]
        # World directions of the rays (x/z, y/z, 1); a camera is below the column's top and above
        # the floor, so a ray enters it through a side face: slabs in x and y, then the height there.
        d = [R[i, 0] * rx + R[i, 1] * ry + R[i, 2] for i in range(3)]
        with np.errstate(divide="ignore", invalid="ignore"):
            tx1, tx2 = (cx - h - o[0]) / d[0], (cx + h - o[0]) / d[0]
            ty1, ty2 = (cy - h - o[1]) / d[1], (cy + h - o[1]) / d[1]
        tx_near, tx_far = np.minimum(tx1, tx2), np.maximum(tx1, tx2)
        ty_near, ty_far = np.minimum(ty1, ty2), np.maximum(ty1, ty2)
        near = np.maximum(tx_near, ty_near)
        z = o[2] + near * d[2]
        hit = (near <= np.minimum(tx_far, ty_far)) & (near > 0) & (z >= 0.0) & (z <= post.height)
        if not np.any(hit):
            return
        # faces normal to x (entered by the x slab) darker than those normal to y; lighter upward
        shade = np.where(tx_near >= ty_near, 85.0, 120.0) + 15.0 * (z / post.height)
        roi = img[y0:y1, x0:x1]
        roi[hit] = np.clip(np.round(shade[hit]), 0, 255).astype(np.uint8)

    def _draw_marker(self, img: np.ndarray, model: CameraModel, xn: np.ndarray, yn: np.ndarray, fov, marker_id: int,
                     T_cam_marker: np.ndarray, half: float) -> None:
        """Composite one printed sheet into ``img`` (in place), area-sampled.

        Each pixel is the mean of ``supersample`` x ``supersample`` point samples at sub-pixel
        offsets (rays interpolated from the per-pixel ray grid): a pixel that an edge crosses gets
        the covered fraction of each side, so edges sit at their true sub-pixel position instead
        of snapping to pixel boundaries (point sampling alone quantises them by up to 0.5 px).
        """
        bbox = _sheet_bbox(model, fov, T_cam_marker, half)
        if bbox is None:
            return
        x0, y0, x1, y1 = bbox
        R = T_cam_marker[:3, :3].astype(np.float32)
        p0 = T_cam_marker[:3, 3].astype(np.float32)
        # Pick the mip level whose size is just above the sheet's size in samples.
        ss = self.supersample
        extent = max(x1 - x0, y1 - y0) * ss
        mips = self._textures[marker_id]
        tex = mips[0]
        for level in mips:
            if level.shape[0] >= extent:
                tex = level
        S = float(tex.shape[0])
        roi = img[y0:y1, x0:x1]
        if ss <= 1:
            u, v, inside = _sheet_hit(xn[y0:y1, x0:x1], yn[y0:y1, x0:x1], R, p0, half)
            if np.any(inside):
                sampled = _sample_sheet(tex, S, u, v, inside, half)
                roi[inside] = sampled[inside]
            return
        gx, gy = np.meshgrid(np.arange(x0, x1, dtype=np.float32), np.arange(y0, y1, dtype=np.float32))
        acc = np.zeros(roi.shape, np.float32)
        cover = np.zeros(roi.shape, np.float32)
        for oy in (np.arange(ss, dtype=np.float32) + 0.5) / ss - 0.5:
            for ox in (np.arange(ss, dtype=np.float32) + 0.5) / ss - 0.5:
                mx, my = gx + ox, gy + oy
                rx = cv2.remap(xn, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                ry = cv2.remap(yn, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                u, v, inside = _sheet_hit(rx, ry, R, p0, half)
                if not np.any(inside):
                    continue
                sampled = _sample_sheet(tex, S, u, v, inside, half).astype(np.float32)
                acc += np.where(inside, sampled, 0.0)
                cover += inside
        hit = cover > 0
        if not np.any(hit):
            return
        n = float(ss * ss)
        out = roi.astype(np.float32) * (1.0 - cover / n) + acc / n
        roi[hit] = np.clip(np.round(out[hit]), 0, 255).astype(np.uint8)


def _sheet_hit(rx: np.ndarray, ry: np.ndarray, R: np.ndarray, p0: np.ndarray, half: float):
    """Marker-plane coordinates (u, v), m, where the rays (rx, ry, 1) hit the sheet, and the mask of
    rays that hit it in front of the camera inside the sheet (+-half)."""
    n = R[:, 2]
    # Ray r = (x, y, 1); plane n.(t r - p0) = 0 -> t = n.p0 / n.r; marker coords of the hit point.
    denom = n[0] * rx + n[1] * ry + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = float(n @ p0) / denom
    dx = t * rx - p0[0]
    dy = t * ry - p0[1]
    dz = t - p0[2]
    u = R[0, 0] * dx + R[1, 0] * dy + R[2, 0] * dz
    v = R[0, 1] * dx + R[1, 1] * dy + R[2, 1] * dz
    inside = (t > 0) & (np.abs(u) <= half) & (np.abs(v) <= half)
    return u, v, inside


def _sample_sheet(tex: np.ndarray, S: float, u: np.ndarray, v: np.ndarray, inside: np.ndarray,
                  half: float) -> np.ndarray:
    """Texture values (bilinear) at marker-plane coordinates; texel i covers [i, i+1)/S of the sheet."""
    map_x = ((u / (2.0 * half) + 0.5) * S - 0.5).astype(np.float32)
    map_y = ((0.5 - v / (2.0 * half)) * S - 0.5).astype(np.float32)
    map_x[~inside] = -10.0
    map_y[~inside] = -10.0
    return cv2.remap(tex, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _marker_mips(dictionary, marker_id: int, modules: int, quiet: float, black: float,
                 white: float) -> List[np.ndarray]:
    """Mip pyramid (largest first) of the printed sheet: marker + white quiet zone, print contrast applied."""
    side = modules * _MODULE_PX
    marker = cv2.aruco.generateImageMarker(dictionary, int(marker_id), side, borderBits=1)
    q = int(round(quiet * _MODULE_PX))
    sheet = cv2.copyMakeBorder(marker, q, q, q, q, cv2.BORDER_CONSTANT, value=255)
    sheet = (black + (white - black) * (sheet.astype(np.float32) / 255.0)).astype(np.float32)
    mips = [sheet]
    while mips[-1].shape[0] > 24:
        s = mips[-1].shape[0] // 2
        mips.append(cv2.resize(mips[-1], (s, s), interpolation=cv2.INTER_AREA))
    return [np.clip(np.round(m), 0, 255).astype(np.uint8) for m in mips]


def _sheet_bbox(model: CameraModel, fov: Tuple[float, float, float, float], T_cam_marker: np.ndarray,
                half: float):
    """Pixel bounding box (x0, y0, x1, y1), end-exclusive, of the sheet in the raw image, or None.

    Samples a 9x9 grid over the sheet, keeps the samples inside the camera's field of view (so
    the distortion polynomial is only evaluated where it is valid), projects them and pads.
    """
    s = np.linspace(-half, half, 9)
    gu, gv = np.meshgrid(s, s)
    pts = np.stack([gu.ravel(), gv.ravel(), np.zeros(gu.size)], axis=1)
    pc = geo.transform_points(T_cam_marker, pts)
    if np.any(pc[:, 2] <= 1e-6):
        return None
    nx, ny = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    keep = (nx >= fov[0]) & (nx <= fov[1]) & (ny >= fov[2]) & (ny <= fov[3])
    if not np.any(keep):
        # The whole sheet may still cover the image centre (very close); then use the image.
        if nx.min() < 0 < nx.max() and ny.min() < 0 < ny.max():
            return 0, 0, model.width, model.height
        return None
    px = model.project(pc[keep])
    step_px = 2.0 * half / 8.0 * model.fx / float(np.min(pc[:, 2]))   # grid spacing on the image
    pad = int(np.ceil(step_px)) + 2
    x0 = max(0, int(np.floor(px[:, 0].min())) - pad)
    y0 = max(0, int(np.floor(px[:, 1].min())) - pad)
    x1 = min(model.width, int(np.ceil(px[:, 0].max())) + pad + 1)
    y1 = min(model.height, int(np.ceil(px[:, 1].max())) + pad + 1)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


def _fov_box(xn: np.ndarray, yn: np.ndarray) -> Tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) of the normalised coordinates seen by the image, slightly enlarged."""
    mx = 0.03 * float(xn.max() - xn.min())
    my = 0.03 * float(yn.max() - yn.min())
    return float(xn.min()) - mx, float(xn.max()) + mx, float(yn.min()) - my, float(yn.max()) + my
