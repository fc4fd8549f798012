"""Anchors: surveyed marker positions (or one full pose) that define the map frame.

Without anchors the map frame is fixed by one marker (the reference marker's heading,
:func:`marker_map.map_frame_from_reference`): a 0.2 m marker's heading is known to a few tenths of
a degree, which turns the whole map (0.3 deg is 9 cm at the far end of an 18 m plate). Users work
in the plate's own frame and can measure a few points of it (tape, laser distance meter, total
station). An :class:`AnchorSet` is those measurements: 2 or more markers with known centre
positions, each with its standard deviation, or one marker with a full known pose.

:func:`fit_frame` is the weighted least-squares fit of the map frame to them: position and heading
always; the plane too when 3 or more anchors span it (else the robot's z is up, as in the
reference-marker frame). The bundle adjustment then takes the anchors as priors
(:class:`bundle_adjustment.MarkerPriors`), so the surveyed points and the images are fitted
together, and the map file records each anchor's residual (docs/formats.md, "Anchors file").

File format (YAML; docs/formats.md)::

    frame_id: plate                  # optional: the name of the surveyed frame (informative)
    anchors:
      - marker: 3                    # marker id
        position: [0.0, 0.0, 0.45]   # m: the centre of the black square in the surveyed frame
        std: 0.001                   # m: 1 sigma, one value or [sx, sy, sz]
        instrument: total station    # optional, free text
      - marker: 7
        position: [6.0, 0.0, 0.45]
        std: [0.001, 0.001, 0.002]
      # or one marker with a full pose:
      # - marker: 3
      #   position: [...]
      #   rotation: [qx, qy, qz, qw]  # the marker frame's orientation in the surveyed frame
      #   rotation_std_deg: 0.05
      #   std: 0.001
    distances:                       # optional: tape / laser distances between marker points
      - from: {marker: 24, corner: 0}   # corner 0-3 (the package's order, docs/formats.md) or centre
        to: {marker: 60, corner: centre}
        distance: 6.017              # m
        std: 0.0002                  # m, 1 sigma
    planes:                          # optional: markers whose points lie on a plane of the surveyed frame
      - markers: [0, 36, 72]
        normal: [0.0, 0.0, 1.0]      # unit vector (surveyed frame)
        distance: 0.0                # m: normal . point = distance
        std: 0.01                    # m, 1 sigma of each point's distance to the plane
        points: corners              # corners (the 4 of each marker, default), centres, or one corner 0-3

Distances and planes (:class:`Measurements`) constrain the map's geometry (its scale along a
measured line, its flatness) without defining a frame: a file may hold only them, and the map
frame is then the reference marker's. A plane is given in the surveyed frame, so it needs anchors.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from . import geometry as geo
from .camera import load_yaml_file
from .errors import ConfigError, GeometryError

logger = logging.getLogger(__name__)

#: Largest anchors file read, bytes (a survey has a handful of points).
MAX_ANCHORS_FILE_BYTES = 1024 * 1024
#: Largest |coordinate| of an anchor, m (as the map's limit).
MAX_COORDINATE = 1.0e5
#: The plane is taken from the anchors when their RMS distance from their best-fit line is at least
#: this many times their (largest) position std: the tilt is then known to ~1/this rad or better.
PLANE_MIN_SPAN_SIGMAS = 100.0
#: Frame kinds (``AnchorFit.kind``).
KINDS = {
    "pose": "one marker's surveyed pose",
    "points": "surveyed marker positions (position, heading and plane)",
    "points_level": "surveyed marker positions (position and heading; the plane from the robot's z)",
}


@dataclass(frozen=True)
class Anchor:
    """One surveyed marker.

    Attributes:
        marker_id: the marker.
        position: (3,) the marker's centre in the surveyed frame, m.
        position_std: (3,) its 1-sigma per axis of the surveyed frame, m.
        rotation: (3, 3) the marker's orientation in the surveyed frame, or None (position only).
        rotation_std: 1-sigma of that orientation, rad (None without a rotation).
        instrument: free text (tape, laser distance meter, total station).
        key: where it is in its file (``anchors[2]``), for messages.
    """

    marker_id: int
    position: np.ndarray
    position_std: np.ndarray
    rotation: Optional[np.ndarray] = None
    rotation_std: Optional[float] = None
    instrument: str = ""
    key: str = ""


@dataclass
class AnchorSet:
    """The anchors of one survey (:func:`load_anchors`)."""

    anchors: List[Anchor]
    frame_id: str = ""
    source: str = "<anchors>"
    #: distances and planes of the same file (:class:`Measurements`), or None. With them the
    #: anchors may be empty: the file then constrains the geometry without defining the frame.
    measurements: Optional["Measurements"] = None

    def __post_init__(self) -> None:
        ids = [a.marker_id for a in self.anchors]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ConfigError(f"marker {dup[0]} is surveyed twice", path=self.source, key="anchors")
        if not self.anchors and self.measurements is not None and len(self.measurements):
            if self.measurements.planes:
                raise ConfigError("a plane is given in the surveyed frame: it needs anchors that define that frame "
                                  "(or leave the planes out; distances alone need none)", path=self.source,
                                  key=self.measurements.planes[0].key)
            return
        if not self.anchors:
            raise ConfigError("expected at least one anchor (or distances)", path=self.source, key="anchors")
        if len(self.anchors) < 2 and self.anchors[0].rotation is None:
            raise ConfigError("one anchor fixes the frame only with a full pose (rotation and rotation_std_deg); "
                              "survey 2 or more markers' positions, or add the rotation", path=self.source,
                              key="anchors")

    @property
    def ids(self) -> List[int]:
        return [a.marker_id for a in self.anchors]

    def subset(self, ids) -> "AnchorSet":
        """The anchors of the markers ``ids`` (raises ConfigError when they no longer define a frame)."""
        keep = [a for a in self.anchors if a.marker_id in set(ids)]
        if not keep:
            raise ConfigError(f"none of the surveyed markers {self.ids} is in the map", path=self.source,
                              key="anchors")
        return AnchorSet(keep, self.frame_id, self.source)

    def to_dict(self) -> Dict[str, Any]:
        """The file's content (what :func:`anchors_from_dict` reads back)."""
        out: Dict[str, Any] = {"frame_id": self.frame_id} if self.frame_id else {}
        if self.anchors:
            out["anchors"] = [_survey_dict(a, "position") for a in self.anchors]
        if self.measurements is not None:
            out.update(self.measurements.to_dict())
        return out


def load_anchors(path: str) -> AnchorSet:
    """Read an anchors file; any problem raises ConfigError naming the file and the key."""
    return anchors_from_dict(load_yaml_file(path, max_bytes=MAX_ANCHORS_FILE_BYTES), source=str(path))


def _vector(value: Any, n: int, source: str, key: str, what: str) -> np.ndarray:
    if isinstance(value, (bool, str)) or not isinstance(value, (list, tuple)) or len(value) != n:
        raise ConfigError(f"expected {what} ({n} numbers), got {value!r}", path=source, key=key)
    try:
        out = np.array([float(v) for v in value], dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"expected {what} ({n} numbers), got {value!r}", path=source, key=key) from None
    if any(isinstance(v, bool) for v in value) or not np.all(np.isfinite(out)):
        raise ConfigError(f"expected finite numbers, got {value!r}", path=source, key=key)
    return out


def _positive(value: Any, source: str, key: str, unit: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"expected a positive number ({unit}), got {value!r}", path=source, key=key)
    return float(value)


_KEYS = {"marker", "position", "std", "rotation", "rotation_std_deg", "instrument"}


def _anchor_from_dict(node: Any, source: str, key: str) -> Anchor:
    _check_keys(node, _KEYS, ("marker", "position", "std"), source, key, "marker, position and std")
    mid = node["marker"]
    if isinstance(mid, bool) or not isinstance(mid, int) or mid < 0:
        raise ConfigError(f"expected a marker id (integer >= 0), got {mid!r}", path=source, key=f"{key}.marker")
    pos = _vector(node["position"], 3, source, f"{key}.position", "a position [x, y, z] in m")
    if np.any(np.abs(pos) > MAX_COORDINATE):
        raise ConfigError(f"beyond {MAX_COORDINATE:g} m from the origin", path=source, key=f"{key}.position")
    std_node = node["std"]
    if isinstance(std_node, (list, tuple)):
        std = _vector(std_node, 3, source, f"{key}.std", "a std [sx, sy, sz] in m")
        if np.any(std <= 0):
            raise ConfigError(f"expected positive values (m), got {std_node!r}", path=source, key=f"{key}.std")
    else:
        std = np.full(3, _positive(std_node, source, f"{key}.std", "m"))
    rot, rot_std = None, None
    if ("rotation" in node) != ("rotation_std_deg" in node):
        missing = "rotation_std_deg" if "rotation" in node else "rotation"
        raise ConfigError("a full pose needs both rotation and rotation_std_deg", path=source, key=f"{key}.{missing}")
    if "rotation" in node:
        q = _vector(node["rotation"], 4, source, f"{key}.rotation", "a quaternion [x, y, z, w]")
        try:
            rot = geo.matrix_from_quaternion(q, name=f"{key}.rotation")
        except (GeometryError, ValueError) as exc:
            raise ConfigError(str(exc), path=source, key=f"{key}.rotation") from None
        rot_std = math.radians(_positive(node["rotation_std_deg"], source, f"{key}.rotation_std_deg", "deg"))
    instrument = node.get("instrument", "")
    if not isinstance(instrument, str):
        raise ConfigError(f"expected text, got {instrument!r}", path=source, key=f"{key}.instrument")
    return Anchor(int(mid), pos, std, rot, rot_std, instrument, key)


def anchors_from_dict(data: Any, source: str = "<anchors>") -> AnchorSet:
    """An :class:`AnchorSet` from a parsed anchors file (see the module doc)."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"expected a mapping with 'anchors' at the top level, got {type(data).__name__}",
                          path=source)
    unknown = sorted(set(map(str, data)) - {"frame_id", "anchors", "distances", "planes"})
    if unknown:
        raise ConfigError(f"unknown key {unknown[0]!r} (expected frame_id, anchors, distances, planes)", path=source,
                          key=unknown[0])
    frame_id = data.get("frame_id", "") or ""
    if not isinstance(frame_id, str):
        raise ConfigError(f"expected a frame name, got {frame_id!r}", path=source, key="frame_id")
    meas = measurements_from_dict(data, source)
    nodes = data.get("anchors")
    if nodes is None and len(meas):
        nodes = []
    if not isinstance(nodes, list):
        raise ConfigError("expected a list of anchors", path=source, key="anchors")
    return AnchorSet([_anchor_from_dict(n, source, f"anchors[{i}]") for i, n in enumerate(nodes)], frame_id, source,
                     meas if len(meas) else None)


# --- the fit ---------------------------------------------------------------------------------

@dataclass
class AnchorFit:
    """The map frame fitted to the anchors (:func:`fit_frame`).

    Attributes:
        T_map_W: (4, 4) the pose of the estimate's frame W in the surveyed (map) frame.
        kind: ``pose``, ``points`` (plane from the anchors) or ``points_level`` (plane from W's z).
        residuals: marker id -> (3,) fitted minus surveyed position, m (surveyed frame).
        rotation_residuals: marker id -> rotation angle between fitted and surveyed, rad (pose anchors).
    """

    T_map_W: np.ndarray
    kind: str
    residuals: Dict[int, np.ndarray] = field(default_factory=dict)
    rotation_residuals: Dict[int, float] = field(default_factory=dict)


def spans_plane(anchors: AnchorSet) -> bool:
    """Whether the position anchors are far enough from one line to fix the plane
    (:data:`PLANE_MIN_SPAN_SIGMAS`)."""
    P = np.array([a.position for a in anchors.anchors])
    if len(P) < 3:
        return False
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    off_line = float(s[1]) / math.sqrt(len(P))
    std = max(float(np.max(a.position_std)) for a in anchors.anchors)
    return off_line >= PLANE_MIN_SPAN_SIGMAS * std


def frame_kind(anchors: AnchorSet) -> str:
    """``pose`` (a rotation anchor fixes the orientation), ``points`` or ``points_level``."""
    if any(a.rotation is not None for a in anchors.anchors):
        return "pose"
    return "points" if spans_plane(anchors) else "points_level"


def _params_to_T(x: np.ndarray, level: bool) -> np.ndarray:
    if level:   # rotation about z only
        R = Rotation.from_rotvec([0.0, 0.0, x[0]]).as_matrix()
        return geo.make_transform(R, x[1:4])
    return geo.make_transform(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6])


def fit_frame(anchors: AnchorSet, T_W_markers: Mapping[int, np.ndarray]) -> AnchorFit:
    """``T_map_W`` that puts the estimated markers (``T_W_markers``, frame W with z up) where the
    survey has them: weighted least squares (each position residual divided by its std, each
    rotation residual by its std), rigid. With only 2 anchors, or anchors (nearly) on one line, the
    rotation is about W's z only (the plane is the robot's floor). Markers of ``anchors`` absent
    from ``T_W_markers`` are left out (``AnchorSet.subset`` raises when too few remain).

    Raises:
        ConfigError: the anchors present do not define a frame.
    """
    present = anchors.subset([m for m in anchors.ids if m in T_W_markers])
    kind = frame_kind(present)
    level = kind == "points_level"
    P = np.array([T_W_markers[a.marker_id][:3, 3] for a in present.anchors])
    Q = np.array([a.position for a in present.anchors])
    S = np.array([a.position_std for a in present.anchors])
    rots = [(T_W_markers[a.marker_id][:3, :3], a.rotation, a.rotation_std) for a in present.anchors
            if a.rotation is not None]
    # Start: the weighted Kabsch solution (Umeyama without scale), or one pose anchor's rotation.
    w = 1.0 / np.mean(S ** 2, axis=1)
    if kind == "pose":
        Rw, Ra, _ = rots[0]
        R0 = Ra @ Rw.T
    elif len(P) >= 2:
        pc, qc = np.average(P, axis=0, weights=w), np.average(Q, axis=0, weights=w)
        A, B = P - pc, Q - qc
        if level:
            A[:, 2] = B[:, 2] = 0.0
        U, _, Vt = np.linalg.svd((B * w[:, None]).T @ A)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        R0 = U @ D @ Vt
    else:
        R0 = np.eye(3)
    t0 = np.average(Q - P @ R0.T, axis=0, weights=w)
    if level:
        R0 = Rotation.from_rotvec([0.0, 0.0, math.atan2(R0[1, 0], R0[0, 0])]).as_matrix()
        x0 = np.r_[math.atan2(R0[1, 0], R0[0, 0]), t0]
    else:
        x0 = np.r_[Rotation.from_matrix(R0).as_rotvec(), t0]

    def residuals(x: np.ndarray) -> np.ndarray:
        T = _params_to_T(x, level)
        r = [((P @ T[:3, :3].T + T[:3, 3] - Q) / S).ravel()]
        for Rw, Ra, sd in rots:
            r.append(Rotation.from_matrix(T[:3, :3] @ Rw @ Ra.T).as_rotvec() / sd)
        return np.concatenate(r)

    sol = least_squares(residuals, x0, method="lm" if len(residuals(x0)) >= len(x0) else "trf", xtol=1e-14,
                        ftol=1e-14, gtol=1e-14)
    T = _params_to_T(sol.x, level)
    out = AnchorFit(T, kind)
    for a in present.anchors:
        Tm = T @ T_W_markers[a.marker_id]
        out.residuals[a.marker_id] = Tm[:3, 3] - a.position
        if a.rotation is not None:
            out.rotation_residuals[a.marker_id] = float(np.linalg.norm(
                Rotation.from_matrix(Tm[:3, :3] @ a.rotation.T).as_rotvec()))
    return out


def _survey_dict(a: Any, position_key: str) -> Dict[str, Any]:
    """One anchor's survey as YAML-ready values: its position under ``position_key``, std, rotation."""
    d: Dict[str, Any] = {"marker": a.marker_id, position_key: [float(v) for v in a.position],
                         "std": [float(v) for v in a.position_std]}
    if a.rotation is not None:
        d["rotation"] = [float(v) for v in Rotation.from_matrix(a.rotation).as_quat()]
        d["rotation_std_deg"] = float(np.degrees(a.rotation_std))
    if a.instrument:
        d["instrument"] = a.instrument
    return d


def anchor_report(anchors: AnchorSet, T_map_markers: Mapping[int, np.ndarray], kind: str) -> Dict[str, Any]:
    """The map file's ``anchors`` section: the survey and each anchor's residual (mapped minus surveyed,
    in the map frame, m; and in units of the survey's std)."""
    points = []
    for a in anchors.anchors:
        d = _survey_dict(a, "surveyed")
        T = T_map_markers.get(a.marker_id)
        if T is None:
            d["mapped"] = False
        else:
            r = np.asarray(T)[:3, 3] - a.position
            d["residual"] = [float(v) for v in r]
            d["residual_sigmas"] = float(np.linalg.norm(r / a.position_std))
            if a.rotation is not None:
                ang = float(np.linalg.norm(Rotation.from_matrix(np.asarray(T)[:3, :3] @ a.rotation.T).as_rotvec()))
                d["rotation_residual_deg"] = float(np.degrees(ang))
        points.append(d)
    return {"source": anchors.source, "frame_id": anchors.frame_id, "kind": kind, "points": points}


def check_anchor_report(report: Any, max_sigmas: float) -> List[str]:
    """Problems of a map's ``anchors`` section (empty: OK): an anchor farther from its surveyed
    position than ``max_sigmas`` of its std (a mistyped survey value, a wrong id, a marker that moved
    between the survey and the mapping) or, with a pose anchor, rotated by more than that many std."""
    if not isinstance(report, Mapping):
        return []
    problems = []
    for p in report.get("points", []) or []:
        if not isinstance(p, Mapping):
            continue
        sig = p.get("residual_sigmas")
        if isinstance(sig, (int, float)) and not sig <= max_sigmas:
            r = np.asarray(p.get("residual", [np.nan] * 3), dtype=float)
            problems.append(f"anchors: marker {p.get('marker')} is mapped {1000 * float(np.linalg.norm(r)):.1f} mm "
                            f"({sig:.1f} sigma, limit {max_sigmas:g}) from its surveyed position: check its line in "
                            f"the anchors file ({report.get('source')}: a mistyped value, a wrong id, a std too "
                            f"small) or whether it moved since the survey")
        rdeg, sdeg = p.get("rotation_residual_deg"), p.get("rotation_std_deg")
        if isinstance(rdeg, (int, float)) and isinstance(sdeg, (int, float)) and sdeg > 0 \
                and not rdeg <= max_sigmas * sdeg:
            problems.append(f"anchors: marker {p.get('marker')} is mapped turned {rdeg:.2f} deg from its surveyed "
                            f"orientation ({rdeg / sdeg:.1f} sigma, limit {max_sigmas:g}): check its rotation in "
                            f"{report.get('source')}")
    return problems


def frame_definition(anchors: AnchorSet, kind: str) -> str:
    """The map file's ``frame_definition`` of a surveyed frame."""
    ids = ", ".join(str(i) for i in anchors.ids)
    name = f" '{anchors.frame_id}'" if anchors.frame_id else ""
    if kind == "pose":
        how = f"marker {anchors.ids[0]}'s surveyed pose" if len(anchors.anchors) == 1 else \
            f"surveyed markers {ids} (with a surveyed pose)"
    elif kind == "points":
        how = f"the surveyed positions of markers {ids} (position, heading and plane)"
    else:
        how = f"the surveyed positions of markers {ids} (position and heading; z up = the robot's z)"
    return f"the surveyed frame{name} of {anchors.source}: fitted to {how}"


def noisy_anchors(T_true: Mapping[int, np.ndarray], ids, std: float, seed: int, frame_id: str = "",
                  source: str = "<generated>", instrument: str = "simulated survey") -> AnchorSet:
    """Anchors at the true centres of markers ``ids`` plus seeded Gaussian noise of ``std`` (m) per
    axis: a simulated survey (the demo's, from the scene's true marker poses)."""
    rng = np.random.default_rng(seed)
    out = []
    for i, m in enumerate(ids):
        p = np.asarray(T_true[m], dtype=float)[:3, 3] + rng.normal(0.0, std, 3)
        out.append(Anchor(int(m), p, np.full(3, float(std)), instrument=instrument, key=f"anchors[{i}]"))
    return AnchorSet(out, frame_id, source)


def spread_markers(T_markers: Mapping[int, np.ndarray], n: int) -> List[int]:
    """``n`` marker ids far apart (farthest-point order from the marker farthest from the centroid,
    ties by id): which markers a simulated survey measures (the widest triangle fixes the heading
    and the plane best)."""
    ids = sorted(T_markers)
    if n > len(ids):
        raise ConfigError(f"a survey of {n} markers needs that many markers, the scene has {len(ids)}")
    P = {m: np.asarray(T_markers[m], dtype=float)[:3, 3] for m in ids}
    c = np.mean([P[m] for m in ids], axis=0)
    chosen = [max(ids, key=lambda m: (float(np.linalg.norm(P[m] - c)), -m))]
    while len(chosen) < n:
        chosen.append(max((m for m in ids if m not in chosen),
                          key=lambda m: (min(float(np.linalg.norm(P[m] - P[k])) for k in chosen), -m)))
    return chosen


def anchors_yaml(anchors: AnchorSet, header: str = "") -> str:
    """The text of an anchors file (with ``header`` as comment lines on top)."""
    import yaml

    lines = "".join(f"# {h}\n" if h else "#\n" for h in header.splitlines()) if header else ""
    return lines + yaml.safe_dump(anchors.to_dict(), sort_keys=False, default_flow_style=None)


# --- survey measurements: distances and planes -----------------------------------------------

#: Names a measured point may have besides the corner numbers 0-3.
CENTRE_NAMES = ("centre", "center")
#: Largest measured distance, m.
MAX_DISTANCE = 1.0e4


@dataclass(frozen=True)
class MarkerPoint:
    """A point of a marker: one of its corners (0-3, the order of :func:`markers.marker_corners`:
    top-left, top-right, bottom-right, bottom-left seen facing the marker) or its centre (None)."""

    marker_id: int
    corner: Optional[int] = None

    def local(self, size: float) -> np.ndarray:
        """(3,) the point in the marker's frame for a marker of side ``size`` (m)."""
        from .markers import marker_corners

        return np.zeros(3) if self.corner is None else marker_corners(size)[self.corner].copy()

    def to_dict(self) -> Dict[str, Any]:
        return {"marker": self.marker_id, "corner": "centre" if self.corner is None else self.corner}

    def __str__(self) -> str:
        return f"marker {self.marker_id} " + ("centre" if self.corner is None else f"corner {self.corner}")


@dataclass(frozen=True)
class DistanceMeasurement:
    """A measured distance between two marker points (tape, laser distance meter), m."""

    a: MarkerPoint
    b: MarkerPoint
    distance: float
    std: float
    instrument: str = ""
    key: str = ""


@dataclass(frozen=True)
class PlaneMeasurement:
    """Markers whose points (their 4 corners, their centres or one corner each) lie on the plane
    ``normal . p = distance`` of the surveyed frame, each point within ``std`` (m)."""

    markers: Tuple[int, ...]
    normal: np.ndarray
    distance: float
    std: float
    points: str = "corners"
    instrument: str = ""
    key: str = ""

    def marker_points(self) -> List[MarkerPoint]:
        """Every constrained point, marker by marker."""
        corners: List[Optional[int]] = [0, 1, 2, 3] if self.points == "corners" else \
            [None] if self.points == "centres" else [int(self.points)]
        return [MarkerPoint(m, c) for m in self.markers for c in corners]


@dataclass
class Measurements:
    """The distances and planes of an anchors file."""

    distances: List[DistanceMeasurement] = field(default_factory=list)
    planes: List[PlaneMeasurement] = field(default_factory=list)
    source: str = "<anchors>"

    def __len__(self) -> int:
        return len(self.distances) + len(self.planes)

    @property
    def ids(self) -> List[int]:
        out = {p.marker_id for d in self.distances for p in (d.a, d.b)}
        out.update(m for pl in self.planes for m in pl.markers)
        return sorted(out)

    def to_dict(self) -> Dict[str, Any]:
        out: Dict[str, Any] = {}
        if self.distances:
            out["distances"] = [dict({"from": d.a.to_dict(), "to": d.b.to_dict(), "distance": float(d.distance),
                                      "std": float(d.std)}, **({"instrument": d.instrument} if d.instrument else {}))
                                for d in self.distances]
        if self.planes:
            out["planes"] = [dict({"markers": list(p.markers), "normal": [float(v) for v in p.normal],
                                   "distance": float(p.distance), "std": float(p.std),
                                   "points": int(p.points) if p.points.isdigit() else p.points},
                                  **({"instrument": p.instrument} if p.instrument else {})) for p in self.planes]
        return out


def _marker_id(value: Any, source: str, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ConfigError(f"expected a marker id (integer >= 0), got {value!r}", path=source, key=key)
    return int(value)


def _marker_point(node: Any, source: str, key: str) -> MarkerPoint:
    if not isinstance(node, Mapping):
        raise ConfigError(f"expected a mapping {{marker: ID, corner: 0-3 or centre}}, got {node!r}", path=source,
                          key=key)
    unknown = sorted(set(map(str, node)) - {"marker", "corner"})
    if unknown:
        raise ConfigError(f"unknown key {unknown[0]!r} (expected marker, corner)", path=source,
                          key=f"{key}.{unknown[0]}")
    if "marker" not in node:
        raise ConfigError("missing", path=source, key=f"{key}.marker")
    mid = _marker_id(node["marker"], source, f"{key}.marker")
    c = node.get("corner", "centre")
    if isinstance(c, str) and c.strip().lower() in CENTRE_NAMES:
        return MarkerPoint(mid, None)
    if isinstance(c, bool) or not isinstance(c, int) or not 0 <= c <= 3:
        raise ConfigError(f"expected a corner 0-3 (top-left, top-right, bottom-right, bottom-left facing the "
                          f"marker) or centre, got {c!r}", path=source, key=f"{key}.corner")
    return MarkerPoint(mid, int(c))


def _text(node: Mapping, source: str, key: str) -> str:
    v = node.get("instrument", "")
    if not isinstance(v, str):
        raise ConfigError(f"expected text, got {v!r}", path=source, key=f"{key}.instrument")
    return v


def _check_keys(node: Any, keys: set, required: Tuple[str, ...], source: str, key: str, what: str) -> None:
    if not isinstance(node, Mapping):
        raise ConfigError(f"expected a mapping with {what}, got {node!r}", path=source, key=key)
    unknown = sorted(set(map(str, node)) - keys)
    if unknown:
        raise ConfigError(f"unknown key {unknown[0]!r} (expected {', '.join(sorted(keys))})", path=source,
                          key=f"{key}.{unknown[0]}")
    for r in required:
        if r not in node:
            raise ConfigError("missing", path=source, key=f"{key}.{r}")


def _distance_from_dict(node: Any, source: str, key: str) -> DistanceMeasurement:
    _check_keys(node, {"from", "to", "distance", "std", "instrument"}, ("from", "to", "distance", "std"), source, key,
                "from, to, distance and std")
    a = _marker_point(node["from"], source, f"{key}.from")
    b = _marker_point(node["to"], source, f"{key}.to")
    if a.marker_id == b.marker_id:
        raise ConfigError(f"both ends on marker {a.marker_id}: a distance links two markers", path=source,
                          key=f"{key}.to")
    d = _positive(node["distance"], source, f"{key}.distance", "m")
    if d > MAX_DISTANCE:
        raise ConfigError(f"longer than {MAX_DISTANCE:g} m", path=source, key=f"{key}.distance")
    return DistanceMeasurement(a, b, d, _positive(node["std"], source, f"{key}.std", "m"), _text(node, source, key),
                               key)


def _plane_from_dict(node: Any, source: str, key: str) -> PlaneMeasurement:
    _check_keys(node, {"markers", "normal", "distance", "std", "points", "instrument"},
                ("markers", "normal", "distance", "std"), source, key, "markers, normal, distance and std")
    ids = node["markers"]
    if not isinstance(ids, list) or not ids:
        raise ConfigError(f"expected a list of marker ids, got {ids!r}", path=source, key=f"{key}.markers")
    mids = tuple(_marker_id(m, source, f"{key}.markers[{i}]") for i, m in enumerate(ids))
    if len(set(mids)) != len(mids):
        raise ConfigError("a marker is listed twice", path=source, key=f"{key}.markers")
    n = _vector(node["normal"], 3, source, f"{key}.normal", "a normal [nx, ny, nz]")
    if abs(float(np.linalg.norm(n)) - 1.0) > 1e-3:
        raise ConfigError(f"expected a unit vector, got length {float(np.linalg.norm(n)):.4g}", path=source,
                          key=f"{key}.normal")
    d = node["distance"]
    if isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d) or abs(d) > MAX_COORDINATE:
        raise ConfigError(f"expected a finite number (m), got {d!r}", path=source, key=f"{key}.distance")
    points = node.get("points", "corners")
    if isinstance(points, int) and not isinstance(points, bool) and 0 <= points <= 3:
        points = str(points)
    if points not in ("corners", "centres", "0", "1", "2", "3"):
        raise ConfigError(f"expected corners, centres or one corner 0-3, got {points!r}", path=source,
                          key=f"{key}.points")
    return PlaneMeasurement(mids, n / np.linalg.norm(n), float(d), _positive(node["std"], source, f"{key}.std", "m"),
                            points, _text(node, source, key), key)


def measurements_from_dict(data: Mapping, source: str = "<anchors>") -> Measurements:
    """The ``distances`` and ``planes`` of a parsed anchors file (empty when it has none)."""
    out = Measurements(source=source)
    for name, parse, dest in (("distances", _distance_from_dict, out.distances),
                              ("planes", _plane_from_dict, out.planes)):
        nodes = data.get(name)
        if nodes is None:
            continue
        if not isinstance(nodes, list):
            raise ConfigError(f"expected a list of {name}", path=source, key=name)
        dest.extend(parse(n, source, f"{name}[{i}]") for i, n in enumerate(nodes))
    return out


def measurement_report(meas: Measurements, T_map_markers: Mapping[int, np.ndarray], sizes: Any) -> Dict[str, Any]:
    """The map's record of the survey measurements: each one's value in the map and its residual
    (mapped minus measured) in mm and in units of its std. ``sizes(marker_id)`` gives marker sides
    (m); planes are evaluated in the map frame (the surveyed frame: they need anchors)."""
    def point(p: MarkerPoint) -> Optional[np.ndarray]:
        T = T_map_markers.get(p.marker_id)
        return None if T is None else np.asarray(T)[:3, :3] @ p.local(float(sizes(p.marker_id))) + np.asarray(T)[:3, 3]

    dists = []
    for d in meas.distances:
        e: Dict[str, Any] = {"key": d.key, "from": d.a.to_dict(), "to": d.b.to_dict(), "measured": float(d.distance),
                             "std": float(d.std)}
        pa, pb = point(d.a), point(d.b)
        if pa is None or pb is None:
            e["mapped"] = False
        else:
            got = float(np.linalg.norm(pa - pb))
            e.update(mapped_distance=got, residual_mm=1000.0 * (got - d.distance),
                     residual_sigmas=abs(got - d.distance) / d.std)
        dists.append(e)
    planes = []
    for pl in meas.planes:
        e = {"key": pl.key, "markers": list(pl.markers), "normal": [float(v) for v in pl.normal],
             "distance": float(pl.distance), "std": float(pl.std), "points": pl.points}
        res = [float(pl.normal @ q - pl.distance) for q in (point(p) for p in pl.marker_points()) if q is not None]
        missing = sorted({m for m in pl.markers if m not in T_map_markers})
        if missing:
            e["unmapped"] = missing
        if res:
            k = int(np.argmax(np.abs(res)))
            worst = [p for p in pl.marker_points() if p.marker_id in T_map_markers][k]
            e.update(rms_mm=1000.0 * float(np.sqrt(np.mean(np.square(res)))), residual_mm=1000.0 * res[k],
                     worst=worst.to_dict(), residual_sigmas=abs(res[k]) / pl.std)
        planes.append(e)
    return {"source": meas.source, "distances": dists, "planes": planes}


def check_measurement_report(report: Any, max_sigmas: float) -> List[str]:
    """Problems of a map's survey measurements (:func:`measurement_report`; empty: OK): a distance
    or a plane point more than ``max_sigmas`` of its std off (a mistyped value, a wrong id or
    corner, a std too small, a marker that moved since the survey)."""
    if not isinstance(report, Mapping):
        return []
    problems = []
    src = report.get("source")
    for e in report.get("distances", []) or []:
        sig = e.get("residual_sigmas") if isinstance(e, Mapping) else None
        if isinstance(sig, (int, float)) and not sig <= max_sigmas:
            problems.append(f"measurements: {e.get('key')} (marker {e['from'].get('marker')} corner "
                            f"{e['from'].get('corner')} to marker {e['to'].get('marker')} corner "
                            f"{e['to'].get('corner')}) is {e.get('mapped_distance', float('nan')):.4f} m in the map, "
                            f"measured {e.get('measured')} m: {e.get('residual_mm', float('nan')):+.1f} mm ({sig:.1f} "
                            f"sigma, limit {max_sigmas:g}): check it in {src} (a mistyped value, a wrong marker or "
                            f"corner, a std too small) or whether a marker moved")
    for e in report.get("planes", []) or []:
        sig = e.get("residual_sigmas") if isinstance(e, Mapping) else None
        if isinstance(sig, (int, float)) and not sig <= max_sigmas:
            w = e.get("worst") or {}
            problems.append(f"measurements: {e.get('key')}: marker {w.get('marker')} corner {w.get('corner')} is "
                            f"{e.get('residual_mm', float('nan')):+.1f} mm off the plane ({sig:.1f} sigma, limit "
                            f"{max_sigmas:g}): check the plane in {src} (its markers, normal, distance, std)")
    return problems



def measurement_lines(report: Any) -> List[str]:
    """One line per survey measurement of a map's record (:func:`measurement_report`), for people."""
    if not isinstance(report, Mapping):
        return []
    out = []
    for e in report.get("distances", []) or []:
        if not isinstance(e, Mapping):
            continue
        what = (f"distance {e.get('key')}: marker {e['from'].get('marker')} corner {e['from'].get('corner')} to "
                f"marker {e['to'].get('marker')} corner {e['to'].get('corner')}, measured {e.get('measured')} m")
        out.append(f"{what}: {e['residual_mm']:+.2f} mm ({e['residual_sigmas']:.1f} sigma)" if "residual_mm" in e
                   else f"{what}: not mapped")
    for e in report.get("planes", []) or []:
        if not isinstance(e, Mapping):
            continue
        what = f"plane {e.get('key')} ({len(e.get('markers', []))} markers)"
        out.append(f"{what}: RMS {e['rms_mm']:.2f} mm, worst {e['residual_mm']:+.2f} mm ({e['residual_sigmas']:.1f} "
                   f"sigma)" if "rms_mm" in e else f"{what}: not mapped")
    return out
