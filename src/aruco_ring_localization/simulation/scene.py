"""The simulated hall: room, plate, markers, posts, robot and the test poses (:class:`Scene`).

A scene is data (``config/lab_scene.yaml``, format in docs/simulation.md): another YAML file
describes another hall without code changes. All poses are in the scene's world frame
(``world``: z up, z = 0 on the floor). Angles in the file are in degrees; in this module they are
radians. Poses of the robot are SE(2) tuples ``(x, y, yaw)`` of ``base_link`` on the floor.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from typing import Any, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from .. import geometry as geo
from ..camera import load_yaml_file
from ..errors import ConfigError
from ..marker_map import MarkerEntry, MarkerMap
from ..markers import MAX_MARKER_ID, marker_corners

logger = logging.getLogger(__name__)

SCENE_FORMAT_VERSION = 1

#: config/lab_scene.yaml of the package (the paper's lab).
DEFAULT_SCENE_FILE = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "..",
                                                  "config", "lab_scene.yaml"))

Pose2 = Tuple[float, float, float]

#: The package's config/ directory (where a bare scene file name such as ``lab_scene_harsh.yaml`` is found).
CONFIG_DIR = os.path.dirname(DEFAULT_SCENE_FILE)


def resolve_scene_file(path: str) -> str:
    """The scene file a ``scene.file`` value names: empty = config/lab_scene.yaml; a path that exists
    (absolute or relative to the working directory) as is; otherwise a file of that name in the
    package's config/ (so a YAML file can say ``lab_scene_harsh.yaml`` wherever the package is)."""
    if not path:
        return DEFAULT_SCENE_FILE
    if os.path.isabs(path) or os.path.exists(path):
        return path
    packaged = os.path.join(CONFIG_DIR, path)
    return packaged if os.path.exists(packaged) else path


@dataclass(frozen=True)
class SceneMarker:
    """One marker fixed in the scene.

    Attributes:
        marker_id: ArUco id.
        T_world_marker: (4, 4) pose of the marker frame (x right, y up the marker, z out of the face).
        size: side of the black square, m.
    """

    marker_id: int
    T_world_marker: np.ndarray
    size: float

    def corners_world(self) -> np.ndarray:
        """(4, 3) corners in the world frame, aruco_detect order."""
        return geo.transform_points(self.T_world_marker, marker_corners(self.size))

    @property
    def normal(self) -> np.ndarray:
        """(3,) unit normal of the printed face in the world frame."""
        return self.T_world_marker[:3, 2].copy()


@dataclass(frozen=True)
class Room:
    """Axis-aligned rectangular room: ``origin`` (x, y) of its south-west corner, ``size`` (m)."""

    origin: Tuple[float, float]
    size: Tuple[float, float]
    height: float = 3.0

    def contains(self, x: float, y: float, margin: float = 0.0) -> bool:
        return (self.origin[0] + margin <= x <= self.origin[0] + self.size[0] - margin
                and self.origin[1] + margin <= y <= self.origin[1] + self.size[1] - margin)

    def wall_segments(self) -> np.ndarray:
        """(4, 2, 2) wall segments [[x0, y0], [x1, y1]] of the rectangle."""
        x0, y0 = self.origin
        x1, y1 = x0 + self.size[0], y0 + self.size[1]
        c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
        return np.stack([c, np.roll(c, -1, axis=0)], axis=1)


@dataclass(frozen=True)
class Plate:
    """The steel plate: ``centre`` (x, y) and ``size`` (along x, along y), m."""

    centre: Tuple[float, float]
    size: Tuple[float, float]

    def contains(self, x: float, y: float, margin: float = 0.0) -> bool:
        return (abs(x - self.centre[0]) <= self.size[0] / 2 - margin
                and abs(y - self.centre[1]) <= self.size[1] / 2 - margin)


@dataclass(frozen=True)
class Post:
    """A vertical square column (the laser sees it): ``centre`` (x, y), ``side``, ``height`` (m).

    With ``occludes`` it is opaque to the cameras too: it hides the markers behind it (corners mode)
    and is drawn (images mode). The kind lab's thin posts that carry markers do not.
    """

    name: str
    centre: Tuple[float, float]
    side: float
    height: float
    occludes: bool = False

    def ray_hits(self, origin: np.ndarray, directions: np.ndarray, t_max: float = np.inf) -> np.ndarray:
        """Distance along each ray ``origin + t d`` (world frame; ``directions`` (N, 3)) at which it
        enters the column, for ``0 < t < t_max``; ``inf`` where it misses (slab test)."""
        lo = np.array([self.centre[0] - self.side / 2, self.centre[1] - self.side / 2, 0.0])
        hi = np.array([self.centre[0] + self.side / 2, self.centre[1] + self.side / 2, self.height])
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t1 = (lo - origin) * inv
            t2 = (hi - origin) * inv
        # a ray parallel to a slab: inside it (t from -inf to inf) or outside it (nan: never)
        t1 = np.where(np.isnan(t1), np.inf, t1)
        t2 = np.where(np.isnan(t2), np.inf, t2)
        near = np.max(np.minimum(t1, t2), axis=1)
        far = np.min(np.maximum(t1, t2), axis=1)
        hit = (near <= far) & (near > 0.0) & (near < t_max)
        return np.where(hit, near, np.inf)

    def segments(self) -> np.ndarray:
        """(4, 2, 2) outline segments."""
        h = self.side / 2
        cx, cy = self.centre
        c = np.array([[cx - h, cy - h], [cx + h, cy - h], [cx + h, cy + h], [cx - h, cy + h]])
        return np.stack([c, np.roll(c, -1, axis=0)], axis=1)


@dataclass(frozen=True)
class Robot:
    """The robot's rectangular footprint (length along x, width along y), m, centred on base_link."""

    footprint: Tuple[float, float] = (0.98, 0.61)


@dataclass
class Scene:
    """A hall for the simulator (see module docstring).

    Attributes:
        name: scene name.
        world_frame: name of the world frame (``world``).
        room, plate, posts, robot: the geometry.
        markers: the fixed markers.
        dictionary: OpenCV predefined ArUco dictionary index (7 = DICT_5X5_1000).
        quiet_zone_modules: white margin around each printed marker, in marker modules.
        mapping_pose, mapping_stations, test_positions, test_orientations: SE(2) poses (x, y, yaw rad).
        source: the file it came from.
    """

    name: str
    world_frame: str
    room: Room
    plate: Plate
    markers: List[SceneMarker]
    dictionary: int = 7
    quiet_zone_modules: float = 1.0
    posts: List[Post] = field(default_factory=list)
    robot: Robot = field(default_factory=Robot)
    mapping_pose: Pose2 = (0.0, 0.0, 0.0)
    mapping_stations: List[Pose2] = field(default_factory=list)
    test_positions: List[Pose2] = field(default_factory=list)
    test_orientations: List[Pose2] = field(default_factory=list)
    source: str = "<scene>"

    # --- construction ------------------------------------------------------------------------

    @classmethod
    def default(cls) -> "Scene":
        """The paper's lab (``config/lab_scene.yaml`` of the package)."""
        return cls.load(DEFAULT_SCENE_FILE)

    @classmethod
    def load(cls, path: str) -> "Scene":
        """Load and validate a scene YAML file; errors name the file and the key."""
        return cls.from_dict(load_yaml_file(str(path)), source=str(path))

    @classmethod
    def from_dict(cls, data: Any, source: str = "<scene>") -> "Scene":
        if not isinstance(data, Mapping):
            raise ConfigError(f"expected a mapping at the top level, got {type(data).__name__}", path=source)
        version = data.get("format_version", SCENE_FORMAT_VERSION)
        if version != SCENE_FORMAT_VERSION:
            raise ConfigError(f"unsupported format_version {version!r}", path=source, key="format_version")
        room_d = _mapping(data, "room", source)
        room = Room(origin=tuple(_floats(room_d.get("origin", [0.0, 0.0]), 2, source, "room.origin")),
                    size=tuple(_floats(room_d.get("size"), 2, source, "room.size", positive=True)),
                    height=_float(room_d.get("height", 3.0), source, "room.height", positive=True))
        plate_d = _mapping(data, "plate", source)
        plate = Plate(centre=tuple(_floats(plate_d.get("centre"), 2, source, "plate.centre")),
                      size=tuple(_floats(plate_d.get("size"), 2, source, "plate.size", positive=True)))
        default_size = _float(data.get("marker_size", 0.2), source, "marker_size", positive=True)
        dictionary = data.get("dictionary", 7)
        if not isinstance(dictionary, int) or not 0 <= dictionary <= 21:
            raise ConfigError(f"expected an OpenCV predefined dictionary index 0..21, got {dictionary!r}",
                              path=source, key="dictionary")
        markers = _read_markers(data.get("markers"), default_size, source)
        posts = []
        posts_d = data.get("posts") or []
        if not isinstance(posts_d, list):
            raise ConfigError("expected a list of posts", path=source, key="posts")
        for i, p in enumerate(posts_d):
            key = f"posts[{i}]"
            if not isinstance(p, Mapping):
                raise ConfigError("expected a mapping {name, centre, side, height}", path=source, key=key)
            posts.append(Post(name=str(p.get("name", f"post{i}")),
                              centre=tuple(_floats(p.get("centre"), 2, source, key + ".centre")),
                              side=_float(p.get("side", 0.1), source, key + ".side", positive=True),
                              height=_float(p.get("height", 1.5), source, key + ".height", positive=True),
                              occludes=_bool(p.get("occludes", False), source, key + ".occludes")))
        robot_d = data.get("robot") or {}
        if not isinstance(robot_d, Mapping):
            raise ConfigError("expected a mapping {footprint: [length, width]}", path=source, key="robot")
        robot = Robot(footprint=tuple(_floats(robot_d.get("footprint", [0.98, 0.61]), 2, source,
                                              "robot.footprint", positive=True)))
        scene = cls(
            name=str(data.get("name", os.path.splitext(os.path.basename(source))[0])),
            world_frame=str(data.get("world_frame", "world")),
            room=room, plate=plate, markers=markers, dictionary=dictionary,
            quiet_zone_modules=_float(data.get("quiet_zone_modules", 1.0), source, "quiet_zone_modules"),
            posts=posts, robot=robot,
            mapping_pose=_pose(data.get("mapping_pose", [plate.centre[0], plate.centre[1], 0.0]), source,
                               "mapping_pose"),
            mapping_stations=_poses(data.get("mapping_stations"), source, "mapping_stations"),
            test_positions=_poses(data.get("test_positions"), source, "test_positions"),
            test_orientations=_poses(data.get("test_orientations"), source, "test_orientations"),
            source=source)
        if not scene.mapping_stations:
            scene.mapping_stations = [scene.mapping_pose]
        for m in scene.markers:
            x, y = m.T_world_marker[0, 3], m.T_world_marker[1, 3]
            if not room.contains(x, y, margin=-0.05):
                raise ConfigError(f"marker {m.marker_id} at ({x:.2f}, {y:.2f}) is outside the room",
                                  path=source, key="markers")
        return scene

    # --- queries ---------------------------------------------------------------------------------

    @property
    def marker_ids(self) -> List[int]:
        return [m.marker_id for m in self.markers]

    def marker(self, marker_id: int) -> SceneMarker:
        for m in self.markers:
            if m.marker_id == marker_id:
                return m
        raise KeyError(marker_id)

    def truth_map(self, frame_id: Optional[str] = None) -> MarkerMap:
        """The true marker poses as a :class:`MarkerMap` in the scene's world frame."""
        return MarkerMap([MarkerEntry(m.marker_id, m.T_world_marker.copy(), m.size) for m in self.markers],
                         frame_id=frame_id or self.world_frame, method="ground truth",
                         frame_definition=f"simulator world frame of scene '{self.name}'")

    @staticmethod
    def T_world_base(pose: Sequence[float]) -> np.ndarray:
        """(x, y, yaw rad) -> 4x4 pose of base_link on the floor."""
        return geo.transform_from_se2(float(pose[0]), float(pose[1]), float(pose[2]))

    @property
    def occluders(self) -> List[Post]:
        """The posts the cameras cannot see through."""
        return [p for p in self.posts if p.occludes]

    def obstacle_segments(self) -> np.ndarray:
        """(N, 2, 2) 2D segments a planar laser sees: the walls and the posts."""
        segs = [self.room.wall_segments()] + [p.segments() for p in self.posts]
        return np.concatenate(segs, axis=0)


# --- parsing helpers ----------------------------------------------------------------------------

def marker_pose(position: Sequence[float], facing: float, tilt: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Pose of a marker whose printed face looks along heading ``facing`` (rad, about world z),
    turned up by ``tilt`` (rad) and rotated about its normal by ``roll`` (rad).

    With tilt = roll = 0 the marker hangs upright on a wall: its y axis (top edge) is world z.
    """
    n = np.array([np.cos(facing) * np.cos(tilt), np.sin(facing) * np.cos(tilt), np.sin(tilt)])
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(up, n)
    x /= np.linalg.norm(x)
    y = np.cross(n, x)
    R = np.stack([x, y, n], axis=1)
    if roll:
        R = R @ geo.rot_z(roll)
    return geo.make_transform(R, np.asarray(position, dtype=float))


def _read_markers(items: Any, default_size: float, source: str) -> List[SceneMarker]:
    if not isinstance(items, list) or not items:
        raise ConfigError("expected a non-empty list of markers", path=source, key="markers")
    out: List[SceneMarker] = []
    seen = set()
    for i, m in enumerate(items):
        key = f"markers[{i}]"
        if not isinstance(m, Mapping):
            raise ConfigError("expected a mapping {id, position, facing}", path=source, key=key)
        mid = m.get("id")
        if not isinstance(mid, int) or isinstance(mid, bool) or not 0 <= mid <= MAX_MARKER_ID:
            raise ConfigError(f"expected an integer id 0..{MAX_MARKER_ID}, got {mid!r}", path=source, key=key + ".id")
        if mid in seen:
            raise ConfigError(f"duplicate marker id {mid}", path=source, key=key + ".id")
        seen.add(mid)
        pos = _floats(m.get("position"), 3, source, key + ".position")
        facing = np.radians(_float(m.get("facing"), source, key + ".facing"))
        tilt = np.radians(_float(m.get("tilt", 0.0), source, key + ".tilt"))
        roll = np.radians(_float(m.get("roll", 0.0), source, key + ".roll"))
        if abs(tilt) > np.radians(89.0):
            raise ConfigError("tilt must be within +-89 deg", path=source, key=key + ".tilt")
        size = _float(m.get("size", default_size), source, key + ".size", positive=True)
        out.append(SceneMarker(mid, marker_pose(pos, facing, tilt, roll), size))
    return out


def _mapping(data: Mapping[str, Any], key: str, source: str) -> Mapping[str, Any]:
    v = data.get(key)
    if not isinstance(v, Mapping):
        raise ConfigError("missing or not a mapping", path=source, key=key)
    return v


def _bool(value: Any, source: str, key: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"expected true or false, got {value!r}", path=source, key=key)
    return value


def _float(value: Any, source: str, key: str, positive: bool = False) -> float:
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"expected a number, got {value!r}", path=source, key=key) from None
    if not np.isfinite(f) or (positive and f <= 0):
        raise ConfigError(f"expected a {'positive ' if positive else ''}finite number, got {value!r}",
                          path=source, key=key)
    return f


def _floats(value: Any, n: int, source: str, key: str, positive: bool = False) -> List[float]:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ConfigError(f"expected a list of {n} numbers, got {value!r}", path=source, key=key)
    return [_float(v, source, f"{key}[{i}]", positive) for i, v in enumerate(value)]


def _pose(value: Any, source: str, key: str) -> Pose2:
    x, y, yaw_deg = _floats(value, 3, source, key)
    return (x, y, float(np.radians(yaw_deg)))


def _poses(value: Any, source: str, key: str) -> List[Pose2]:
    if value is None:
        return []
    if not isinstance(value, list):
        raise ConfigError("expected a list of [x, y, yaw_deg]", path=source, key=key)
    return [_pose(v, source, f"{key}[{i}]") for i, v in enumerate(value)]
