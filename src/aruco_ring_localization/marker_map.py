"""The marker map: the pose of every mapped marker in the map frame.

:class:`MarkerMap` holds, per marker id, ``T_map_marker`` (4x4), the marker's side length, its
uncertainty and how often it was observed, plus the definition of the map frame. Look-ups are by
id (a dict), so the cost of using the map grows with the markers in view, not with its size.

File format (YAML, written atomically with the previous file kept as ``.bak``; docs/formats.md)::

    format_version: 1
    frame_id: map
    reference_marker: 3
    frame_definition: "origin on the floor below marker 3's centre, z up, x along marker 3's x made horizontal"
    method: refined
    created: "2026-11-22T10:00:00Z"
    markers:
      - id: 3
        size: 0.2                           # side of the black square, m
        translation: [1.0, 2.0, 1.2]        # m, in frame_id
        rotation: [0.5, 0.5, 0.5, 0.5]      # quaternion x, y, z, w
        position_std: [0.001, 0.001, 0.001] # m, 1 sigma per axis of the map frame
        rotation_std: [0.002, 0.002, 0.002] # rad, 1 sigma about the marker's x, y, z
        observations: 120
    ring_calibration:                       # optional: the ring extrinsics refined while mapping
      base_frame: base_link
      cameras:
        cam0: {translation: [0.12, 0.0, 0.75], rotation: [-0.5, 0.5, -0.5, 0.5]}
      covariance:                           # optional: their uncertainty (the bundle adjustment's)
        cameras: [cam0, ...]                # order of the 6 x 6 blocks
        matrix: [[...], ...]                # 6n x 6n: per camera (rx, ry, rz rad, tx, ty, tz m)
    anchors:                                # optional: the surveyed markers that define the frame
      source: plate_anchors.yaml            # (frame_convention: survey; reference_marker: null)
      frame_id: plate
      kind: points                          # pose | points | points_level
      points:
        - {marker: 3, surveyed: [0, 0, 0.45], std: [0.001, 0.001, 0.001],
           residual: [0.0004, -0.0002, 0.0001], residual_sigmas: 0.46}   # mapped - surveyed, m

The markers were estimated through the ring extrinsics. When bundle adjustment refined those
(``ring_calibration``), localizing with them instead of the original calibration removes the
calibration error from every pose (``ring_tf`` publishes them when given the map file). Their
covariance is in the convention of the ring file's ``extrinsics_std``: the error ``D`` of each
camera in its own optical frame (``T_base_cam_true = T_base_cam · D``), rotation first; it
includes the correlations between cameras (what the adjustment cannot tell apart, e.g. a turn of
the whole ring against the robot, is common to all of them).

fiducial_slam's ``map.txt`` (one marker a line: ``id x y z rx ry rz variance nObs [links...]``,
angles fixed-axis roll/pitch/yaw in degrees) is imported and exported too.
"""
from __future__ import annotations

import datetime
import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any, Dict, Iterable, Iterator, List, Mapping, Optional, Tuple

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from . import geometry as geo
from .camera import load_yaml_file
from .config import param
from .errors import ConfigError, GeometryError, MapSanityError
from .fileio import atomic_write_text
from .markers import marker_corners
from .anchors import check_anchor_report, check_measurement_report

logger = logging.getLogger(__name__)

MAP_FORMAT_VERSION = 1

#: Largest map file read, bytes (32 MiB: about 130,000 markers as the mapper writes them; a
#: 5,000-marker map is 1.2 MB). A larger file is refused before it is parsed.
MAX_MAP_FILE_BYTES = 32 * 1024 * 1024

#: Largest |coordinate| of a marker in the map frame, m (100 km: no hall is larger). A value
#: beyond it is a corrupt or hostile file: refused, naming the key, before any product overflows.
MAX_COORDINATE = 1.0e5

#: Map frame conventions (``frame_convention`` in the file).
FRAME_CONVENTIONS = {
    "floor": "origin on the floor below the reference marker's centre, z up (the ring base frame's z while "
             "mapping), x the reference marker's x made horizontal",
    "marker": "the reference marker's own frame (fiducial_slam's convention)",
    "survey": "the frame of surveyed markers (anchors): their measured positions, or one measured pose",
}


@dataclass(frozen=True)
class MapSanityLimits:
    """What a map must satisfy before it is written (:func:`marker_map.check_map`)."""

    max_extent: float = param(5000.0, "every marker within this distance of the map origin (a box larger "
                                      "than any hall or site; a diverged adjustment puts markers at 1e14 m)",
                              unit="m")
    max_rms_px: float = param(5.0, "largest reprojection RMS of the whole map and of any one marker (when "
                                   "the map records it)", unit="px")
    max_rms_sigmas: float = param(10.0, "... or this many of the corner noise the map was adjusted with "
                                        "(quality.pixel_noise, the mapping's ba.pixel_noise) where that is larger "
                                        "(10: 5 px at 0.5 px, 20 px at 2 px)")
    max_extrinsics_sigmas: float = param(6.0, "refined ring extrinsics may move at most this many prior "
                                              "standard deviations from the calibration")
    max_anchor_sigmas: float = param(5.0, "surveyed frame: every anchor mapped within this many of its survey "
                                          "std from its surveyed position (a mistyped value, a wrong id, a "
                                          "moved marker)")

    def __post_init__(self) -> None:
        for name in ("max_extent", "max_rms_px", "max_rms_sigmas", "max_extrinsics_sigmas", "max_anchor_sigmas"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"must be positive, got {getattr(self, name)!r}", key=name)



@dataclass(frozen=True)
class MarkerEntry:
    """One mapped marker.

    Attributes:
        marker_id: ArUco id.
        T_map_marker: (4, 4) pose of the marker frame in the map frame.
        size: side of the black square, m.
        position_std: (3,) 1-sigma position uncertainty along the map axes, m.
        rotation_std: (3,) 1-sigma rotation uncertainty about the marker's axes, rad.
        observations: number of corner observations that went into the estimate.
        ambiguous: the orientation is one of the two IPPE solutions of views from one viewpoint
            (its rotation_std covers the other solution); another view resolves it.
        rms_px: reprojection RMS of its observations in the map (None: not recorded).
        surveyed_only: the pose is the survey's alone (an anchor with a full pose that the
            recording never detected), its std the survey's; no observation went into it.
    """

    marker_id: int
    T_map_marker: np.ndarray
    size: float
    position_std: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation_std: np.ndarray = field(default_factory=lambda: np.zeros(3))
    observations: int = 0
    ambiguous: bool = False
    rms_px: Optional[float] = None
    surveyed_only: bool = False

    def corners_in_map(self) -> np.ndarray:
        """(4, 3) corners in the map frame, aruco_detect order."""
        return geo.transform_points(self.T_map_marker, marker_corners(self.size))


class MarkerMap:
    """Marker poses in one map frame, with the frame's definition.

    Args:
        entries: the markers.
        frame_id: name of the map frame (``map``; ``aruco_map`` beside gmapping).
        reference_marker: id that fixes the frame (the gauge), or None.
        frame_definition: human-readable definition of the frame.
        method: how it was built (``paper``, ``refined``, ``imported``, ...).
    """

    def __init__(self, entries: Iterable[MarkerEntry] = (), frame_id: str = "map",
                 reference_marker: Optional[int] = None, frame_definition: str = "", method: str = "",
                 created: str = "", ring_extrinsics: Optional[Mapping[str, np.ndarray]] = None,
                 ring_base_frame: str = "base_link", frame_convention: str = ""):
        self._entries: Dict[int, MarkerEntry] = {}
        #: camera name -> refined ``T_base_cam`` (4x4), empty when the map carries no calibration.
        self.ring_extrinsics: Dict[str, np.ndarray] = {
            str(k): geo.validate_transform(v, f"ring extrinsics of {k}") for k, v in (ring_extrinsics or {}).items()}
        self.ring_base_frame = ring_base_frame
        #: prior std of the calibration the extrinsics were refined from: {"translation": m, "rotation": rad}.
        self.ring_prior_sigma: Dict[str, float] = {}
        #: camera -> (translation m, rotation rad) the refinement moved it from the calibration.
        self.ring_moved: Dict[str, Tuple[float, float]] = {}
        #: ``floor`` / ``marker`` (:data:`FRAME_CONVENTIONS`), "" when the file does not say.
        self.frame_convention = frame_convention
        #: how the map came about: reprojection_rms_px, stations, station_model, notes (free-form).
        self.quality: Dict[str, Any] = {}
        #: (6n, 6n) covariance of the refined extrinsics of ``ring_covariance_cameras`` (see the
        #: module doc), or None.
        self.ring_extrinsics_covariance: Optional[np.ndarray] = None
        self.ring_covariance_cameras: List[str] = []
        #: the surveyed markers that define the frame, with their residuals (:func:`anchors.anchor_report`),
        #: or None (the reference marker's frame).
        self.anchors: Optional[Dict[str, Any]] = None
        self._corners: Dict[int, np.ndarray] = {}
        self.frame_id = frame_id
        self.reference_marker = reference_marker
        self.frame_definition = frame_definition
        self.method = method
        self.created = created
        for e in entries:
            self.add(e)

    def add(self, entry: MarkerEntry) -> None:
        """Add or replace a marker (validated)."""
        T = geo.validate_transform(entry.T_map_marker, f"marker {entry.marker_id} pose")
        if not (isinstance(entry.size, (int, float)) and math.isfinite(entry.size) and entry.size > 0):
            raise GeometryError(f"marker {entry.marker_id}: size must be a positive length, got {entry.size!r}")
        entry = replace(entry, marker_id=int(entry.marker_id), T_map_marker=T,
                        position_std=np.asarray(entry.position_std, dtype=float).reshape(3),
                        rotation_std=np.asarray(entry.rotation_std, dtype=float).reshape(3))
        self._entries[entry.marker_id] = entry
        self._corners[entry.marker_id] = entry.corners_in_map()

    def remove(self, marker_id: int) -> None:
        self._entries.pop(marker_id, None)
        self._corners.pop(marker_id, None)

    def __contains__(self, marker_id: object) -> bool:
        return marker_id in self._entries

    def __len__(self) -> int:
        return len(self._entries)

    def __iter__(self) -> Iterator[MarkerEntry]:
        return iter(self._entries[k] for k in sorted(self._entries))

    def __getitem__(self, marker_id: int) -> MarkerEntry:
        return self._entries[marker_id]

    def get(self, marker_id: int) -> Optional[MarkerEntry]:
        return self._entries.get(marker_id)

    @property
    def ids(self) -> List[int]:
        return sorted(self._entries)

    @property
    def surveyed_only_ids(self) -> List[int]:
        """The markers whose pose is the survey's alone (:attr:`MarkerEntry.surveyed_only`)."""
        return [e.marker_id for e in self if e.surveyed_only]

    def corners(self, marker_id: int) -> np.ndarray:
        """(4, 3) corners of a mapped marker in the map frame (cached; do not modify)."""
        return self._corners[marker_id]

    def T_map_marker(self, marker_id: int) -> np.ndarray:
        return self._entries[marker_id].T_map_marker

    # --- YAML -------------------------------------------------------------------------------

    def to_dict(self) -> Dict[str, Any]:
        markers = []
        for e in self:
            markers.append({
                "id": e.marker_id,
                "size": float(e.size),
                "translation": [float(v) for v in e.T_map_marker[:3, 3]],
                "rotation": [float(v) for v in geo.quaternion_from_matrix(e.T_map_marker)],
                "position_std": [float(v) for v in e.position_std],
                "rotation_std": [float(v) for v in e.rotation_std],
                "observations": int(e.observations),
            })
            if e.rms_px is not None:
                markers[-1]["rms_px"] = float(e.rms_px)
            if e.ambiguous:
                markers[-1]["ambiguous"] = True
            if e.surveyed_only:
                markers[-1]["surveyed_only"] = True
        out: Dict[str, Any] = {
            "format_version": MAP_FORMAT_VERSION,
            "frame_id": self.frame_id,
            "reference_marker": self.reference_marker,
            "frame_definition": self.frame_definition,
            "frame_convention": self.frame_convention,
            "method": self.method,
            "created": self.created or _now_iso(),
            "markers": markers,
        }
        if self.quality:
            out["quality"] = _plain(self.quality)
        if self.ring_extrinsics:
            cams: Dict[str, Any] = {}
            for name, T in sorted(self.ring_extrinsics.items()):
                cams[name] = {"translation": [float(v) for v in T[:3, 3]],
                              "rotation": [float(v) for v in geo.quaternion_from_matrix(T)]}
                if name in self.ring_moved:
                    cams[name]["moved"] = [float(v) for v in self.ring_moved[name]]
            out["ring_calibration"] = {"base_frame": self.ring_base_frame, "cameras": cams}
            if self.ring_prior_sigma:
                out["ring_calibration"]["prior_sigma"] = {k: float(v) for k, v in self.ring_prior_sigma.items()}
            if self.ring_extrinsics_covariance is not None:
                out["ring_calibration"]["covariance"] = {
                    "cameras": list(self.ring_covariance_cameras),
                    "matrix": [[float(f"{v:.9g}") for v in row] for row in self.ring_extrinsics_covariance]}
        if self.anchors is not None:
            out["anchors"] = _plain(self.anchors)
        return out

    def save(self, path: str, limits: Optional["MapSanityLimits"] = None, backups: int = 1) -> None:
        """Write the map as YAML, atomically; the previous file is kept as ``<path>.bak`` (and the
        ``backups - 1`` before it as ``.bak.2`` ...: :func:`fileio.atomic_write_text`).

        The map must pass :func:`check_map` first (``limits``: default :class:`MapSanityLimits`);
        when it does not, nothing is written and :class:`errors.MapSanityError` says why.
        """
        problems = check_map(self, limits)
        if problems:
            raise MapSanityError(problems, path=str(path))
        text = "# aruco_ring_localization marker map (docs/formats.md)\n" + \
            yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None)
        atomic_write_text(path, text, backups=backups)
        logger.info("saved %d markers to %s", len(self), path)

    @classmethod
    def load(cls, path: str) -> "MarkerMap":
        """Load a YAML map; any problem raises ConfigError naming the file and the key.

        Files larger than :data:`MAX_MAP_FILE_BYTES` are refused unread; markers farther than
        :data:`MAX_COORDINATE` from the origin are refused naming their key.
        """
        return cls.from_dict(load_yaml_file(path, max_bytes=MAX_MAP_FILE_BYTES), source=str(path))

    @classmethod
    def from_dict(cls, data: Any, source: str = "<map>") -> "MarkerMap":
        if not isinstance(data, Mapping):
            raise ConfigError(f"expected a mapping at the top level, got {type(data).__name__}", path=source)
        version = data.get("format_version")
        if version is None:
            raise ConfigError("missing (is this a marker map file? fiducial_slam map.txt files are "
                              "read with 'aruco_ring import-map')", path=source, key="format_version")
        if version != MAP_FORMAT_VERSION:
            raise ConfigError(f"unsupported format_version {version!r}: this version reads {MAP_FORMAT_VERSION}",
                              path=source, key="format_version")
        frame_id = data.get("frame_id", "map")
        if not isinstance(frame_id, str) or not frame_id:
            raise ConfigError("expected a non-empty frame name", path=source, key="frame_id")
        ref = data.get("reference_marker")
        if ref is not None and (isinstance(ref, bool) or not isinstance(ref, int)):
            raise ConfigError(f"expected a marker id or null, got {ref!r}", path=source, key="reference_marker")
        markers = data.get("markers")
        if not isinstance(markers, list):
            raise ConfigError("expected a list of markers", path=source, key="markers")
        convention = data.get("frame_convention", "") or ""
        if not isinstance(convention, str) or (convention and convention not in FRAME_CONVENTIONS):
            raise ConfigError(f"expected one of {', '.join(FRAME_CONVENTIONS)}, got {convention!r}", path=source,
                              key="frame_convention")
        out = cls(frame_id=frame_id, reference_marker=ref,
                  frame_definition=str(data.get("frame_definition", "")),
                  method=str(data.get("method", "")), created=str(data.get("created", "")),
                  frame_convention=str(convention))
        quality = data.get("quality")
        if quality is not None and not isinstance(quality, Mapping):
            raise ConfigError("expected a mapping", path=source, key="quality")
        out.quality = dict(quality or {})
        noise = out.quality.get("pixel_noise")
        if noise is not None and not _is_pixel_noise(noise):
            raise ConfigError(f"expected a positive number of pixels (the corner noise the map was adjusted with), "
                              f"got {noise!r}", path=source, key="quality.pixel_noise")
        if not _add_all_vectorised(out, markers):
            # Something is wrong (or unusual) in the list: one marker at a time, naming the key.
            for i, m in enumerate(markers):
                entry = _entry_from_dict(m, source, f"markers[{i}]")
                if entry.marker_id in out:
                    raise ConfigError(f"duplicate marker id {entry.marker_id}", path=source, key=f"markers[{i}].id")
                out.add(entry)
        if ref is not None and ref not in out:
            raise ConfigError(f"reference marker {ref} is not among the markers", path=source, key="reference_marker")
        if data.get("anchors") is not None:
            out.anchors = _read_anchor_report(data["anchors"], source)
        if data.get("ring_calibration") is not None:
            out.ring_base_frame, out.ring_extrinsics = _read_ring_calibration(data["ring_calibration"], source)
            out.ring_prior_sigma, out.ring_moved = _read_ring_refinement(data["ring_calibration"], source)
            if data["ring_calibration"].get("covariance") is not None:
                out.ring_covariance_cameras, out.ring_extrinsics_covariance = _read_ring_covariance(
                    data["ring_calibration"]["covariance"], out.ring_extrinsics, source)
        return out

    # --- fiducial_slam ------------------------------------------------------------------------

    def to_fiducial_slam_text(self) -> str:
        """fiducial_slam ``map.txt``: ``id x y z rx ry rz variance nObs`` (angles in degrees).

        ``variance`` is the mean of the position variances (m^2), the closest quantity to
        fiducial_slam's. Marker sizes are not part of that format.
        """
        lines = []
        for e in self:
            r, p, y = (math.degrees(a) for a in geo.rpy_from_matrix(e.T_map_marker))
            t = e.T_map_marker[:3, 3]
            var = float(np.mean(np.square(e.position_std)))
            lines.append(f"{e.marker_id} {t[0]:.6f} {t[1]:.6f} {t[2]:.6f} {r:.6f} {p:.6f} {y:.6f} "
                         f"{var:.9f} {int(e.observations)}")
        return "\n".join(lines) + "\n"

    def export_fiducial_slam(self, path: str) -> None:
        atomic_write_text(path, self.to_fiducial_slam_text())

    @classmethod
    def from_fiducial_slam_text(cls, text: str, marker_size: float, source: str = "<map.txt>",
                                frame_id: str = "map") -> "MarkerMap":
        """Read fiducial_slam's map.txt. Sizes are not stored there, so ``marker_size`` applies to all."""
        out = cls(frame_id=frame_id, method="imported from fiducial_slam",
                  frame_definition="as in the imported fiducial_slam map")
        for lineno, line in enumerate(text.splitlines(), start=1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.split()
            key = f"line {lineno}"
            if len(fields) < 9:
                raise ConfigError(f"expected 'id x y z rx ry rz variance nObs [links]', got {len(fields)} fields",
                                  path=source, key=key)
            try:
                mid = int(fields[0])
                x, y, z, rx, ry, rz, var = (float(v) for v in fields[1:8])
                nobs = int(float(fields[8]))
            except (ValueError, OverflowError):  # OverflowError: nObs "inf"
                raise ConfigError("a field is not a number", path=source, key=key) from None
            values = np.array([x, y, z, rx, ry, rz, var])
            if not np.all(np.isfinite(values)) or var < 0:
                raise ConfigError("non-finite value or negative variance", path=source, key=key)
            if mid in out:
                raise ConfigError(f"duplicate marker id {mid}", path=source, key=key)
            T = np.eye(4)
            T[:3, :3] = geo.matrix_from_rpy(math.radians(rx), math.radians(ry), math.radians(rz))
            T[:3, 3] = (x, y, z)
            std = math.sqrt(var)
            out.add(MarkerEntry(mid, T, marker_size, np.full(3, std), np.zeros(3), nobs))
        if not len(out):
            raise ConfigError("no markers found", path=source)
        return out

    @classmethod
    def import_fiducial_slam(cls, path: str, marker_size: float, frame_id: str = "map") -> "MarkerMap":
        try:
            with open(path, "r", encoding="utf-8") as handle:
                text = handle.read()
        except OSError as exc:
            raise ConfigError(f"cannot read file ({exc})", path=str(path)) from None
        return cls.from_fiducial_slam_text(text, marker_size, source=str(path), frame_id=frame_id)


def _entry_from_dict(m: Any, source: str, key: str) -> MarkerEntry:
    if not isinstance(m, Mapping):
        raise ConfigError("expected a mapping", path=source, key=key)
    mid = m.get("id")
    if isinstance(mid, bool) or not isinstance(mid, int) or mid < 0:
        raise ConfigError(f"expected a non-negative integer id, got {mid!r}", path=source, key=f"{key}.id")
    size = m.get("size")
    if isinstance(size, bool) or not isinstance(size, (int, float)) or not math.isfinite(size) or size <= 0:
        raise ConfigError(f"expected a positive side length in metres, got {size!r}", path=source, key=f"{key}.size")
    from .ring import read_transform  # local import: rig imports camera, not marker_map

    T = read_transform({"translation": m.get("translation"), "rotation": m.get("rotation")}, source, key)
    if np.abs(T[:3, 3]).max() > MAX_COORDINATE:
        raise ConfigError(f"{T[:3, 3].tolist()} lies more than {MAX_COORDINATE:g} m from the map origin",
                          path=source, key=f"{key}.translation")
    pos_std = _read_std(m, "position_std", source, key)
    rot_std = _read_std(m, "rotation_std", source, key)
    nobs = m.get("observations", 0)
    if isinstance(nobs, bool) or not isinstance(nobs, int) or nobs < 0:
        raise ConfigError(f"expected a non-negative integer, got {nobs!r}", path=source, key=f"{key}.observations")
    ambiguous = m.get("ambiguous", False)
    if not isinstance(ambiguous, bool):
        raise ConfigError(f"expected true or false, got {ambiguous!r}", path=source, key=f"{key}.ambiguous")
    rms = m.get("rms_px")
    if rms is not None and (isinstance(rms, bool) or not isinstance(rms, (int, float)) or not rms >= 0):
        raise ConfigError(f"expected a non-negative number of pixels, got {rms!r}", path=source, key=f"{key}.rms_px")
    surveyed_only = m.get("surveyed_only", False)
    if not isinstance(surveyed_only, bool):
        raise ConfigError(f"expected true or false, got {surveyed_only!r}", path=source, key=f"{key}.surveyed_only")
    return MarkerEntry(mid, T, float(size), pos_std, rot_std, nobs, ambiguous, None if rms is None else float(rms),
                       surveyed_only)


def _add_all_vectorised(out: MarkerMap, markers: List[Any]) -> bool:
    """Add every marker of a map file's list to ``out`` at once, when the whole list is valid.

    The checks of :func:`_entry_from_dict` and :meth:`MarkerMap.add`, on arrays (a 5,000-marker map
    in a few ms instead of 0.3 s); it accepts a subset of what they accept. Returns False (and
    adds nothing) at the first doubt: the caller then goes marker by marker and names the key.
    """
    n = len(markers)
    if n == 0 or not all(isinstance(m, dict) for m in markers):
        return False
    ids = [m.get("id") for m in markers]
    sizes = [m.get("size") for m in markers]
    nobs = [m.get("observations", 0) for m in markers]
    ambiguous = [m.get("ambiguous", False) for m in markers]
    surveyed_only = [m.get("surveyed_only", False) for m in markers]
    rms = [m.get("rms_px") for m in markers]
    if not (all(type(i) is int and i >= 0 for i in ids) and len(set(ids)) == n
            and all(type(v) is int and v >= 0 for v in nobs)
            and all(type(v) in (int, float) for v in sizes)
            and all(type(v) is bool for v in ambiguous) and all(type(v) is bool for v in surveyed_only)
            and all(v is None or (type(v) in (int, float) and v >= 0) for v in rms)):
        return False
    fields = {}
    for name, width, dflt in (("translation", 3, None), ("rotation", 4, None), ("position_std", 3, _ZERO3),
                              ("rotation_std", 3, _ZERO3)):
        values = [m.get(name, dflt) for m in markers]
        if not all(type(v) is list and len(v) == width for v in values):
            return False
        try:
            arr = np.array(values, dtype=np.float64)
        except (TypeError, ValueError):
            return False
        if arr.shape != (n, width) or not np.isfinite(arr).all():
            return False
        fields[name] = arr
    size = np.array(sizes, dtype=np.float64)
    t, q = fields["translation"], fields["rotation"]
    norm = np.linalg.norm(q, axis=1)
    if not ((size > 0).all() and np.isfinite(size).all() and (norm > 0.9).all() and (norm < 1.1).all()
            and (np.abs(t) <= MAX_COORDINATE).all() and (fields["position_std"] >= 0).all()
            and (fields["rotation_std"] >= 0).all()):
        return False
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = Rotation.from_quat(q).as_matrix()
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    local = marker_corners(1.0)[None] * size[:, None, None]           # (n, 4, 3) in each marker's frame
    corners = np.einsum("nij,nkj->nki", T[:, :3, :3], local) + t[:, None, :]
    for k in range(n):
        mid = ids[k]
        out._entries[mid] = MarkerEntry(mid, T[k], float(size[k]), fields["position_std"][k],
                                        fields["rotation_std"][k], nobs[k], ambiguous[k],
                                        None if rms[k] is None else float(rms[k]), surveyed_only[k])
        out._corners[mid] = corners[k]
    return True


_ZERO3 = [0.0, 0.0, 0.0]


def _read_ring_calibration(node: Any, source: str):
    key = "ring_calibration"
    if not isinstance(node, Mapping) or not isinstance(node.get("cameras"), Mapping) or not node["cameras"]:
        raise ConfigError("expected {base_frame: NAME, cameras: {NAME: {translation, rotation}}}", path=source, key=key)
    base = node.get("base_frame", "base_link")
    if not isinstance(base, str) or not base:
        raise ConfigError("expected a non-empty frame name", path=source, key=f"{key}.base_frame")
    from .ring import read_transform

    cams = {str(name): read_transform(T, source, f"{key}.cameras.{name}") for name, T in node["cameras"].items()}
    return base, cams


def _read_ring_covariance(node: Any, extrinsics: Mapping[str, np.ndarray], source: str):
    key = "ring_calibration.covariance"
    if not isinstance(node, Mapping) or not isinstance(node.get("cameras"), list):
        raise ConfigError("expected {cameras: [NAME, ...], matrix: [[...], ...]}", path=source, key=key)
    names = [str(n) for n in node["cameras"]]
    unknown = sorted(set(names) - set(extrinsics))
    if unknown or len(set(names)) != len(names):
        raise ConfigError(f"expected distinct cameras of ring_calibration.cameras, got {names}", path=source,
                          key=f"{key}.cameras")
    try:
        C = np.asarray(node.get("matrix"), dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError("expected a matrix of numbers", path=source, key=f"{key}.matrix") from None
    n = 6 * len(names)
    if C.shape != (n, n) or not np.all(np.isfinite(C)):
        raise ConfigError(f"expected a finite {n}x{n} matrix (6 per camera), got shape {C.shape}", path=source,
                          key=f"{key}.matrix")
    C = 0.5 * (C + C.T)
    if n and np.linalg.eigvalsh(C)[0] < -1e-6 * float(np.abs(C).max()):
        raise ConfigError("not a covariance (negative eigenvalue)", path=source, key=f"{key}.matrix")
    return names, C


def _read_std(m: Mapping[str, Any], name: str, source: str, key: str) -> np.ndarray:
    value = m.get(name, [0.0, 0.0, 0.0])
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError("expected three numbers", path=source, key=f"{key}.{name}") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ConfigError(f"expected three non-negative numbers, got {value!r}", path=source, key=f"{key}.{name}")
    return arr


def _read_ring_refinement(node: Mapping[str, Any], source: str):
    """(prior_sigma, moved) of a ``ring_calibration`` block (both optional)."""
    key = "ring_calibration"
    sigma: Dict[str, float] = {}
    ps = node.get("prior_sigma")
    if ps is not None:
        if not isinstance(ps, Mapping):
            raise ConfigError("expected {translation: m, rotation: rad}", path=source, key=f"{key}.prior_sigma")
        for k in ("translation", "rotation"):
            v = ps.get(k)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ConfigError(f"expected a positive number, got {v!r}", path=source, key=f"{key}.prior_sigma.{k}")
            sigma[k] = float(v)
    moved: Dict[str, Tuple[float, float]] = {}
    for name, cam in node["cameras"].items():
        v = cam.get("moved") if isinstance(cam, Mapping) else None
        if v is None:
            continue
        try:
            arr = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            arr = np.zeros(0)
        if arr.shape != (2,) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
            raise ConfigError(f"expected [translation m, rotation rad], got {v!r}", path=source,
                              key=f"{key}.cameras.{name}.moved")
        moved[str(name)] = (float(arr[0]), float(arr[1]))
    return sigma, moved


def _read_anchor_report(node: Any, source: str) -> Dict[str, Any]:
    """The map's ``anchors`` section, checked for the keys the sanity checks and the evaluation read."""
    if not isinstance(node, Mapping):
        raise ConfigError("expected a mapping (source, kind, points)", path=source, key="anchors")
    points = node.get("points")
    if not isinstance(points, list):
        raise ConfigError("expected a list of surveyed markers", path=source, key="anchors.points")
    for i, p in enumerate(points):
        key = f"anchors.points[{i}]"
        if not isinstance(p, Mapping):
            raise ConfigError("expected a mapping (marker, surveyed, std, residual)", path=source, key=key)
        mid = p.get("marker")
        if isinstance(mid, bool) or not isinstance(mid, int):
            raise ConfigError(f"expected a marker id, got {mid!r}", path=source, key=f"{key}.marker")
        for name in ("surveyed", "std", "residual"):
            if name == "residual" and name not in p:
                continue
            v = p.get(name)
            if not (isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                                 and math.isfinite(x) for x in v)):
                raise ConfigError(f"expected 3 finite numbers, got {v!r}", path=source, key=f"{key}.{name}")
        sig = p.get("residual_sigmas")
        if sig is not None and (isinstance(sig, bool) or not isinstance(sig, (int, float))):
            raise ConfigError(f"expected a number, got {sig!r}", path=source, key=f"{key}.residual_sigmas")
    return dict(node)


def _plain(value: Any) -> Any:
    """numpy scalars / tuples -> plain YAML types (recursively)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _ids_text(ids: List[int], n: int = 12) -> str:
    return ", ".join(str(i) for i in ids[:n]) + (f" and {len(ids) - n} more" if len(ids) > n else "")


def _is_pixel_noise(value: Any) -> bool:
    """Whether ``value`` is a usable corner noise: a finite number of pixels > 0."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def rms_limit_px(limits: MapSanityLimits, quality: Mapping) -> float:
    """The reprojection check's limit, px, for a map whose ``quality`` records the corner noise it was
    adjusted with (``pixel_noise``, px): ``max_rms_px``, or ``max_rms_sigmas`` times that noise where
    larger (a map without the record: ``max_rms_px``)."""
    noise = quality.get("pixel_noise") if isinstance(quality, Mapping) else None
    if _is_pixel_noise(noise):
        return max(float(limits.max_rms_px), float(limits.max_rms_sigmas) * float(noise))
    return float(limits.max_rms_px)


def check_map(m: "MarkerMap", limits: Optional[MapSanityLimits] = None, ring: Any = None) -> List[str]:
    """The sanity checks every map passes before it is written; the problems found (empty: OK).

    Each problem names the check, the markers (or cameras) involved and what to do:

    * ``finite``: every pose and uncertainty is a finite number;
    * ``extent``: every marker lies within ``max_extent`` of the origin (a hall-sized box);
    * ``reprojection``: the map's recorded reprojection RMS (``quality.reprojection_rms_px``) and
      every marker's (``rms_px``) are within ``max_rms_px`` (or ``max_rms_sigmas`` of the recorded
      corner noise, ``quality.pixel_noise``, where larger: :func:`rms_limit_px`);
    * ``anchors``: every surveyed marker is mapped within ``max_anchor_sigmas`` of its survey std
      from its surveyed position (:func:`anchors.check_anchor_report`);
    * ``measurements``: every surveyed distance and plane (``quality.survey_measurements``) is met
      within ``max_anchor_sigmas`` of its std (:func:`anchors.check_measurement_report`);
    * ``extrinsics``: refined ring extrinsics moved at most ``max_extrinsics_sigmas`` prior standard
      deviations from the calibration (recorded ``moved``; and against ``ring``'s calibration,
      a :class:`~aruco_ring_localization.ring.CameraRing`, when given: what ``check-config`` does).
    """
    lim = limits or MapSanityLimits()
    problems: List[str] = []
    bad = [e.marker_id for e in m if not (np.all(np.isfinite(e.T_map_marker)) and np.all(np.isfinite(e.position_std))
                                          and np.all(np.isfinite(e.rotation_std)))]
    if bad:
        problems.append(f"finite: markers {_ids_text(bad)} have a non-finite pose or covariance (the adjustment "
                        f"could not determine them): record more views of them or list them in ignore_fiducials")
    far = [e for e in m if e.marker_id not in bad and float(np.linalg.norm(e.T_map_marker[:3, 3])) > lim.max_extent]
    if far:
        e = max(far, key=lambda e: float(np.linalg.norm(e.T_map_marker[:3, 3])))
        t = e.T_map_marker[:3, 3]
        problems.append(f"extent: markers {_ids_text([x.marker_id for x in far])} lie more than {lim.max_extent:g} m "
                        f"from the map origin (marker {e.marker_id} at ({t[0]:.3g}, {t[1]:.3g}, {t[2]:.3g}) m): the "
                        f"estimate diverged; check the ring file (extrinsics, base frame), the marker sizes "
                        f"(fiducial_len_override) and, for a handheld rig, planar: false")
    quality = m.quality if isinstance(m.quality, Mapping) else {}
    rms = quality.get("reprojection_rms_px")
    max_rms = rms_limit_px(lim, quality)
    if isinstance(rms, (int, float)) and not rms <= max_rms:
        problems.append(f"reprojection: the map reprojects its observations with {rms:.2f} px RMS (limit "
                        f"{max_rms:g} px): the ring calibration (intrinsics, extrinsics) or the marker sizes "
                        f"do not fit the detections")
    worst = sorted((e for e in m if e.rms_px is not None and not e.rms_px <= max_rms),
                   key=lambda e: -float(e.rms_px))
    if worst:
        problems.append(f"reprojection: markers {_ids_text([e.marker_id for e in worst])} reproject worse than "
                        f"{max_rms:g} px RMS (marker {worst[0].marker_id}: {worst[0].rms_px:.2f} px): a wrong "
                        f"size, a marker that moved or an id printed twice; fix its size or ignore it")
    sigma_t = m.ring_prior_sigma.get("translation")
    sigma_r = m.ring_prior_sigma.get("rotation")
    moved = dict(m.ring_moved)
    if ring is not None:
        for name, T in m.ring_extrinsics.items():
            if name in ring.names:
                dp, dr = geo.pose_distance(ring[name].T_base_cam, T)
                moved[name] = (dp, dr)
    if sigma_t and sigma_r:
        over = [n for n, (dp, dr) in sorted(moved.items())
                if dp > lim.max_extrinsics_sigmas * sigma_t or dr > lim.max_extrinsics_sigmas * sigma_r]
        if over:
            desc = ", ".join(f"{n} {1000 * moved[n][0]:.0f} mm / {np.degrees(moved[n][1]):.1f} deg" for n in over)
            problems.append(f"extrinsics: the refinement moved cameras {desc} from the calibration, more than "
                            f"{lim.max_extrinsics_sigmas:g} prior sigmas ({1000 * sigma_t:.0f} mm, "
                            f"{np.degrees(sigma_r):.2f} deg): check the ring file (base frame, extrinsics) or map "
                            f"with refine_extrinsics: false")
    if m.anchors is not None:
        problems += check_anchor_report(m.anchors, lim.max_anchor_sigmas)
    if isinstance(m.quality, Mapping):
        problems += check_measurement_report(m.quality.get("survey_measurements"), lim.max_anchor_sigmas)
    return problems


def _now_iso() -> str:
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def map_frame_from_reference(T_x_marker: np.ndarray, floor_z: float = 0.0) -> np.ndarray:
    """Pose ``T_x_map`` of the map frame fixed to a reference marker, given in a frame x with z up.

    The map frame (DESIGN §2): origin on the floor (z = ``floor_z`` in x) below the reference
    marker's centre, z up (x's z), x axis = the marker's x axis made horizontal, y = z cross x.
    Works for markers on walls (x horizontal) and, as long as the marker's x is not vertical,
    for tilted ones. Raises GeometryError when the marker's x axis is (nearly) vertical.
    """
    T = geo.validate_transform(T_x_marker, "reference marker pose")
    x_axis = T[:3, 0].copy()
    x_axis[2] = 0.0
    n = float(np.linalg.norm(x_axis))
    if n < 1e-3:
        raise GeometryError("reference marker's x axis is vertical: the map's x axis is undefined")
    x_axis /= n
    z_axis = np.array([0.0, 0.0, 1.0])
    y_axis = np.cross(z_axis, x_axis)
    out = np.eye(4)
    out[:3, :3] = np.stack([x_axis, y_axis, z_axis], axis=1)
    out[:3, 3] = (T[0, 3], T[1, 3], floor_z)
    return out
