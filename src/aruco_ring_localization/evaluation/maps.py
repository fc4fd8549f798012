"""A marker map against the truth: per-marker errors, the strict convention and the best fit.

An estimated map lives in a frame fixed to its reference marker (docs/formats.md, "Marker map"), the
truth in the simulator's world frame. The fair comparison (the strict convention,
:func:`truth_in_map_frame`) expresses the truth in the *same frame definition*:
:func:`marker_map.map_frame_from_reference` applied to the truth's pose of the estimate's
reference marker. No free alignment is fitted, so an error in how the frame is fixed shows up in
the numbers. A best-fit SE(3) alignment (:func:`align_map_to_truth`: evo's Umeyama alignment of
all marker corners) is offered too, reported separately: it shows the map's shape (internal
consistency), not its error in use; :func:`map_frame_error` is the difference of the two.
"""
from __future__ import annotations

import logging
from typing import Any, Dict, List, Optional

import numpy as np
from evo.core.geometry import umeyama_alignment

from .. import geometry as geo
from ..errors import GeometryError
from ..marker_map import MarkerMap, map_frame_from_reference

logger = logging.getLogger(__name__)


def truth_in_map_frame(est: MarkerMap, truth: MarkerMap, floor_z: float = 0.0) -> np.ndarray:
    """``T_truth_est``: the estimated map's frame definition applied to the truth.

    The estimate's reference marker (``est.reference_marker``) must be in the truth; its true
    pose gives the map frame (origin on the floor z = ``floor_z`` of the truth frame below it,
    z up, x along its x made horizontal).
    A surveyed map (``frame_convention: survey``, anchors) is in the frame of its survey, taken
    to be the truth's (the identity): the anchors must have been surveyed in the truth's frame.
    """
    if est.frame_convention == "survey":
        # A surveyed frame is the frame the anchors were measured in: the truth's, when (as in the
        # demo) they come from the true marker poses; nothing is fitted to the estimate.
        return np.eye(4)
    ref = est.reference_marker
    if ref is None or ref not in truth:
        raise GeometryError(f"the estimated map's reference marker {ref!r} is not in the truth map")
    return map_frame_from_reference(truth.T_map_marker(ref), floor_z=floor_z)


def align_map_to_truth(est: MarkerMap, truth: MarkerMap) -> np.ndarray:
    """Best-fit rigid ``T_truth_est`` (evo's Umeyama alignment of the common markers' corners).

    Raises GeometryError when fewer than 2 markers are shared.
    """
    ids = [i for i in est.ids if i in truth]
    if len(ids) < 2:
        raise GeometryError(f"need at least 2 common markers to align, have {len(ids)}")
    P = np.concatenate([est.corners(i) for i in ids])     # in est frame
    Q = np.concatenate([truth.corners(i) for i in ids])   # in truth frame
    R, t, _ = umeyama_alignment(P.T, Q.T)
    return geo.make_transform(R, t)


def map_error(est: MarkerMap, truth: MarkerMap, T_truth_est: Optional[np.ndarray] = None,
              best_fit: bool = False, floor_z: float = 0.0) -> Dict[str, Any]:
    """Per-marker pose errors of ``est`` against ``truth``.

    Args:
        est: estimated map.
        truth: reference map (e.g. ``Scene.truth_map()``).
        T_truth_est: (4, 4) pose of the estimate's frame in the truth's frame; default: the
            estimate's frame definition applied to the truth (:func:`truth_in_map_frame`), or the
            best fit when ``best_fit``.
        best_fit: use :func:`align_map_to_truth` (SE(3) least squares) instead.
        floor_z: height of the floor in the truth frame.

    Returns:
        dict with ``n`` (common markers), ``position_rms_mm``, ``position_max_mm``,
        ``rotation_mean_deg``, ``rotation_max_deg``, ``per_marker`` ({id: (position mm,
        rotation deg)}), ``missing`` (truth ids not in est), ``extra`` (est ids not in truth),
        ``alignment`` (``reference``, ``given`` or ``best_fit``), ``T_truth_est``.
    """
    if T_truth_est is not None:
        alignment = "given"
        T = geo.validate_transform(T_truth_est, "T_truth_est")
    elif best_fit:
        alignment = "best_fit"
        T = align_map_to_truth(est, truth)
    else:
        alignment = "reference"
        T = truth_in_map_frame(est, truth, floor_z)
    T_est_truth = geo.inverse(T)
    per: Dict[int, tuple] = {}
    for e in est:
        if e.marker_id not in truth:
            continue
        T_true = T_est_truth @ truth.T_map_marker(e.marker_id)
        dp, dr = geo.pose_distance(e.T_map_marker, T_true)
        per[e.marker_id] = (1000.0 * dp, float(np.degrees(dr)))
    pos = np.array([v[0] for v in per.values()])
    rot = np.array([v[1] for v in per.values()])
    missing: List[int] = [i for i in truth.ids if i not in est]
    extra: List[int] = [i for i in est.ids if i not in truth]
    return {
        "n": len(per),
        "position_rms_mm": float(np.sqrt(np.mean(pos ** 2))) if pos.size else float("nan"),
        "position_max_mm": float(pos.max()) if pos.size else float("nan"),
        "rotation_mean_deg": float(rot.mean()) if rot.size else float("nan"),
        "rotation_max_deg": float(rot.max()) if rot.size else float("nan"),
        "per_marker": per,
        "missing": missing,
        "extra": extra,
        "alignment": alignment,
        "T_truth_est": T,
    }


def map_frame_error(est: MarkerMap, truth: MarkerMap, floor_z: float = 0.0) -> Dict[str, float]:
    """How far the map's own frame is from its definition applied to the truth.

    Compares the frame definition alignment (:func:`truth_in_map_frame`: the truth's pose of
    the estimate's reference marker) with the best-fit alignment (:func:`align_map_to_truth`):
    their difference is the error of the frame itself (the reference marker's estimated pose),
    which moves every marker of the map rigidly. Returns ``yaw_deg`` (rotation about the vertical,
    signed), ``rotation_deg`` (whole rotation), ``mm_at_5m`` (the displacement that rotation makes
    5 m from the origin) and ``origin_mm`` (offset of the origin).
    """
    T_own = truth_in_map_frame(est, truth, floor_z)
    T_fit = align_map_to_truth(est, truth)
    D = geo.inverse(T_fit) @ T_own
    ang = geo.rotation_angle(D[:3, :3])
    return {"yaw_deg": float(np.degrees(np.arctan2(D[1, 0], D[0, 0]))),
            "rotation_deg": float(np.degrees(ang)),
            "mm_at_5m": float(5000.0 * 2.0 * np.sin(ang / 2.0)),
            "origin_mm": float(1000.0 * np.linalg.norm(D[:3, 3]))}


def format_map_error(err: Dict[str, Any]) -> str:
    """One line for logs and reports."""
    return (f"{err['n']} markers ({err['alignment']} alignment): position RMS {err['position_rms_mm']:.2f} mm, "
            f"max {err['position_max_mm']:.2f} mm; rotation mean {err['rotation_mean_deg']:.3f} deg, "
            f"max {err['rotation_max_deg']:.3f} deg"
            + (f"; missing {err['missing']}" if err["missing"] else ""))
