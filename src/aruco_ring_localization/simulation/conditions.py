"""What makes a lab harsh, as models the simulator applies per frame (docs/simulation.md, "The harsh lab").

* :class:`Floor` — a plate that is not flat: a tilt plus seeded bumps; base_link stands on it
  (height, roll and pitch from the floor under its four wheels), the wheel odometry stays planar.
* :class:`RingVibration` — per-frame jitter of each camera's extrinsics (the ring shakes).
* :class:`Photometry` — per camera: an image gain that wanders (auto exposure, lights) and a
  brightness gradient across the image whose direction drifts (uneven light).

Each draws from its own seeded generator, and each is the identity when its parameters are zero
(the kind lab), so the kind lab draws exactly what it did before these existed.
"""
from __future__ import annotations

from typing import Dict, Iterable, Optional, Sequence, Tuple

import cv2
import numpy as np

from .. import geometry as geo
from .params import PlateParams, RenderParams, RingParams


class Floor:
    """The floor's height ``h(x, y)`` (m) and the pose of a robot standing on it.

    ``h`` = a plane through the plate's centre rising ``tilt_deg`` toward ``tilt_direction_deg``,
    plus two sinusoidal waves of ``bump_wavelength`` along seeded directions with seeded phases,
    their amplitude such that their summed slope never exceeds ``bump_deg``.

    Args:
        params: the ``plate`` section.
        centre: (x, y) where the tilt plane has height 0 (the plate's centre).
        footprint: (length, width) of the robot, m: its wheels at the footprint's corners.
        seed: the bumps' directions and phases.
    """

    def __init__(self, params: PlateParams = PlateParams(), centre: Sequence[float] = (0.0, 0.0),
                 footprint: Sequence[float] = (0.98, 0.61), seed: int = 0):
        self.params = params
        self.centre = np.asarray(centre, dtype=float).reshape(2)
        self.footprint = (float(footprint[0]), float(footprint[1]))
        d = np.radians(params.tilt_direction_deg)
        self._tilt = np.tan(np.radians(params.tilt_deg)) * np.array([np.cos(d), np.sin(d)])
        rng = np.random.default_rng([int(seed), 0xf100])
        self._k = 2.0 * np.pi / params.bump_wavelength
        angles = rng.uniform(0.0, 2.0 * np.pi, 2)
        self._dirs = np.stack([np.cos(angles), np.sin(angles)], axis=1)   # (2, 2) wave directions
        self._phases = rng.uniform(0.0, 2.0 * np.pi, 2)
        # slope of A sin(k u + phi) is at most A k: two waves -> A = tan(bump) / (2 k)
        self._amp = np.tan(np.radians(params.bump_deg)) / (2.0 * self._k)

    @property
    def flat(self) -> bool:
        return self.params.tilt_deg == 0.0 and self.params.bump_deg == 0.0

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Floor height (m) at points ``xy`` (..., 2) in the world."""
        p = np.asarray(xy, dtype=float)
        h = (p - self.centre) @ self._tilt
        if self._amp > 0.0:
            h = h + self._amp * np.sum(np.sin(self._k * (p @ self._dirs.T) + self._phases), axis=-1)
        return h

    def T_world_base(self, pose: Sequence[float]) -> np.ndarray:
        """base_link's 4x4 pose standing at (x, y, yaw) on the floor: its height is the mean of the
        floor under its four wheels (the footprint's corners), its roll and pitch the slopes between
        them (left - right over the width, front - back over the length); its yaw is ``yaw``."""
        x, y, yaw = (float(v) for v in pose)
        if self.flat:
            return geo.transform_from_se2(x, y, yaw)
        L, W = self.footprint
        c, s = np.cos(yaw), np.sin(yaw)
        body = np.array([[L / 2, W / 2], [L / 2, -W / 2], [-L / 2, W / 2], [-L / 2, -W / 2]])
        world = np.stack([x + c * body[:, 0] - s * body[:, 1], y + s * body[:, 0] + c * body[:, 1]], axis=1)
        h = self.height(world)      # front-left, front-right, back-left, back-right
        slope_x = (0.5 * (h[0] + h[1]) - 0.5 * (h[2] + h[3])) / L
        slope_y = (0.5 * (h[0] + h[2]) - 0.5 * (h[1] + h[3])) / W
        T = np.eye(4)
        # R = Rz(yaw) Ry(pitch) Rx(roll): the nose up (front higher) is a negative pitch, the left side
        # up a positive roll (REP-103).
        T[:3, :3] = geo.matrix_from_rpy(float(np.arctan(slope_y)), float(-np.arctan(slope_x)), yaw)
        T[:3, 3] = (x, y, float(np.mean(h)))
        return T


class RingVibration:
    """Per-frame jitter of each camera's extrinsics: ``T_base_cam @ D`` with ``D`` a fresh seeded
    Gaussian rotation (``vibration_rot_std_deg`` per axis) and translation (``vibration_trans_std``)
    in the camera's own frame, drawn once per frame (:meth:`draw`)."""

    def __init__(self, params: RingParams = RingParams(), seed: int = 0):
        self.rot_std = np.radians(params.vibration_rot_std_deg)
        self.trans_std = float(params.vibration_trans_std)
        self.rng = np.random.default_rng([int(seed), 0x5ba1])

    @property
    def rigid(self) -> bool:
        return self.rot_std == 0.0 and self.trans_std == 0.0

    def draw(self, cameras: Iterable[str]) -> Dict[str, np.ndarray]:
        """{camera: D (4x4)} for one frame (identities when rigid, without drawing)."""
        out = {}
        for name in cameras:
            D = np.eye(4)
            if not self.rigid:
                D[:3, :3] = geo.rotation_from_rvec(self.rng.normal(0.0, self.rot_std, 3))
                D[:3, 3] = self.rng.normal(0.0, self.trans_std, 3)
            out[name] = D
        return out

    @staticmethod
    def shaken_base(T_world_base: np.ndarray, T_base_cam: np.ndarray, D: np.ndarray) -> np.ndarray:
        """The base pose through which a camera at ``T_base_cam`` sees as if shaken by ``D``:
        ``T' @ T_base_cam = T_world_base @ T_base_cam @ D`` (so the renderer and the visibility model
        need no other input)."""
        return T_world_base @ T_base_cam @ D @ geo.inverse(T_base_cam)


class Photometry:
    """Per camera and frame: an image gain and a linear brightness gradient (images mode).

    The log gain is a first-order autoregressive process (stationary sigma ``gain_std``, correlation
    time ``correlation_time`` s); the gradient's amplitude is ``illumination_gradient`` and its
    direction in the image drifts by a Gaussian step (0.1 rad) per frame, from a seeded start.
    """

    def __init__(self, params: RenderParams = RenderParams(), cameras: Sequence[str] = (), rate: float = 10.0,
                 seed: int = 0, correlation_time: float = 2.0):
        self.gain_std = float(params.gain_std)
        self.gradient = float(params.illumination_gradient)
        self.rho = float(np.exp(-1.0 / (float(rate) * correlation_time)))
        self.rng = np.random.default_rng([int(seed), 0x11f0])
        self._log_gain = {c: (float(self.rng.normal(0.0, self.gain_std)) if self.gain_std > 0 else 0.0)
                          for c in cameras}
        self._angle = {c: (float(self.rng.uniform(0.0, 2.0 * np.pi)) if self.gradient > 0 else 0.0) for c in cameras}

    @property
    def neutral(self) -> bool:
        return self.gain_std == 0.0 and self.gradient == 0.0

    def draw(self) -> Dict[str, Optional[Tuple[float, float, float]]]:
        """{camera: (gain, gradient amplitude, gradient direction rad)} for one frame; None when neutral."""
        if self.neutral:
            return {c: None for c in self._log_gain}
        out = {}
        innovation = self.gain_std * np.sqrt(1.0 - self.rho ** 2)
        for c in self._log_gain:
            if self.gain_std > 0:
                self._log_gain[c] = self.rho * self._log_gain[c] + float(self.rng.normal(0.0, innovation))
            if self.gradient > 0:
                self._angle[c] += float(self.rng.normal(0.0, 0.1))
            out[c] = (float(np.exp(self._log_gain[c])), self.gradient, self._angle[c])
        return out


def lit(img: np.ndarray, photometry: Tuple[float, float, float]) -> np.ndarray:
    """``img`` (float32 grey levels) times the gain and the gradient, not clipped (the light the
    sensor receives: :func:`apply_photometry` then clips it)."""
    gain, amp, angle = photometry
    if amp > 0:
        h, w = img.shape
        u, v = _unit_grids(h, w)
        k = gain * amp / np.sqrt(2.0)
        ramp = cv2.addWeighted(u, float(k * np.cos(angle)), v, float(k * np.sin(angle)), float(gain))
        return cv2.multiply(img, ramp)
    return img * np.float32(gain)


def apply_photometry(img: np.ndarray, photometry: Optional[Tuple[float, float, float]]) -> np.ndarray:
    """``img`` (grey levels, float32 or uint8) times the gain and the gradient (:func:`lit`), rounded
    and clipped to a mono8 image (values past 255 saturate, as a sensor does)."""
    out = img if img.dtype == np.float32 else img.astype(np.float32)
    if photometry is not None:
        out = lit(out, photometry)
    return cv2.convertScaleAbs(out)   # saturate_cast: rounds, clips to 0..255


_GRIDS: Dict[Tuple[int, int], Tuple[np.ndarray, np.ndarray]] = {}


def _unit_grids(h: int, w: int) -> Tuple[np.ndarray, np.ndarray]:
    """(h, w) float32 grids running -1..1 across the image (u along x, v along y), cached by size."""
    if (h, w) not in _GRIDS:
        u = (np.arange(w, dtype=np.float32) - 0.5 * (w - 1)) / (0.5 * w)
        v = (np.arange(h, dtype=np.float32) - 0.5 * (h - 1)) / (0.5 * h)
        _GRIDS[(h, w)] = (np.ascontiguousarray(np.broadcast_to(u[None, :], (h, w))),
                          np.ascontiguousarray(np.broadcast_to(v[:, None], (h, w))))
    return _GRIDS[(h, w)]


class LabConditions:
    """A lab's per-frame conditions for code that simulates still frames itself (the benchmarks):
    the floor (the robot's true pose at an SE(2) stop), the ring's vibration and the photometry,
    drawn afresh for each frame, from the simulator's parameters (e.g. ``params.lab_config("harsh")``).
    A robot at rest has no motion blur and its free-running cameras all see the same pose, so those
    two do not apply here; :class:`~.simulator.SimulatorCore` models them for a moving robot.

    Args:
        config: the simulator's parameters (its ``plate``, ``ring``, ``render``, ``rate``, ``seed``).
        scene: the hall (the plate's centre, the robot's footprint).
        cameras: the ring's camera names.
    """

    def __init__(self, config, scene, cameras: Sequence[str], seed: Optional[int] = None):
        s = config.seed if seed is None else seed
        self.floor = Floor(config.plate, scene.plate.centre, scene.robot.footprint, seed=s)
        self.vibration = RingVibration(config.ring, seed=s)
        self.photometry = Photometry(config.render, cameras, rate=config.rate, seed=s)
        self.cameras = list(cameras)

    def T_world_base(self, pose: Sequence[float]) -> np.ndarray:
        """base_link's true 4x4 pose at rest at (x, y, yaw) on the floor."""
        return self.floor.T_world_base(pose)

    def views(self, ring, T_world_base: np.ndarray) -> Dict[str, np.ndarray]:
        """{camera: the base pose it sees through this frame} (this frame's vibration drawn)."""
        shake = self.vibration.draw(self.cameras)
        if self.vibration.rigid:
            return {c: T_world_base for c in self.cameras}
        return {c: RingVibration.shaken_base(T_world_base, ring[c].T_base_cam, shake[c]) for c in self.cameras}

    def observe(self, sim, T_world_base: np.ndarray, stamp: float):
        """Corners mode: a :class:`RingFrame` of one still frame (``sim``: a RingSimulator, true rig)."""
        from ..detections import CameraFrame, RingFrame

        frame = RingFrame(stamp=float(stamp))
        for c, T in self.views(sim.ring, T_world_base).items():
            frame.cameras[c] = CameraFrame(camera=c, stamp=float(stamp), observations=sim.observe_camera(T, c))
        return frame

    def render(self, sim, T_world_base: np.ndarray, rng: Optional[np.random.Generator] = None
               ) -> Dict[str, np.ndarray]:
        """Images mode: {camera: mono8 image} of one still frame, shaken and lit as this frame is."""
        light = self.photometry.draw()
        return {c: sim.render_views([T], c, light.get(c), rng=rng) for c, T in self.views(sim.ring, T_world_base).items()}
