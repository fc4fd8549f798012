"""Marker geometry in aruco_detect's conventions, per-id sizes and ignore lists.

Marker frame: origin at the centre of the black square, x to the right, y toward the top edge,
z out of the printed face. Corners are numbered as aruco_detect and OpenCV number them:
0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left, at (-L/2, +L/2), (+L/2, +L/2),
(+L/2, -L/2), (-L/2, -L/2) for a marker of side L (the black square, in metres).

Sizes per id use aruco_detect's ``fiducial_len_override`` syntax, ``"1-10: 0.05, 12: 0.06"``;
ignore lists use its ``ignore_fiducials`` syntax, ``"1,4,9-12"``.
"""
from __future__ import annotations

import logging
import math
import re
from typing import Dict, FrozenSet, List, Mapping, Optional

import numpy as np

from .errors import ConfigError

logger = logging.getLogger(__name__)

_CORNER_SIGNS = np.array([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]])

#: Largest id in OpenCV's predefined dictionaries (ARUCO_ORIGINAL has 1024, 5X5_1000 has 1000, ...).
MAX_MARKER_ID = 4095


#: AprilTag detectors (the AprilTag library, apriltag_msgs, TagSLAM) give the corners counter-clockwise
#: in the image from the tag's bottom-left, i.e. (-L/2, -L/2), (+L/2, -L/2), (+L/2, +L/2), (-L/2, +L/2)
#: in the marker frame above; aruco_detect corner k is AprilTag corner ``APRILTAG_TO_ARUCO[k]``.
#: Checked by reprojection of TagSLAM's tag and camera poses onto its detections (test_apriltag.py).
APRILTAG_TO_ARUCO = (3, 2, 1, 0)


def aruco_corners_from_apriltag(corners_px) -> np.ndarray:
    """(4, 2) AprilTag-order corners -> aruco_detect order (0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left)."""
    return np.asarray(corners_px, dtype=np.float64).reshape(4, 2)[list(APRILTAG_TO_ARUCO)]


def marker_corners(length: float) -> np.ndarray:
    """(4, 3) corners of a marker of side ``length`` (m) in its own frame, aruco_detect order."""
    if not np.isfinite(length) or length <= 0.0:
        raise ConfigError(f"marker side must be a positive length in metres, got {length!r}")
    out = np.zeros((4, 3))
    out[:, :2] = _CORNER_SIGNS * (length / 2.0)
    return out


def _parse_id_range(token: str, what: str, source: str) -> range:
    m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", token)
    if not m:
        raise ConfigError(f"cannot read {token.strip()!r} as an id or an id range 'a-b'", key=what, path=source or None)
    lo = int(m.group(1))
    hi = int(m.group(2)) if m.group(2) is not None else lo
    if hi < lo:
        raise ConfigError(f"empty id range {token.strip()!r} (end before start)", key=what, path=source or None)
    if hi > MAX_MARKER_ID:
        raise ConfigError(f"id {hi} is above the largest marker id {MAX_MARKER_ID}", key=what, path=source or None)
    return range(lo, hi + 1)


def parse_id_list(text: str, key: str = "ignore_fiducials", source: str = "") -> FrozenSet[int]:
    """Parse ``"1,4,9-12"`` into a set of ids. Empty text gives an empty set."""
    if text is None:
        return frozenset()
    if isinstance(text, (list, tuple)):
        text = ",".join(str(t) for t in text)
    text = str(text).strip()
    if not text:
        return frozenset()
    ids = set()
    for token in text.split(","):
        if token.strip():
            ids.update(_parse_id_range(token, key, source))
    return frozenset(ids)


def parse_size_overrides(text: str, key: str = "fiducial_len_override", source: str = "") -> Dict[int, float]:
    """Parse ``"1-10: 0.05, 12: 0.06"`` into ``{id: side in metres}``; later entries win."""
    if text is None:
        return {}
    text = str(text).strip()
    if not text:
        return {}
    out: Dict[int, float] = {}
    for token in text.split(","):
        if not token.strip():
            continue
        if ":" not in token:
            raise ConfigError(f"entry {token.strip()!r} needs the form 'ids: length'", key=key, path=source or None)
        ids_text, len_text = token.split(":", 1)
        try:
            length = float(len_text)
        except ValueError:
            raise ConfigError(f"length {len_text.strip()!r} is not a number", key=key, path=source or None) from None
        if not np.isfinite(length) or length <= 0.0:
            raise ConfigError(f"length {length} for ids {ids_text.strip()} must be positive", key=key,
                              path=source or None)
        for i in _parse_id_range(ids_text, key, source):
            out[i] = length
    return out


class MarkerSizes:
    """Side length (m) of each marker id: a default plus per-id overrides."""

    def __init__(self, default: float, overrides: Optional[Mapping[int, float]] = None):
        if not np.isfinite(default) or default <= 0.0:
            raise ConfigError(f"default marker side must be positive, got {default!r}", key="fiducial_len")
        self.default = float(default)
        self.overrides: Dict[int, float] = {int(k): float(v) for k, v in (overrides or {}).items()}

    @classmethod
    def parse(cls, default: float, override_text: str = "") -> "MarkerSizes":
        return cls(default, parse_size_overrides(override_text))

    def __call__(self, marker_id: int) -> float:
        return self.overrides.get(int(marker_id), self.default)

    def corners(self, marker_id: int) -> np.ndarray:
        """(4, 3) corners of marker ``marker_id`` in its own frame."""
        return marker_corners(self(marker_id))


#: Up to this many quads :func:`quads_ok` works on Python floats: the same arithmetic as its
#: array path, without the fixed cost of about twenty small numpy calls (the localizer checks each
#: camera's few detections on every message).
_SCALAR_QUADS = 16


def quads_ok(corners_px: np.ndarray, min_area_px: float = 4.0) -> np.ndarray:
    """(k,) bool for (k, 4, 2) image corners: True where the four corners form a usable quad.

    Usable: finite, convex (not self-intersecting) and at least ``min_area_px`` square pixels.
    Bad detections and corrupted messages give the others.
    """
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if c.shape[0] <= _SCALAR_QUADS:
        return np.array([quad_ok_scalar(q, min_area_px) for q in c.tolist()], dtype=bool)
    finite = np.isfinite(c).all(axis=(1, 2))
    c = np.where(np.isfinite(c), c, 0.0)
    nxt = [1, 2, 3, 0]
    cn = c[:, nxt]
    with np.errstate(over="ignore", invalid="ignore"):
        e = cn - c
        en = e[:, nxt]
        cross = e[:, :, 0] * en[:, :, 1] - e[:, :, 1] * en[:, :, 0]
        convex = (cross > 0).all(axis=1) | (cross < 0).all(axis=1)
        area = 0.5 * np.abs(np.sum(c[:, :, 0] * cn[:, :, 1] - cn[:, :, 0] * c[:, :, 1], axis=1))
        return finite & convex & (area >= min_area_px)


def quad_ok_scalar(q: List[List[float]], min_area_px: float) -> bool:
    """:func:`quads_ok` of one quad given as 4 [x, y] Python floats (IEEE arithmetic as numpy's:
    an overflow gives inf, a NaN fails every comparison): finite, then :func:`finite_quad_ok`."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = q
    isfinite = math.isfinite
    if not (isfinite(x0) and isfinite(y0) and isfinite(x1) and isfinite(y1) and isfinite(x2) and isfinite(y2)
            and isfinite(x3) and isfinite(y3)):
        return False
    return finite_quad_ok(x0, y0, x1, y1, x2, y2, x3, y3, min_area_px)


def finite_quad_ok(x0: float, y0: float, x1: float, y1: float, x2: float, y2: float, x3: float, y3: float,
                   min_area_px: float) -> bool:
    """:func:`quad_ok_scalar` of a quad whose corners the caller found finite already
    (:func:`detections.sanitize_observations` checks them first, to count them apart)."""
    # Unrolled (no comprehension or generator: this runs for every detection the localizer gets).
    ex0, ex1, ex2, ex3 = x1 - x0, x2 - x1, x3 - x2, x0 - x3
    ey0, ey1, ey2, ey3 = y1 - y0, y2 - y1, y3 - y2, y0 - y3
    c0, c1 = ex0 * ey1 - ey0 * ex1, ex1 * ey2 - ey1 * ex2
    c2, c3 = ex2 * ey3 - ey2 * ex3, ex3 * ey0 - ey3 * ex0
    if not ((c0 > 0 and c1 > 0 and c2 > 0 and c3 > 0) or (c0 < 0 and c1 < 0 and c2 < 0 and c3 < 0)):
        return False
    area = 0.5 * abs((x0 * y1 - x1 * y0) + (x1 * y2 - x2 * y1) + (x2 * y3 - x3 * y2) + (x3 * y0 - x0 * y3))
    return area >= min_area_px


def quad_is_degenerate(corners_px, min_area_px: float = 4.0) -> bool:
    """True when four image corners do not form a usable convex quadrilateral (see :func:`quads_ok`)."""
    c = np.asarray(corners_px, dtype=np.float64)
    if c.shape != (4, 2):
        return True
    return not bool(quads_ok(c[None], min_area_px)[0])
