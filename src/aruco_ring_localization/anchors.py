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
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional

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

    def __post_init__(self) -> None:
        ids = [a.marker_id for a in self.anchors]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ConfigError(f"marker {dup[0]} is surveyed twice", path=self.source, key="anchors")
        if not self.anchors:
            raise ConfigError("expected at least one anchor", path=self.source, key="anchors")
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
        out = [_survey_dict(a, "position") for a in self.anchors]
        return {"frame_id": self.frame_id, "anchors": out} if self.frame_id else {"anchors": out}


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
    if not isinstance(node, Mapping):
        raise ConfigError(f"expected a mapping with marker, position and std, got {node!r}", path=source, key=key)
    unknown = sorted(set(map(str, node)) - _KEYS)
    if unknown:
        raise ConfigError(f"unknown key {unknown[0]!r} (expected {', '.join(sorted(_KEYS))})", path=source,
                          key=f"{key}.{unknown[0]}")
    for required in ("marker", "position", "std"):
        if required not in node:
            raise ConfigError("missing", path=source, key=f"{key}.{required}")
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
    unknown = sorted(set(map(str, data)) - {"frame_id", "anchors"})
    if unknown:
        raise ConfigError(f"unknown key {unknown[0]!r} (expected frame_id, anchors)", path=source, key=unknown[0])
    frame_id = data.get("frame_id", "") or ""
    if not isinstance(frame_id, str):
        raise ConfigError(f"expected a frame name, got {frame_id!r}", path=source, key="frame_id")
    nodes = data.get("anchors")
    if not isinstance(nodes, list):
        raise ConfigError("expected a list of anchors", path=source, key="anchors")
    return AnchorSet([_anchor_from_dict(n, source, f"anchors[{i}]") for i, n in enumerate(nodes)], frame_id, source)


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
