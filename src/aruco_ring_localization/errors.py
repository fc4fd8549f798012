"""The package's own exceptions.

Every error the core raises on bad input is one of these, so callers (nodes, the command line
tool, tests) can catch exactly what the package documents and nothing else. Messages are written
for people: they name the file, the key or the field, and say what was expected.
"""
from __future__ import annotations

from typing import List, Optional, Sequence


class ArucoRingError(Exception):
    """Base class of every error raised by aruco_ring_localization on bad input."""


class GeometryError(ArucoRingError, ValueError):
    """A pose, rotation or point array is malformed (wrong shape, NaN, not a rotation)."""


class ConfigError(ArucoRingError, ValueError):
    """A configuration or data file (ring, camera_info, map, scene) is missing or malformed.

    Attributes:
        path: the file, when known.
        key: the dotted key inside the file, when known (e.g. ``cameras[3].T_base_camera``).
    """

    def __init__(self, message: str, path: Optional[str] = None, key: Optional[str] = None):
        self.path = path
        self.key = key
        self.detail = message
        where = []
        if path:
            where.append(str(path))
        if key:
            where.append(f"key '{key}'")
        prefix = ": ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class MeasurementError(ArucoRingError, ValueError):
    """A runtime measurement (detected corners, a camera_info message) is unusable."""


class MapSanityError(ArucoRingError):
    """A map failed its sanity checks (:func:`marker_map.check_map`) and was not written.

    Attributes:
        problems: one line per failed check, naming it, the markers involved and what to do.
        path: the file that was not written (the previous version, if any, is untouched).
    """

    def __init__(self, problems: Sequence[str], path: Optional[str] = None):
        self.problems: List[str] = list(problems)
        self.path = path
        where = f"map not written to {path}" if path else "map not written"
        super().__init__(f"{where} (the previous file, if any, is kept): " + "; ".join(self.problems))
