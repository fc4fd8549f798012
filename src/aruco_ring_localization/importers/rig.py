"""Camera rigs from Kalibr and TagSLAM files -> :class:`~aruco_ring_localization.ring.CameraRing`.

Two inputs, one per-camera layout (Kalibr's ``camchain.yaml``, which TagSLAM's ``cameras.yaml``
copies)::

    cam0:
      camera_model: pinhole                 # the only projection the package has
      intrinsics: [fx, fy, cx, cy]          # pixels
      distortion_model: radtan              # radtan | equidistant | plumb_bob | rational_polynomial | none
      distortion_coeffs: [k1, k2, p1, p2]   # radtan: 4 or 5 (k3 last); equidistant: 4
      resolution: [width, height]
      rostopic: /cam0/image_raw             # image topic (its namespace becomes the camera's)
      tagtopic: /cam0/tags                  # TagSLAM only: the detections' topic
      wiggle_rotation: 0.01                 # TagSLAM only (rad): see "wiggle" below
      wiggle_translation: 0.01              # TagSLAM only (m)
      T_cam_imu: 4x4                        # Kalibr imu-cam: p_cam = T_cam_imu p_imu
      T_cn_cnm1: 4x4                        # Kalibr: p_camN = T_cn_cnm1 p_cam(N-1)

Camera poses, in this order of preference:

* TagSLAM's ``camera_poses.yaml`` (``camK: {pose: {position: {x, y, z}, rotation: {x, y, z}}}``,
  the rotation a rotation vector): the pose of each camera's optical frame in the rig body,
  ``T_rig_cam``. The rig frame is TagSLAM's body frame (often camera 0's optical frame). Its
  optional ``R`` (36 numbers, the upper-triangular square-root information matrix of the pose,
  GTSAM's order: rotation, then translation, a perturbation in the camera's own frame) gives the
  pose's uncertainty: the ring file's ``extrinsics_std`` of that camera is the square root of the
  diagonal of ``(R^T R)^-1`` (the correlations are dropped: the ring file has none). A camera whose
  pose comes without ``R`` (or from a Kalibr file) gets the ring file's default
  (:data:`ring.DEFAULT_EXTRINSICS_STD_TRANSLATION` / ``_ROTATION_DEG``): made up, and the
  importer says so (:attr:`ImportedRig.notes`).
* Kalibr ``T_cam_imu`` of every camera: the ring's base frame is the IMU's.
* Kalibr ``T_cn_cnm1`` chained from camera 0: the base frame is camera 0's optical frame.
* A single camera without any pose: it is the base frame (identity).

A camera none of these places is reported by name (:class:`errors.ConfigError`), never guessed.
Distortion: ``radtan`` is OpenCV's ``plumb_bob`` (k1 k2 p1 p2 [k3]); ``equidistant`` is the
fisheye model (k1..k4); ``plumb_bob``, ``rational_polynomial`` pass through; ``none`` is a camera
without distortion. Kalibr's ``fov`` (ATAN) model and the ``omni``, ``ds``, ``eucm`` projections
cannot be represented by :class:`~aruco_ring_localization.camera.CameraModel` and are refused with
a message saying so (calibrate again with radtan or equidistant).

Wiggle: TagSLAM's ``wiggle_rotation`` / ``wiggle_translation`` declare a camera that is *not*
rigid on its rig: TagSLAM gives it its own pose in every frame, tied to the camera's fixed pose
(the one camera_poses.yaml and TagSLAM's output hold) by an identity prior of those std (its
camera.cpp / tag_slam.cpp; 1e-5 when not given: rigid). The fixed pose is then the mean pose
the camera wiggles about, not a rigid rig's best fit: the two differ by more than either's
noise on TagSLAM's tests 5 and 6 (docs/benchmarks.md). The importer keeps the declared values
(:attr:`ImportedCamera.wiggle`), writes them to the ring (:attr:`RingCamera.wiggle`, the ring
file's ``wiggle``: ``calibrate-ring`` then estimates the fixed pose) and says so
(:attr:`ImportedRig.notes`).
"""
from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np

from .. import geometry as geo
from ..camera import CameraModel, load_yaml_file, save_camera_yaml
from ..errors import ConfigError, GeometryError
from ..ring import (DEFAULT_EXTRINSICS_STD_ROTATION_DEG, DEFAULT_EXTRINSICS_STD_TRANSLATION, CameraRing,
                    RingCamera)

logger = logging.getLogger(__name__)

#: Kalibr / TagSLAM distortion model name -> (CameraModel name, accepted coefficient counts).
DISTORTION_MODELS = {
    "radtan": ("plumb_bob", (4, 5)),
    "plumb_bob": ("plumb_bob", (0, 4, 5)),
    "rational_polynomial": ("rational_polynomial", (8,)),
    "equidistant": ("equidistant", (4,)),
    "fisheye": ("equidistant", (4,)),
    "none": ("plumb_bob", (0,)),
}
#: Models the package cannot represent, with what they are.
UNSUPPORTED_DISTORTION = {"fov": "Kalibr's FOV (ATAN) model"}


@dataclass
class ImportedCamera:
    """One camera read from the file.

    Attributes:
        name: the file's key (``cam0``).
        model: intrinsics and distortion.
        T_base_cam: pose of its optical frame in the rig's base frame, None when the files give none.
        namespace: ROS namespace of its topics (from ``tagtopic`` or ``rostopic``).
        frame_id: optical frame name (the file's ``frame_id`` or ``<name>_optical_frame``).
        topic: the detections' topic (``tagtopic``) or the image topic (``rostopic``), "" if neither.
        pose_source: where the pose came from (``camera_poses.yaml``, ``T_cam_imu``, ...).
        extrinsics_std: (6,) 1-sigma of the pose per axis of the camera's frame (rotation rad, then
            translation m) when the source states it (TagSLAM's ``R``), else None (the default).
        wiggle: TagSLAM's declared per-frame freedom of the camera on its rig, (rotation rad,
            translation m), when the file gives ``wiggle_rotation`` or ``wiggle_translation``
            (the other 1e-5, TagSLAM's default), else None (rigid).
    """

    name: str
    model: CameraModel
    T_base_cam: Optional[np.ndarray]
    namespace: str
    frame_id: str
    topic: str = ""
    pose_source: str = ""
    extrinsics_std: Optional[Tuple[float, ...]] = None
    wiggle: Optional[Tuple[float, float]] = None


#: TagSLAM's wiggle when cameras.yaml does not give it (camera.cpp): a rigid camera.
TAGSLAM_DEFAULT_WIGGLE = 1e-5


def ring_wiggle(wiggle: Optional[Tuple[float, float]]) -> Optional[Tuple[float, float]]:
    """The ring file's wiggle (:attr:`RingCamera.wiggle`) of a declared TagSLAM one: None (rigid) when
    absent or no larger than TagSLAM's default for a rigid camera, else the declared (rotation rad,
    translation m)."""
    if wiggle is None or max(wiggle) <= TAGSLAM_DEFAULT_WIGGLE:
        return None
    return float(wiggle[0]), float(wiggle[1])


def _wiggle(entry: Mapping, name: str, path: str) -> Optional[Tuple[float, float]]:
    """(rotation rad, translation m): TagSLAM's ``wiggle_rotation`` / ``wiggle_translation``; None without either."""
    keys = ("wiggle_rotation", "wiggle_translation")
    if not any(k in entry for k in keys):
        return None
    out = []
    for k in keys:
        v = entry.get(k, TAGSLAM_DEFAULT_WIGGLE)
        try:
            v = float(v)
        except (TypeError, ValueError):
            raise ConfigError(f"expected a number, got {v!r}", path=path, key=f"{name}.{k}") from None
        if not np.isfinite(v) or v <= 0.0:
            raise ConfigError(f"expected a positive std, got {v!r}", path=path, key=f"{name}.{k}")
        out.append(v)
    return out[0], out[1]


@dataclass
class ImportedRig:
    """A rig read by :func:`read_rig`.

    Attributes:
        cameras: in the file's order (``cam0``, ``cam1``, ...).
        base_frame: name given to the rig's base frame.
        base_definition: what that frame physically is (for the user and the docs).
        source: the file(s) read.
    """

    cameras: List[ImportedCamera]
    base_frame: str
    base_definition: str
    source: str
    notes: List[str] = field(default_factory=list)

    def missing_poses(self) -> List[str]:
        return [c.name for c in self.cameras if c.T_base_cam is None]

    def ring(self) -> CameraRing:
        """The ring; ConfigError naming every camera whose pose the files do not give."""
        missing = self.missing_poses()
        if missing:
            raise ConfigError(f"no pose for camera(s) {', '.join(missing)} in the rig (give a TagSLAM "
                              f"camera_poses.yaml with --camera-poses, or a Kalibr camchain with T_cn_cnm1 / "
                              f"T_cam_imu): a camera's extrinsics are never guessed", path=self.source)
        cams = [RingCamera(c.name, c.frame_id, c.model, np.asarray(c.T_base_cam), c.namespace,
                           **({} if c.extrinsics_std is None else {"extrinsics_std": c.extrinsics_std}),
                           wiggle=ring_wiggle(c.wiggle))
                for c in self.cameras]
        try:
            return CameraRing(cams, self.base_frame)
        except ConfigError as exc:
            raise ConfigError(exc.detail, path=self.source, key=exc.key) from None


def _camera_order(keys) -> List[str]:
    def key(k: str):
        m = re.fullmatch(r"cam(\d+)", str(k))
        return (0, int(m.group(1)), "") if m else (1, 0, str(k))
    return sorted((str(k) for k in keys), key=key)


def _namespace(entry: Mapping[str, Any], name: str) -> str:
    """The camera's namespace from its tag topic (``/ns/tags``, ``/ns/left``: the topic's parent) or its
    image topic (``/ns/image_raw``)."""
    tag = str(entry.get("tagtopic") or "").strip("/")
    if tag:
        return tag.rpartition("/")[0]
    img = str(entry.get("rostopic") or "").strip("/")
    if img:
        parts = img.split("/")
        while len(parts) > 1 and (parts[-1].startswith("image") or parts[-1] in ("compressed", "theora",
                                                                                   "compressedDepth")):
            parts.pop()
        return "/".join(parts)
    return f"ring/{name}"


def _numbers(entry: Mapping[str, Any], key: str, n: Optional[int], source: str, where: str) -> np.ndarray:
    value = entry.get(key)
    if value is None:
        raise ConfigError("missing", path=source, key=f"{where}.{key}")
    try:
        arr = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise ConfigError("expected a list of numbers", path=source, key=f"{where}.{key}") from None
    if n is not None and arr.size != n:
        raise ConfigError(f"expected {n} numbers, got {arr.size}", path=source, key=f"{where}.{key}")
    if not np.all(np.isfinite(arr)):
        raise ConfigError("contains NaN or infinite values", path=source, key=f"{where}.{key}")
    return arr


def _model(entry: Mapping[str, Any], name: str, source: str) -> CameraModel:
    projection = str(entry.get("camera_model", "pinhole"))
    if projection != "pinhole":
        raise ConfigError(f"camera model {projection!r} cannot be represented (the package's cameras are pinhole "
                          f"with plumb_bob, rational_polynomial or equidistant distortion): calibrate {name} with "
                          f"camera_model pinhole", path=source, key=f"{name}.camera_model")
    fx, fy, cx, cy = _numbers(entry, "intrinsics", 4, source, name)
    res = _numbers(entry, "resolution", 2, source, name)
    dist = str(entry.get("distortion_model", "none")).lower()
    coeffs = _numbers(entry, "distortion_coeffs", None, source, name) if "distortion_coeffs" in entry else np.zeros(0)
    if dist not in DISTORTION_MODELS:
        what = UNSUPPORTED_DISTORTION.get(dist, "an unknown model")
        raise ConfigError(f"distortion model {dist!r} ({what}) cannot be represented by the package's camera model "
                          f"(plumb_bob = Kalibr radtan, rational_polynomial, equidistant): calibrate {name} again "
                          f"with radtan or equidistant", path=source, key=f"{name}.distortion_model")
    model_name, counts = DISTORTION_MODELS[dist]
    if dist == "none":
        if np.any(coeffs):
            raise ConfigError(f"distortion model none with non-zero coefficients {coeffs.tolist()}", path=source,
                              key=f"{name}.distortion_coeffs")
        coeffs = np.zeros(0)
    if coeffs.size not in counts:
        raise ConfigError(f"{dist} takes {' or '.join(map(str, counts))} coefficients, got {coeffs.size}",
                          path=source, key=f"{name}.distortion_coeffs")
    if res[0] != int(res[0]) or res[1] != int(res[1]):
        raise ConfigError(f"expected integer [width, height], got {res.tolist()}", path=source, key=f"{name}.resolution")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    try:
        return CameraModel(K=K, D=coeffs, distortion_model=model_name, width=int(res[0]), height=int(res[1]),
                           name=name)
    except ConfigError as exc:
        raise ConfigError(exc.detail, path=source, key=f"{name}.{exc.key}" if exc.key else name) from None


def _matrix(entry: Mapping[str, Any], key: str, name: str, source: str) -> Optional[np.ndarray]:
    if key not in entry:
        return None
    arr = _numbers(entry, key, 16, source, name).reshape(4, 4)
    try:
        return geo.validate_transform(arr, f"{name}.{key}")
    except GeometryError as exc:
        raise ConfigError(str(exc), path=source, key=f"{name}.{key}") from None


def _tagslam_std(node: Mapping[str, Any], path: str, name: str) -> Optional[Tuple[float, ...]]:
    """The 1-sigma per axis (rotation rad x3, translation m x3) from a TagSLAM pose's ``R`` (the
    upper-triangular square-root information matrix, 36 numbers row-major), or None without one."""
    if "R" not in node:
        return None
    key = f"{name}.pose.R"
    try:
        R = np.array([float(v) for v in node["R"]], dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError("expected 36 numbers (the pose's square-root information matrix)", path=path,
                          key=key) from None
    if R.size != 36 or not np.all(np.isfinite(R)):
        raise ConfigError(f"expected 36 finite numbers (a 6x6 square-root information matrix), got {R.size}",
                          path=path, key=key)
    R = np.triu(R.reshape(6, 6))   # TagSLAM writes the upper triangle; anything below is not R's
    if np.min(np.abs(np.diag(R))) <= 0.0:
        raise ConfigError("singular square-root information matrix (a zero on its diagonal)", path=path, key=key)
    Rinv = np.linalg.solve(R, np.eye(6))
    return tuple(float(v) for v in np.sqrt(np.sum(Rinv * Rinv, axis=1)))   # diag((R^T R)^-1)


def _tagslam_poses(path: str) -> Dict[str, Tuple[np.ndarray, Optional[Tuple[float, ...]]]]:
    """TagSLAM ``camera_poses.yaml``: camera -> (``T_rig_cam`` (position + rotation vector), its
    1-sigma per axis from ``R`` or None)."""
    data = load_yaml_file(path)
    if not isinstance(data, Mapping):
        raise ConfigError("expected a mapping of cameras", path=path)
    out = {}
    for name, node in data.items():
        pose = node.get("pose") if isinstance(node, Mapping) else None
        if not isinstance(pose, Mapping):
            raise ConfigError("expected {pose: {position: {x, y, z}, rotation: {x, y, z}}}", path=path, key=str(name))
        vec = {}
        for part in ("position", "rotation"):
            p = pose.get(part)
            try:
                vec[part] = np.array([float(p[a]) for a in ("x", "y", "z")])
            except (TypeError, KeyError, ValueError):
                raise ConfigError("expected {x, y, z} numbers", path=path, key=f"{name}.pose.{part}") from None
            if not np.all(np.isfinite(vec[part])):
                raise ConfigError("contains NaN or infinite values", path=path, key=f"{name}.pose.{part}")
        out[str(name)] = (geo.transform_from_rvec_tvec(vec["rotation"], vec["position"]),
                          _tagslam_std(pose, path, str(name)))
    return out


def read_rig(path: str, camera_poses: Optional[str] = None, base_frame: str = "rig") -> ImportedRig:
    """Read a Kalibr camchain or a TagSLAM ``cameras.yaml`` (see the module docstring).

    Args:
        path: the camchain / cameras file.
        camera_poses: TagSLAM ``camera_poses.yaml``; None = the one beside ``path`` if there is one.
        base_frame: name of the rig's base frame in the ring file.

    Raises:
        ConfigError: naming the file and key of anything unreadable or unrepresentable. Cameras
            without a pose are *not* an error here (:meth:`ImportedRig.ring` reports them).
    """
    data = load_yaml_file(path)
    if not isinstance(data, Mapping) or not data or not all(isinstance(v, Mapping) for v in data.values()):
        raise ConfigError("expected a mapping camera name -> {intrinsics, distortion_model, ...}", path=path)
    if camera_poses is None:
        beside = os.path.join(os.path.dirname(os.path.abspath(path)), "camera_poses.yaml")
        camera_poses = beside if os.path.exists(beside) and os.path.abspath(beside) != os.path.abspath(path) else None
    names = _camera_order(data.keys())
    cams: List[ImportedCamera] = []
    for name in names:
        entry = data[name]
        frame = str(entry.get("frame_id") or f"{name}_optical_frame").strip("/").replace("/", "_")
        cams.append(ImportedCamera(name, _model(entry, name, path), None, _namespace(entry, name), frame,
                                   str(entry.get("tagtopic") or entry.get("rostopic") or ""),
                                   wiggle=_wiggle(entry, name, path)))
    shared = {ns: [c.name for c in cams if c.namespace == ns] for ns in {c.namespace for c in cams}}
    shared = {ns: names_ for ns, names_ in shared.items() if len(names_) > 1}
    if shared:
        ns, names_ = sorted(shared.items())[0]
        raise ConfigError(f"cameras {names_} would share the namespace '{ns}' (from their tagtopic / rostopic): the "
                          f"nodes and the bag source find a camera's topics under its own namespace; give each "
                          f"camera a topic of its own namespace (e.g. /{ns}/<camera>/tags)", path=path)
    sources = [path]
    notes: List[str] = []
    if camera_poses is not None:
        poses = _tagslam_poses(camera_poses)
        sources.append(camera_poses)
        for c in cams:
            if c.name in poses:
                (c.T_base_cam, c.extrinsics_std), c.pose_source = poses[c.name], os.path.basename(camera_poses)
        unknown = sorted(set(poses) - set(names))
        if unknown:
            notes.append(f"{camera_poses}: poses of cameras not in {path} ignored: {unknown}")
        bodies = sorted({str(data[n].get("rig_body")) for n in names if data[n].get("rig_body")})
        definition = (f"TagSLAM's rig body{' ' + bodies[0] if len(bodies) == 1 else ''} "
                      f"(the frame camera_poses.yaml gives the camera poses in)")
    else:
        imu = {c.name: _matrix(data[c.name], "T_cam_imu", c.name, path) for c in cams}
        chain = {c.name: _matrix(data[c.name], "T_cn_cnm1", c.name, path) for c in cams}
        if all(imu[c.name] is not None for c in cams):
            for c in cams:
                c.T_base_cam, c.pose_source = geo.inverse(imu[c.name]), "T_cam_imu"
            definition = "the IMU frame of the Kalibr camera-IMU calibration (T_cam_imu)"
        else:
            cams[0].T_base_cam, cams[0].pose_source = np.eye(4), "base frame"
            for prev, c in zip(cams, cams[1:]):
                T = chain[c.name]
                if T is not None and prev.T_base_cam is not None:
                    c.T_base_cam, c.pose_source = prev.T_base_cam @ geo.inverse(T), "T_cn_cnm1"
            definition = f"camera {cams[0].name}'s optical frame (z forward, x right, y down)"
            if len(cams) > 1 and any(imu[c.name] is not None for c in cams):
                notes.append("T_cam_imu is not given for every camera: the cameras are chained with T_cn_cnm1")
    wiggling = [c for c in cams if c.wiggle is not None and max(c.wiggle) > TAGSLAM_DEFAULT_WIGGLE]
    if wiggling:
        notes.append(f"{path} declares wiggle for {', '.join(c.name for c in wiggling)} (largest "
                     f"{max(c.wiggle[0] for c in wiggling):g} rad / {max(c.wiggle[1] for c in wiggling):g} m): TagSLAM "
                     f"lets each camera move against the rig in every frame, and its camera poses are the mean pose "
                     f"each wiggles about; written to the ring file as each camera's wiggle (calibrate-ring then "
                     f"estimates that mean pose too; a rigid calibration, --wiggle off, need not agree with those "
                     f"poses within their noise)")
    invented = [c.name for c in cams if c.T_base_cam is not None and c.extrinsics_std is None]
    if invented:
        notes.append(f"no uncertainty is given for the pose of {', '.join(invented)}: the ring file's default "
                     f"extrinsics_std ({DEFAULT_EXTRINSICS_STD_TRANSLATION * 1000:g} mm / "
                     f"{DEFAULT_EXTRINSICS_STD_ROTATION_DEG:g} deg per axis) applies, a guess: state your "
                     f"calibration's in the ring file (0: exact)")
    for n in notes:
        logger.warning("%s", n)
    return ImportedRig(cams, base_frame, definition, " + ".join(sources), notes)


def write_ring_files(ring: CameraRing, ring_path: str, camera_info_dir: Optional[str] = None) -> List[str]:
    """Write ``camera_info/<cam>.yaml`` for every camera and the ring file referring to them.

    Args:
        ring: the ring.
        ring_path: the ring YAML to write.
        camera_info_dir: where the camera_info files go (default: ``camera_info/`` beside the ring).

    Returns:
        The files written (all atomically), ring file last.
    """
    ring_path = os.path.abspath(ring_path)
    base = os.path.dirname(ring_path)
    info_dir = os.path.abspath(camera_info_dir) if camera_info_dir else os.path.join(base, "camera_info")
    written, refs = [], {}
    for cam in ring.cameras:
        p = os.path.join(info_dir, f"{cam.name}.yaml")
        save_camera_yaml(cam.model, p)
        written.append(p)
        refs[cam.name] = os.path.relpath(p, base)
    ring.save(ring_path, camera_info_files=refs)
    written.append(ring_path)
    return written
