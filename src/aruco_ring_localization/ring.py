"""The camera ring: :class:`CameraRing` holds each camera's model and its extrinsics.

``config/ring.yaml`` (format in docs/formats.md)::

    format_version: 1
    base_frame: base_link
    cameras:
      - name: cam0
        frame_id: cam0_optical_frame      # tf frame of the optical centre (z forward, x right, y down)
        namespace: ring/cam0              # where the camera's topics live
        camera_info: camera_info/cam0.yaml   # relative to this file, or an inline mapping
        T_base_camera:                    # pose of the optical frame in base_frame
          translation: [0.17, 0.0, 0.55]  # m
          rotation: [-0.5, 0.5, -0.5, 0.5]   # quaternion x, y, z, w
        extrinsics_std: {translation: 0.002, rotation_deg: 0.2}   # optional, see below

Extrinsics are ``T_base_cam`` (4x4): ``p_base = T_base_cam @ p_cam``.

``extrinsics_std`` is how far the calibration may be off: the 1-sigma error per axis of the
camera's own optical frame, translation in m and rotation in degrees (a scalar for all three axes
or a list of three). Given at the top level it applies to every camera without its own; absent
everywhere it is :data:`DEFAULT_EXTRINSICS_STD_TRANSLATION` / :data:`DEFAULT_EXTRINSICS_STD_ROTATION_DEG`
(a ring measured by hand or calibrated once). The joint estimator (``fusion: joint``) uses it to
weigh what each camera says; ``0`` declares the calibration exact.

``wiggle`` (optional, per camera or at the top level for every camera without its own;
``wiggle: null`` on a camera overrides a top-level one) declares a camera that is *not* rigid on
the ring: ``{translation: m, rotation_deg: deg}``, both positive, the 1-sigma of its per-frame
motion about its fixed pose (TagSLAM's ``wiggle_translation`` / ``wiggle_rotation``). Absent: the
camera is rigid. ``aruco_ring calibrate-ring`` then estimates the fixed pose the camera wiggles
about (:mod:`ring_calibration`); :attr:`RingCamera.wiggle` holds it as (rotation rad, translation m).
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import yaml

from . import geometry as geo
from .camera import CameraModel, load_yaml_file
from .errors import ConfigError, GeometryError
from .fileio import atomic_write_text

logger = logging.getLogger(__name__)

RING_FORMAT_VERSION = 1

#: Default 1-sigma calibration error of a camera's extrinsics per axis of its optical frame (m, deg):
#: what a ring measured with care or calibrated once achieves (docs/formats.md, "Ring file").
DEFAULT_EXTRINSICS_STD_TRANSLATION = 0.002
DEFAULT_EXTRINSICS_STD_ROTATION_DEG = 0.2
_DEFAULT_STD = tuple([float(np.radians(DEFAULT_EXTRINSICS_STD_ROTATION_DEG))] * 3
                     + [DEFAULT_EXTRINSICS_STD_TRANSLATION] * 3)


@dataclass(frozen=True)
class RingCamera:
    """One camera of the ring.

    Attributes:
        name: short name (``cam0``), also the key used everywhere in the core.
        frame_id: tf frame of its optical centre (``cam0_optical_frame``).
        model: intrinsics and distortion.
        T_base_cam: (4, 4) pose of the optical frame in the robot's base frame.
        namespace: ROS namespace of its topics (``ring/cam0``).
        extrinsics_std: (6,) 1-sigma calibration error of ``T_base_cam``: rotation about the
            optical frame's x, y, z (rad), then translation along them (m). The true pose is
            ``T_base_cam @ D`` with ``D`` such a small motion (the simulator's ``perturb_ring``).
        wiggle: declared per-frame freedom of the camera about ``T_base_cam``, (rotation rad,
            translation m) 1-sigma, or None (rigid; the ring file's ``wiggle``).
    """

    name: str
    frame_id: str
    model: CameraModel
    T_base_cam: np.ndarray
    namespace: str = ""
    extrinsics_std: Tuple[float, ...] = _DEFAULT_STD
    wiggle: Optional[Tuple[float, float]] = None

    @property
    def extrinsics_covariance(self) -> np.ndarray:
        """(6, 6) covariance of the left perturbation (w, v) of ``T_base_cam`` in the *base* frame
        (``T_base_cam_true = exp(w, v) · T_base_cam``): the optical-frame std moved by the adjoint."""
        A = geo.se3_adjoint(self.T_base_cam)
        return A @ np.diag(np.square(self.extrinsics_std)) @ A.T

    @property
    def T_cam_base(self) -> np.ndarray:
        return geo.inverse(self.T_base_cam)

    @property
    def yaw(self) -> float:
        """Heading (rad) of the camera's optical axis (its z) in the base frame."""
        z = self.T_base_cam[:3, 2]
        return float(np.arctan2(z[1], z[0]))


class CameraRing:
    """An ordered set of :class:`RingCamera` rigidly mounted on the robot."""

    def __init__(self, cameras: Sequence[RingCamera], base_frame: str = "base_link"):
        if not cameras:
            raise ConfigError("a ring needs at least one camera", key="cameras")
        names = [c.name for c in cameras]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConfigError(f"duplicate camera names {dup}", key="cameras")
        frames = [c.frame_id for c in cameras]
        dupf = sorted({f for f in frames if frames.count(f) > 1})
        if dupf:
            raise ConfigError(f"duplicate frame_id {dupf}", key="cameras")
        self.cameras: List[RingCamera] = list(cameras)
        self.base_frame = base_frame
        self._by_name: Dict[str, RingCamera] = {c.name: c for c in cameras}
        self._by_frame: Dict[str, RingCamera] = {c.frame_id: c for c in cameras}

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[RingCamera]:
        return iter(self.cameras)

    def __getitem__(self, name: str) -> RingCamera:
        return self._by_name[name]

    @property
    def names(self) -> List[str]:
        return [c.name for c in self.cameras]

    def by_frame(self, frame_id: str) -> Optional[RingCamera]:
        """The camera whose optical frame is ``frame_id`` (a detection's header.frame_id), or None."""
        return self._by_frame.get(frame_id.lstrip("/"))

    def with_extrinsics(self, extrinsics: Mapping[str, np.ndarray]) -> "CameraRing":
        """A copy with some cameras' ``T_base_cam`` replaced (e.g. the simulator's true rig)."""
        cams = [RingCamera(c.name, c.frame_id, c.model, np.asarray(extrinsics.get(c.name, c.T_base_cam)),
                           c.namespace, c.extrinsics_std, c.wiggle) for c in self.cameras]
        return CameraRing(cams, self.base_frame)

    def with_extrinsics_std(self, translation: float, rotation_deg: float) -> "CameraRing":
        """A copy whose every camera claims this calibration error (0, 0: exact extrinsics)."""
        std = tuple([float(np.radians(rotation_deg))] * 3 + [float(translation)] * 3)
        cams = [RingCamera(c.name, c.frame_id, c.model, c.T_base_cam, c.namespace, std, c.wiggle) for c in self.cameras]
        return CameraRing(cams, self.base_frame)

    # --- files ------------------------------------------------------------------------------

    @classmethod
    def load(cls, path: str) -> "CameraRing":
        """Load and validate a ring YAML file; errors name the file and the key."""
        path = str(path)
        data = load_yaml_file(path)
        return cls.from_dict(data, source=path, base_dir=os.path.dirname(os.path.abspath(path)))

    @classmethod
    def from_dict(cls, data: Any, source: str = "<ring>", base_dir: str = ".") -> "CameraRing":
        if not isinstance(data, Mapping):
            raise ConfigError(f"expected a mapping at the top level, got {type(data).__name__}", path=source)
        version = data.get("format_version", RING_FORMAT_VERSION)
        if version != RING_FORMAT_VERSION:
            raise ConfigError(f"unsupported format_version {version!r} (this version reads {RING_FORMAT_VERSION})",
                              path=source, key="format_version")
        base_frame = data.get("base_frame", "base_link")
        if not isinstance(base_frame, str) or not base_frame:
            raise ConfigError("expected a non-empty frame name", path=source, key="base_frame")
        cams = data.get("cameras")
        if not isinstance(cams, list) or not cams:
            raise ConfigError("expected a non-empty list of cameras", path=source, key="cameras")
        default_std = _read_extrinsics_std(data.get("extrinsics_std"), source, "extrinsics_std", _DEFAULT_STD)
        default_wiggle = read_wiggle(data.get("wiggle"), source, "wiggle")
        cameras = [_camera_from_dict(c, i, source, base_dir, default_std, default_wiggle) for i, c in enumerate(cams)]
        try:
            return cls(cameras, base_frame)
        except ConfigError as exc:
            raise ConfigError(str(exc).split(": ", 1)[-1], path=source, key=exc.key) from None

    def to_dict(self, camera_info_files: Optional[Mapping[str, str]] = None) -> Dict[str, Any]:
        """YAML mapping; cameras reference ``camera_info_files[name]`` or carry their intrinsics inline."""
        cams = []
        for c in self.cameras:
            q = geo.quaternion_from_matrix(c.T_base_cam)
            info: Any = (camera_info_files or {}).get(c.name) or c.model.to_dict()
            cam = {
                "name": c.name, "frame_id": c.frame_id, "namespace": c.namespace, "camera_info": info,
                "T_base_camera": {"translation": [float(v) for v in c.T_base_cam[:3, 3]],
                                  "rotation": [float(v) for v in q]},
                "extrinsics_std": {"translation": [float(v) for v in c.extrinsics_std[3:]],
                                   "rotation_deg": [float(np.degrees(v)) for v in c.extrinsics_std[:3]]},
            }
            if c.wiggle is not None:
                cam["wiggle"] = {"translation": float(c.wiggle[1]), "rotation_deg": float(np.degrees(c.wiggle[0]))}
            cams.append(cam)
        return {"format_version": RING_FORMAT_VERSION, "base_frame": self.base_frame, "cameras": cams}

    def save(self, path: str, camera_info_files: Optional[Mapping[str, str]] = None) -> None:
        """Write the ring file atomically (intrinsics inline unless file names are given)."""
        atomic_write_text(path, yaml.safe_dump(self.to_dict(camera_info_files), sort_keys=False))


def _camera_from_dict(c: Any, i: int, source: str, base_dir: str,
                      default_std: Tuple[float, ...] = _DEFAULT_STD,
                      default_wiggle: Optional[Tuple[float, float]] = None) -> RingCamera:
    key = f"cameras[{i}]"
    if not isinstance(c, Mapping):
        raise ConfigError("expected a mapping", path=source, key=key)
    name = c.get("name")
    if not isinstance(name, str) or not name:
        raise ConfigError("expected a non-empty string", path=source, key=f"{key}.name")
    frame_id = c.get("frame_id", f"{name}_optical_frame")
    if not isinstance(frame_id, str) or not frame_id:
        raise ConfigError("expected a non-empty string", path=source, key=f"{key}.frame_id")
    namespace = c.get("namespace", f"ring/{name}")
    if not isinstance(namespace, str):
        raise ConfigError("expected a string", path=source, key=f"{key}.namespace")
    info = c.get("camera_info")
    if isinstance(info, str):
        info_path = info if os.path.isabs(info) else os.path.join(base_dir, info)
        try:
            model = CameraModel.from_yaml(info_path)
        except ConfigError as exc:
            raise ConfigError(f"camera_info file {info_path}: {exc}", path=source, key=f"{key}.camera_info") from None
    elif isinstance(info, Mapping):
        try:
            model = CameraModel.from_dict(info, source=f"{source} {key}.camera_info")
        except ConfigError as exc:
            raise ConfigError(str(exc), path=None) from None
    else:
        raise ConfigError("expected a file name or a camera_info mapping", path=source, key=f"{key}.camera_info")
    T = read_transform(c.get("T_base_camera"), source, f"{key}.T_base_camera")
    std = _read_extrinsics_std(c.get("extrinsics_std"), source, f"{key}.extrinsics_std", default_std)
    # ``wiggle: null`` on a camera: rigid, whatever the top level declares.
    wiggle = None if ("wiggle" in c and c["wiggle"] is None) else (
        read_wiggle(c["wiggle"], source, f"{key}.wiggle") if "wiggle" in c else default_wiggle)
    return RingCamera(name=name, frame_id=frame_id.lstrip("/"), model=model, T_base_cam=T, namespace=namespace,
                      extrinsics_std=std, wiggle=wiggle)


def read_wiggle(node: Any, source: str, key: str) -> Optional[Tuple[float, float]]:
    """``{translation: m, rotation_deg: deg}`` (both positive numbers) -> (rotation rad, translation m);
    None for an absent node."""
    if node is None:
        return None
    if not isinstance(node, Mapping):
        raise ConfigError(f"expected {{translation: m, rotation_deg: deg}}, got {node!r}", path=source, key=key)
    unknown = sorted(set(node) - {"translation", "rotation_deg"})
    if unknown:
        raise ConfigError(f"unknown keys {unknown} (expected translation, rotation_deg)", path=source, key=key)
    out = []
    for sub, scale in (("rotation_deg", np.pi / 180.0), ("translation", 1.0)):
        if sub not in node:
            raise ConfigError("missing (a wiggle needs both translation, m, and rotation_deg, deg)", path=source,
                              key=f"{key}.{sub}")
        value = node[sub]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
            raise ConfigError(f"expected a positive number, got {value!r}", path=source, key=f"{key}.{sub}")
        out.append(float(value) * scale)
    return out[0], out[1]


def _read_extrinsics_std(node: Any, source: str, key: str, default: Tuple[float, ...]) -> Tuple[float, ...]:
    """``{translation: m, rotation_deg: deg}`` (scalars or lists of three) -> (6,) (rad, rad, rad, m, m, m).
    A missing part keeps ``default``'s."""
    if node is None:
        return default
    if not isinstance(node, Mapping):
        raise ConfigError("expected {translation: m, rotation_deg: deg}", path=source, key=key)
    unknown = sorted(set(node) - {"translation", "rotation_deg"})
    if unknown:
        raise ConfigError(f"unknown keys {unknown} (expected translation, rotation_deg)", path=source, key=key)
    out = list(default)
    for sub, sl, scale in (("rotation_deg", slice(0, 3), np.pi / 180.0), ("translation", slice(3, 6), 1.0)):
        if sub not in node:
            continue
        value = node[sub]
        try:
            arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,))
        except (TypeError, ValueError):
            raise ConfigError(f"expected a number or three numbers, got {value!r}", path=source,
                              key=f"{key}.{sub}") from None
        if isinstance(value, bool) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
            raise ConfigError(f"expected non-negative numbers, got {value!r}", path=source, key=f"{key}.{sub}")
        out[sl] = [float(v) * scale for v in arr]
    return tuple(out)


def read_transform(node: Any, source: str, key: str) -> np.ndarray:
    """Parse ``{translation: [x, y, z], rotation: [qx, qy, qz, qw]}`` into a 4x4 transform."""
    if not isinstance(node, Mapping):
        raise ConfigError("expected a mapping with 'translation' and 'rotation'", path=source, key=key)
    for sub in ("translation", "rotation"):
        if sub not in node:
            raise ConfigError("missing", path=source, key=f"{key}.{sub}")
    t, q = node["translation"], node["rotation"]
    if not isinstance(t, list) or len(t) != 3:
        raise ConfigError("expected [x, y, z] in metres", path=source, key=f"{key}.translation")
    if not isinstance(q, list) or len(q) != 4:
        raise ConfigError("expected a quaternion [x, y, z, w]", path=source, key=f"{key}.rotation")
    try:
        return geo.transform_from_translation_quaternion(t, q)
    except GeometryError as exc:
        raise ConfigError(str(exc), path=source, key=key) from None


def ring_summary(ring: CameraRing) -> List[str]:
    """Lines for people: each camera's heading, FOV, and the overlap with its neighbour."""
    lines = [f"{len(ring)} cameras, base frame {ring.base_frame}"]
    fovs = [c.model.horizontal_fov() for c in ring.cameras]
    for c, fov in zip(ring.cameras, fovs):
        t = c.T_base_cam[:3, 3]
        lines.append(f"  {c.name:6s} {c.frame_id:22s} yaw {np.degrees(c.yaw):7.1f} deg  "
                     f"at ({t[0]:+.3f}, {t[1]:+.3f}, {t[2]:+.3f}) m  {c.model.width}x{c.model.height} "
                     f"HFOV {np.degrees(fov):5.1f} deg  {c.model.distortion_model}")
    order = sorted(range(len(ring)), key=lambda k: ring.cameras[k].yaw)
    for a, b in zip(order, order[1:] + order[:1]):
        if a == b:
            continue
        gap = geo.wrap_angle(ring.cameras[b].yaw - ring.cameras[a].yaw) % (2 * np.pi)
        overlap = (fovs[a] + fovs[b]) / 2 - gap
        lines.append(f"  overlap {ring.cameras[a].name}-{ring.cameras[b].name}: {np.degrees(overlap):+.1f} deg"
                     + ("  (blind gap)" if overlap < 0 else ""))
    return lines


def apply_refined_extrinsics(ring: CameraRing, extrinsics: Mapping[str, np.ndarray], base_frame: str,
                             source: str = "<map>") -> CameraRing:
    """The ring with the extrinsics refined while mapping (a map file's ``ring_calibration``).

    Cameras absent from ``extrinsics`` keep their calibration. Raises ConfigError when the
    calibration was made for another base frame or names a camera the ring does not have.
    """
    if base_frame != ring.base_frame:
        raise ConfigError(f"refined for base frame '{base_frame}', but the ring's base frame is "
                          f"'{ring.base_frame}'", path=source, key="ring_calibration.base_frame")
    unknown = sorted(set(extrinsics) - set(ring.names))
    if unknown:
        raise ConfigError(f"cameras {unknown} are not in the ring ({', '.join(ring.names)})", path=source,
                          key="ring_calibration.cameras")
    return ring.with_extrinsics(extrinsics)
