"""Camera intrinsics and lens distortion: :class:`CameraModel`.

A camera is described as in ROS ``sensor_msgs/CameraInfo``: the 3x3 matrix ``K`` (pixels), a
distortion model name and its coefficients ``D``, and the image size. Three models are supported:

* ``plumb_bob`` (OpenCV's radial-tangential, D = k1 k2 p1 p2 [k3]),
* ``rational_polynomial`` (D = k1 k2 p1 p2 k3 k4 k5 k6),
* ``equidistant`` (fisheye, D = k1 k2 k3 k4 on the angle from the optical axis).

Points in the camera's optical frame (z forward, x right, y down, metres) project to raw image
pixels with :meth:`CameraModel.project`; :meth:`CameraModel.normalize` goes back from raw pixels to
undistorted normalised coordinates (x/z, y/z). Files use the camera_calibration_parsers YAML
layout (``image_width``, ``camera_matrix: {rows, cols, data}``, ``distortion_model``, ...).
"""
from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field
from typing import Any, Dict, Mapping, Optional

import cv2
import numpy as np
import yaml

from .errors import ConfigError, MeasurementError

#: :meth:`CameraModel.normalize`'s iteration: up to 50 rounds, to 1e-12.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)

logger = logging.getLogger(__name__)

#: Distortion model name -> accepted numbers of coefficients.
DISTORTION_LENGTHS = {
    "plumb_bob": (0, 4, 5),
    "rational_polynomial": (8,),
    "equidistant": (4,),
}


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with lens distortion.

    Attributes:
        K: (3, 3) intrinsic matrix in pixels.
        D: distortion coefficients, length fixed by ``distortion_model``.
        distortion_model: ``plumb_bob``, ``rational_polynomial`` or ``equidistant``.
        width, height: image size in pixels.
        name: camera name (from the file's ``camera_name``), informational.
    """

    K: np.ndarray
    D: np.ndarray
    distortion_model: str
    width: int
    height: int
    name: str = ""
    _D_full: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        D = np.asarray(self.D, dtype=np.float64).ravel()
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "D", D)
        problem = _check_intrinsics(K, D, self.distortion_model, self.width, self.height)
        if problem:
            key, msg = problem
            raise ConfigError(msg, key=key)
        if self.distortion_model == "plumb_bob":
            full = np.zeros(5)
            full[: D.size] = D
        else:
            full = D.copy()
        object.__setattr__(self, "_D_full", full)

    def __eq__(self, other: object) -> bool:
        # The dataclass-generated __eq__ compares the arrays with ``==`` inside a tuple and raises
        # "truth value of an array is ambiguous" for two equal models loaded separately.
        if not isinstance(other, CameraModel):
            return NotImplemented
        return (self.distortion_model == other.distortion_model and self.width == other.width
                and self.height == other.height and self.name == other.name
                and np.array_equal(self.K, other.K) and np.array_equal(self.D, other.D))

    # --- construction ------------------------------------------------------------------------

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "<camera_info>") -> "CameraModel":
        """Build from a camera_calibration_parsers-style mapping; errors name ``source`` and the key."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"expected a mapping of camera_info keys, got {type(data).__name__}", path=source)
        K = _read_matrix(data, "camera_matrix", (3, 3), source)
        model = data.get("distortion_model", "plumb_bob")
        if not isinstance(model, str) or model not in DISTORTION_LENGTHS:
            raise ConfigError(f"unknown distortion model {model!r}; expected one of "
                              f"{sorted(DISTORTION_LENGTHS)}", path=source, key="distortion_model")
        D = _read_vector(data, "distortion_coefficients", source) if "distortion_coefficients" in data else np.zeros(0)
        width = _read_positive_int(data, "image_width", source)
        height = _read_positive_int(data, "image_height", source)
        name = str(data.get("camera_name", ""))
        try:
            return cls(K=K, D=D, distortion_model=model, width=width, height=height, name=name)
        except ConfigError as exc:
            raise ConfigError(str(exc).split(": ", 1)[-1], path=source, key=exc.key) from None

    @classmethod
    def from_yaml(cls, path: str) -> "CameraModel":
        """Load a camera_info YAML file (as written by camera_calibration / camera_info_manager)."""
        return cls.from_dict(load_yaml_file(path), source=str(path))

    @classmethod
    def from_camera_info(cls, K, D, distortion_model: str, width: int, height: int,
                         name: str = "") -> "CameraModel":
        """Build from the fields of a ``sensor_msgs/CameraInfo`` message (K row-major, 9 values).

        Raises :class:`MeasurementError` naming the field when the message is unusable.
        """
        K = np.asarray(K, dtype=np.float64).ravel()
        if K.size != 9:
            raise MeasurementError(f"camera_info.K: expected 9 values, got {K.size}")
        model = distortion_model or "plumb_bob"
        if model not in DISTORTION_LENGTHS:
            raise MeasurementError(f"camera_info.distortion_model: unknown model {model!r}")
        try:
            return cls(K=K.reshape(3, 3), D=np.asarray(D, dtype=np.float64), distortion_model=model,
                       width=int(width), height=int(height), name=name)
        except ConfigError as exc:
            raise MeasurementError(f"camera_info.{exc.key}: {str(exc).split(': ', 1)[-1]}") from None

    def to_dict(self) -> Dict[str, Any]:
        """The camera_calibration_parsers YAML mapping of this model."""
        P = np.zeros((3, 4))
        P[:3, :3] = self.K
        return {
            "image_width": int(self.width),
            "image_height": int(self.height),
            "camera_name": self.name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": [float(v) for v in self.K.ravel()]},
            "distortion_model": self.distortion_model,
            "distortion_coefficients": {"rows": 1, "cols": int(self.D.size),
                                        "data": [float(v) for v in self.D]},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": [float(v) for v in np.eye(3).ravel()]},
            "projection_matrix": {"rows": 3, "cols": 4, "data": [float(v) for v in P.ravel()]},
        }

    # --- properties -------------------------------------------------------------------------

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def is_fisheye(self) -> bool:
        return self.distortion_model == "equidistant"

    @property
    def opencv_distortion(self) -> np.ndarray:
        """Coefficients in the layout OpenCV's pinhole functions take (zeros for ``plumb_bob`` without D)."""
        return self._D_full

    def horizontal_fov(self) -> float:
        """Horizontal field of view in rad, measured through the distortion along the centre row."""
        left = self.normalize(np.array([[0.0, self.cy]]))[0, 0]
        right = self.normalize(np.array([[self.width - 1.0, self.cy]]))[0, 0]
        return float(np.arctan(-left) + np.arctan(right)) if not self.is_fisheye else \
            float(_fisheye_angle(left) + _fisheye_angle(right))

    def frustum_segments(self, depth: float) -> np.ndarray:
        """(16, 3) end points of the 8 segments that draw the field of view in the optical frame, for
        rviz: the rays through the four image corners (undistorted) from the centre to ``depth`` m
        along z, and the rectangle joining their ends."""
        corners = np.array([[0.0, 0.0], [self.width - 1.0, 0.0], [self.width - 1.0, self.height - 1.0],
                            [0.0, self.height - 1.0]])
        xy = self.normalize(corners)
        ends = depth * np.column_stack([xy, np.ones(4)])
        segments = []
        for k in range(4):
            segments += [np.zeros(3), ends[k], ends[k], ends[(k + 1) % 4]]
        return np.asarray(segments)

    # --- projection -------------------------------------------------------------------------

    def distort_normalized(self, xy) -> np.ndarray:
        """Undistorted normalised coordinates (N, 2) -> distorted normalised coordinates (N, 2)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        x, y = xy[:, 0], xy[:, 1]
        d = self._D_full
        if self.is_fisheye:
            r = np.hypot(x, y)
            theta = np.arctan(r)
            t2 = theta * theta
            theta_d = theta * (1 + d[0] * t2 + d[1] * t2 ** 2 + d[2] * t2 ** 3 + d[3] * t2 ** 4)
            scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
            return xy * scale[:, None]
        r2 = x * x + y * y
        radial = 1 + d[0] * r2 + d[1] * r2 ** 2 + d[4] * r2 ** 3
        if self.distortion_model == "rational_polynomial":
            radial = radial / (1 + d[5] * r2 + d[6] * r2 ** 2 + d[7] * r2 ** 3)
        xd = x * radial + 2 * d[2] * x * y + d[3] * (r2 + 2 * x * x)
        yd = y * radial + d[2] * (r2 + 2 * y * y) + 2 * d[3] * x * y
        return np.stack([xd, yd], axis=1)

    def project(self, points_cam) -> np.ndarray:
        """Project (N, 3) points in the optical frame to raw pixels (N, 2).

        Points at or behind the camera (z <= 1e-9) give NaN rows; use :meth:`visible` to filter.
        """
        P = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        z = P[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = P[:, :2] / z[:, None]
        xy[z <= 1e-9] = np.nan
        return self.pixels_from_normalized(self.distort_normalized(xy))

    def pixels_from_normalized(self, xy_distorted) -> np.ndarray:
        """Distorted normalised coordinates (N, 2) -> pixels (N, 2), applying K (with skew)."""
        xy = np.asarray(xy_distorted, dtype=np.float64).reshape(-1, 2)
        K = self.K
        u = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
        v = K[1, 1] * xy[:, 1] + K[1, 2]
        return np.stack([u, v], axis=1)

    def normalize(self, pixels) -> np.ndarray:
        """Raw pixels (N, 2) -> undistorted normalised coordinates (N, 2), i.e. (x/z, y/z).

        Iterative inversion of the distortion (OpenCV), accurate to well below 1e-6 for the
        field of view of the lens; the round trip ``normalize(project(p))`` is tested.
        """
        # (no copy of a contiguous float64 input, what the localizer hands in every frame: OpenCV
        # only reads it; the skew's correction below writes to a copy)
        px = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if px.shape[0] == 0:
            return np.zeros((0, 2))
        K = self.K
        if K[0, 1] != 0.0:
            # OpenCV's undistortion ignores the skew K[0, 1] that project() applies: remove it
            # here (u' = u - s * y_d) and hand OpenCV a skew-free K.
            px = px.copy()
            px[:, 0, 0] -= K[0, 1] * (px[:, 0, 1] - K[1, 2]) / K[1, 1]
            K = K.copy()
            K[0, 1] = 0.0
        if self.is_fisheye:
            out = cv2.fisheye.undistortPoints(px, K, self._D_full.reshape(4, 1))
        else:
            out = cv2.undistortPointsIter(px, K, self._D_full, None, None, _UNDISTORT_CRITERIA)
        return out.reshape(-1, 2)

    def pixel_jacobian(self, xy, step: float = 1e-6) -> np.ndarray:
        """(N, 2, 2) Jacobian of the raw pixels with respect to undistorted normalised coordinates
        ``xy`` (N, 2), by central differences: how far a raw pixel moves per unit of x/z and y/z
        (``diag(fx, fy)`` for a camera without distortion)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        n = len(xy)
        out = np.zeros((n, 2, 2))
        # The four displaced copies through the lens model at once (one call each, not four).
        d = np.array([[step, 0.0], [-step, 0.0], [0.0, step], [0.0, -step]])
        px = self.pixels_from_normalized(self.distort_normalized((xy[None] + d[:, None]).reshape(-1, 2)))
        px = px.reshape(4, n, 2)
        for j in range(2):
            out[:, :, j] = (px[2 * j] - px[2 * j + 1]) / (2.0 * step)
        return out

    def undistort_pixels(self, pixels) -> np.ndarray:
        """Raw pixels -> pixels of the ideal (distortion-free) pinhole camera with the same K."""
        xy = self.normalize(pixels)
        return np.stack([self.fx * xy[:, 0] + self.K[0, 1] * xy[:, 1] + self.cx,
                         self.fy * xy[:, 1] + self.cy], axis=1)

    def in_image(self, pixels, margin: float = 0.0) -> np.ndarray:
        """Boolean mask (N,) of pixels inside the image, ``margin`` pixels away from the border."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            return ((px[:, 0] >= margin) & (px[:, 0] <= self.width - 1 - margin)
                    & (px[:, 1] >= margin) & (px[:, 1] <= self.height - 1 - margin))


def _fisheye_angle(x_norm: float) -> float:
    return float(np.arctan(abs(x_norm)))


def _check_intrinsics(K: np.ndarray, D: np.ndarray, model: str, width: int, height: int):
    """Return (key, message) describing the first problem, or None when the intrinsics are valid."""
    if K.shape != (3, 3):
        return "camera_matrix", f"expected a 3x3 matrix, got shape {K.shape}"
    if not np.all(np.isfinite(K)):
        return "camera_matrix", "contains NaN or infinite values"
    if not np.any(K):
        return "camera_matrix", "is all zeros (the camera is not calibrated)"
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return "camera_matrix", f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}"
    if abs(K[2, 2] - 1.0) > 1e-9 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0:
        return "camera_matrix", "last row must be [0, 0, 1] and the lower triangle zero"
    if model not in DISTORTION_LENGTHS:
        return "distortion_model", f"unknown distortion model {model!r}; expected one of {sorted(DISTORTION_LENGTHS)}"
    if D.size not in DISTORTION_LENGTHS[model]:
        return ("distortion_coefficients",
                f"model {model} takes {' or '.join(map(str, DISTORTION_LENGTHS[model]))} coefficients, got {D.size}")
    if not np.all(np.isfinite(D)):
        return "distortion_coefficients", "contains NaN or infinite values"
    if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))) \
            or width <= 0 or height <= 0:
        return "image_width", f"image size must be positive integers, got {width}x{height}"
    return None


class _UniqueKeyLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
    """yaml's safe loader (the C parser when libyaml is there: a 1,000-marker map loads ~6x
    faster) that refuses a key repeated in one mapping (PyYAML silently keeps the last, so a
    hand edit that adds a second ``image_width:`` or ``markers:`` would go unnoticed)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = set()
            for key_node, _ in node.value:
                # A plain string key is its text: no need to construct every key twice.
                key = key_node.value if key_node.tag == _STR_TAG and isinstance(key_node, yaml.ScalarNode) \
                    else self.construct_object(key_node, deep=deep)
                try:
                    duplicate = key in seen
                    seen.add(key)
                except TypeError:  # unhashable key: the base class reports it
                    continue
                if duplicate:
                    raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key!r}",
                                                            key_node.start_mark)
        return super().construct_mapping(node, deep)


_STR_TAG = "tag:yaml.org,2002:str"

#: Largest YAML file :func:`load_yaml_file` reads by default (ring, camera_info, scene files), bytes.
MAX_YAML_FILE_BYTES = 4 * 1024 * 1024

# The plain scalars PyYAML's safe loader reads as a float or an int, in the forms our writers use
# (the first patterns of yaml.resolver's float and int resolvers; every other form goes to it).
_PLAIN_FLOAT = re.compile(r"[-+]?[0-9][0-9_]*\.[0-9_]*(?:[eE][-+][0-9]+)?\Z")
_PLAIN_INT = re.compile(r"[-+]?(?:0|[1-9][0-9_]*)\Z")
_SIMPLE = (str, bool, int, float, type(None))


class _Unusual(Exception):
    """Something :func:`_fast_safe_load` leaves to the full loader (tags, merge keys, duplicates)."""


def _fast_safe_load(text: str) -> Any:
    """``yaml.load(text, Loader=_UniqueKeyLoader)`` for the common case, built from libyaml's events.

    PyYAML's C loader still builds a node per scalar and resolves and constructs each in Python:
    a 5,000-marker map took 0.7-1.1 s of CPU. Here the C parser's events become dicts and lists
    directly (no recursion, anchors and aliases shared as PyYAML shares them), and plain scalars
    that are decimal floats or ints are converted at once; any other plain scalar goes through the
    loader's own resolver and constructor. Anything else (an explicit tag, a merge key, a
    duplicate key, a second document, a scalar that is not a str/bool/int/float/null, a parse
    error) raises :class:`_Unusual` or the parser's error, and the caller uses the full loader,
    which gives its own result or error: the outcome is always the full loader's.
    """
    loader = _UniqueKeyLoader("")
    cache: Dict[str, Any] = {}

    def plain(value: str) -> Any:
        if _PLAIN_FLOAT.match(value):
            return float(value.replace("_", ""))
        if _PLAIN_INT.match(value):
            return int(value.replace("_", ""))
        if value in cache:
            return cache[value]
        tag = loader.resolve(yaml.ScalarNode, value, (True, False))
        try:
            obj = loader.construct_object(yaml.ScalarNode(tag, value))
        except Exception:  # noqa: BLE001 - whatever it is, the full loader reports it its own way
            raise _Unusual from None
        if type(obj) not in _SIMPLE or tag == "tag:yaml.org,2002:merge":
            raise _Unusual
        cache[value] = obj
        return obj

    anchors: Dict[str, Any] = {}
    stack: list = []        # [container, pending key]; _NO_KEY when a mapping waits for a key
    root: list = []
    documents = 0
    for ev in yaml.parse(text, Loader=_UniqueKeyLoader):
        kind = type(ev)
        if kind is yaml.ScalarEvent:
            if ev.tag is not None:
                raise _Unusual
            value = plain(ev.value) if ev.implicit[0] else ev.value
        elif kind is yaml.AliasEvent:
            if ev.anchor not in anchors:
                raise _Unusual
            value = anchors[ev.anchor]
        elif kind is yaml.MappingStartEvent or kind is yaml.SequenceStartEvent:
            if ev.tag is not None and not ev.implicit:
                raise _Unusual
            value = {} if kind is yaml.MappingStartEvent else []
        elif kind is yaml.MappingEndEvent or kind is yaml.SequenceEndEvent:
            stack.pop()
            continue
        elif kind is yaml.DocumentStartEvent:
            documents += 1
            if documents > 1:
                raise _Unusual
            continue
        else:  # stream start/end, document end
            continue
        if getattr(ev, "anchor", None) is not None and kind is not yaml.AliasEvent:
            anchors[ev.anchor] = value
        if not stack:
            root.append(value)
        else:
            top = stack[-1]
            container = top[0]
            if type(container) is list:
                container.append(value)
            elif top[1] is _NO_KEY:
                if type(value) not in _SIMPLE or value in container:
                    raise _Unusual  # a container as key, or a duplicate key: the full loader says so
                top[1] = value
            else:
                container[top[1]] = value
                top[1] = _NO_KEY
        if kind is yaml.MappingStartEvent or kind is yaml.SequenceStartEvent:
            stack.append([value, _NO_KEY])
    return root[0] if root else None


_NO_KEY = object()

#: Most values a YAML document may expand to, aliases counted at every use (a 32 MiB map holds about
#: 4 million). A "billion laughs" file (aliases of aliases) is small on disk but expands to far more:
#: the first numpy call on it would try to allocate terabytes.
MAX_YAML_VALUES = 10_000_000


def _expanded_size(root: Any, limit: int) -> Optional[str]:
    """Why the document ``root`` must not be used (it expands beyond ``limit`` values, or refers to
    itself), or None. Linear in the distinct lists and dicts (shared ones are counted once, with
    their size, at every use)."""
    sizes: Dict[int, int] = {}
    entered = set()
    stack = [(root, False)]
    while stack:
        obj, done = stack.pop()
        kind = type(obj)
        if kind is not list and kind is not dict:
            continue
        oid = id(obj)
        children = obj.values() if kind is dict else obj
        if done:
            entered.discard(oid)
            n = 1 + (len(obj) if kind is dict else 0) + sum(
                sizes[id(c)] if type(c) is list or type(c) is dict else 1 for c in children)
            if n > limit:
                return f"its aliases expand it to more than {limit:,} values (a YAML bomb?)"
            sizes[oid] = n
            continue
        if oid in sizes:
            continue
        if oid in entered:
            return "it contains itself (a recursive alias)"
        entered.add(oid)
        stack.append((obj, True))
        stack.extend((c, False) for c in children if (type(c) is list or type(c) is dict) and id(c) not in sizes)
    return None


def load_yaml_file(path: str, max_bytes: int = MAX_YAML_FILE_BYTES) -> Any:
    """Read a YAML file; any failure becomes a ConfigError naming the file (and line, if known).

    A key repeated in one mapping is an error too (naming the key and its line), and so is a file
    larger than ``max_bytes`` (refused before it is parsed: parse time and memory grow with it) or
    one whose aliases expand it beyond :data:`MAX_YAML_VALUES` values or make it recursive.
    YAML's safe subset only (no Python objects); the common case takes the fast route
    (:func:`_fast_safe_load`), with the same result.
    """
    try:
        with open(path, "r", encoding="utf-8") as handle:
            size = os.fstat(handle.fileno()).st_size
            if size > max_bytes:
                raise ConfigError(f"file is {size / 2 ** 20:.1f} MiB, more than the {max_bytes / 2 ** 20:.0f} MiB "
                                  "this file type may have", path=str(path))
            text = handle.read()
        try:
            data = _fast_safe_load(text)
        except (_Unusual, yaml.YAMLError, RecursionError):
            data = yaml.load(text, Loader=_UniqueKeyLoader)
    except FileNotFoundError:
        raise ConfigError("file not found", path=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read file ({exc})", path=str(path)) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise ConfigError(f"invalid YAML{where}: {getattr(exc, 'problem', exc)}", path=str(path)) from None
    except RecursionError:
        raise ConfigError("invalid YAML: nested too deeply", path=str(path)) from None
    if data is None:
        raise ConfigError("file is empty", path=str(path))
    problem = _expanded_size(data, MAX_YAML_VALUES)
    if problem:
        raise ConfigError(f"refused: {problem}", path=str(path))
    return data


def _read_matrix(data: Mapping[str, Any], key: str, shape, source: str) -> np.ndarray:
    if key not in data:
        raise ConfigError("missing", path=source, key=key)
    node = data[key]
    values = node.get("data") if isinstance(node, Mapping) else node
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"expected {shape[0] * shape[1]} numbers", path=source, key=f"{key}.data") from None
    if arr.size != shape[0] * shape[1]:
        raise ConfigError(f"expected {shape[0] * shape[1]} numbers, got {arr.size}", path=source, key=f"{key}.data")
    if isinstance(node, Mapping):
        rows, cols = node.get("rows", shape[0]), node.get("cols", shape[1])
        if (rows, cols) != shape:
            raise ConfigError(f"expected rows={shape[0]}, cols={shape[1]}, got rows={rows}, cols={cols}",
                              path=source, key=key)
    return arr.reshape(shape)


def _read_vector(data: Mapping[str, Any], key: str, source: str) -> np.ndarray:
    node = data[key]
    if isinstance(node, Mapping) and "data" not in node:
        # A truncated file must not silently become a camera without distortion.
        raise ConfigError("missing", path=source, key=f"{key}.data")
    values = node.get("data") if isinstance(node, Mapping) else node
    try:
        arr = np.asarray(values if values is not None else [], dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise ConfigError("expected a list of numbers", path=source, key=f"{key}.data") from None
    if isinstance(node, Mapping) and "rows" in node and "cols" in node:
        rows, cols = node["rows"], node["cols"]
        if not (isinstance(rows, int) and isinstance(cols, int)) or rows * cols != arr.size:
            raise ConfigError(f"rows={rows!r}, cols={cols!r} do not match the {arr.size} values in data",
                              path=source, key=key)
    return arr


def _read_positive_int(data: Mapping[str, Any], key: str, source: str) -> int:
    if key not in data:
        raise ConfigError("missing", path=source, key=key)
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ConfigError(f"expected a positive integer, got {value!r}", path=source, key=key)
    return value


def save_camera_yaml(model: CameraModel, path: str) -> None:
    """Write ``model`` as a camera_info YAML file (atomically)."""
    from .fileio import atomic_write_text

    atomic_write_text(path, yaml.safe_dump(model.to_dict(), sort_keys=False))


def model_summary(model: CameraModel) -> str:
    """One line for people: size, focal length, field of view, distortion model."""
    return (f"{model.width}x{model.height}, fx={model.fx:.1f} fy={model.fy:.1f}, "
            f"HFOV {np.degrees(model.horizontal_fov()):.1f} deg, {model.distortion_model}")


def default_model_for_tests(distortion_model: str = "plumb_bob", D: Optional[np.ndarray] = None) -> CameraModel:
    """A 1280x960 camera with about 77 deg horizontal field of view (the ring's cameras)."""
    K = np.array([[805.0, 0.0, 640.5], [0.0, 805.0, 480.5], [0.0, 0.0, 1.0]])
    defaults = {"plumb_bob": [-0.05, 0.02, 0.0005, -0.0003, 0.0],
                "rational_polynomial": [-0.05, 0.02, 0.0005, -0.0003, 0.0, 0.01, 0.005, 0.0],
                "equidistant": [-0.01, 0.005, -0.002, 0.0005]}
    return CameraModel(K=K, D=np.asarray(defaults[distortion_model] if D is None else D),
                       distortion_model=distortion_model, width=1280, height=960, name="test")
