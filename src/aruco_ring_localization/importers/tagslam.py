"""TagSLAM's ``tagslam.yaml``: tag sizes, ignored tags, the tags it fixes, the bodies that move.

TagSLAM describes the world as *bodies* (a list of one-key mappings ``- name: {...}``): static
ones (the building, a board on the wall) and moving ones (the camera rig, a tumbling block). A
body has a ``default_tag_size``, explicit ``tags`` (``id``, ``size``, optional ``pose`` with
``position`` and a rotation-vector ``rotation`` in the body's frame) and, for ``type: board`` /
``staggered_board``, a grid of ``tag_rows`` x ``tag_columns`` tags from ``tag_start_id`` of
``tag_size``. ``default_body`` names the body that newly discovered tags join (its
``default_tag_size`` is the size of every tag not listed); without a ``default_body`` TagSLAM ignores
every tag no body lists ("no default body, ignoring tag"), so the importer does too. ``ignore_tags``
(per body) are tags TagSLAM never uses.

:func:`read_tagslam_tags` returns what mapping needs: :class:`~aruco_ring_localization.markers.MarkerSizes`
(also as aruco_detect's ``fiducial_len`` / ``fiducial_len_override``), the ids to ignore (TagSLAM's
ignored tags, the tags of moving bodies other than the rig: a static map cannot hold them, and
without a ``default_body`` every tag no body lists: :meth:`TagslamTags.ignored_ids`),
and the poses TagSLAM's file fixes (``known_poses``, body frame, for reference only).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Set, Tuple

import numpy as np

from .. import geometry as geo
from ..camera import load_yaml_file
from ..boards import Board, BoardSet, grid_board
from ..errors import ConfigError, GeometryError
from ..markers import MAX_MARKER_ID, MarkerSizes, parse_size_overrides

logger = logging.getLogger(__name__)


@dataclass
class TagslamTags:
    """Tags of a ``tagslam.yaml`` (see the module docstring).

    Attributes:
        default_size: side of a tag not listed (the default body's ``default_tag_size``), m.
        sizes: id -> side, m, for every listed tag (explicit or on a board).
        ignore: TagSLAM's ``ignore_tags`` of all bodies.
        moving: ids of tags on bodies that are not static (not part of a static map).
        known_poses: id -> ``T_body_tag`` for tags whose pose the file gives, on static bodies.
        static_bodies, moving_bodies: body names.
        pixel_noise: TagSLAM's ``tagslam_parameters.pixel_noise`` (px), or None.
        remaps: TagSLAM's ``tag_id_remap``: (detected id, id it stands for, start s, end s), for one
            id printed on several tags seen at different times (:meth:`remap`).
    """

    default_size: float
    sizes: Dict[int, float] = field(default_factory=dict)
    ignore: Set[int] = field(default_factory=set)
    moving: Set[int] = field(default_factory=set)
    known_poses: Dict[int, np.ndarray] = field(default_factory=dict)
    #: id -> (position std (3,) m, rotation std rad) of a known pose (its ``position_noise`` /
    #: ``rotation_noise``, else ``body_defaults``'; the body's ``override_tag_*_noise`` replace both
    #: when it gives them, as in TagSLAM).
    known_noise: Dict[int, Tuple[np.ndarray, float]] = field(default_factory=dict)
    static_bodies: List[str] = field(default_factory=list)
    moving_bodies: List[str] = field(default_factory=list)
    remaps: List[Tuple[int, int, float, float]] = field(default_factory=list)
    #: ``tagslam_parameters.pixel_noise``: the corner noise (px) TagSLAM weighs the images with
    #: against the known poses' noise (None when the file does not give it).
    pixel_noise: Optional[float] = None
    #: ``tagslam_parameters.minimum_viewing_angle`` (deg) and ``minimum_tag_area`` (px^2): the views
    #: TagSLAM drops (None when the file does not give them).
    minimum_viewing_angle: Optional[float] = None
    minimum_tag_area: Optional[float] = None
    #: ``default_body``: the body undeclared tags join; None when the file names none, and then
    #: TagSLAM ignores every tag that no body lists (:meth:`ignored_ids`).
    default_body: Optional[str] = None

    @property
    def undeclared_ignored(self) -> bool:
        """True when TagSLAM ignores the tags no body lists (the file names no ``default_body``)."""
        return self.default_body is None

    def ignored_ids(self) -> Set[int]:
        """Every id a static map of this file must leave out: TagSLAM's ``ignore_tags``, the tags of
        moving bodies and, without a ``default_body``, every id (up to ``MAX_MARKER_ID``) that no body
        lists -- TagSLAM drops those detections (test_24: tags 2090-2094 and 2100-2104 of boards the
        file does not declare, whose size is not the default's)."""
        out = set(self.ignore) | set(self.moving)
        if self.undeclared_ignored:
            out |= set(range(MAX_MARKER_ID + 1)) - set(self.sizes)
        return out

    def remap(self, marker_id: int, stamp: float) -> int:
        """The id a detection of ``marker_id`` at ``stamp`` (s) stands for (``tag_id_remap``)."""
        for mid, new, start, end in self.remaps:
            if mid == marker_id and start <= stamp <= end:
                return new
        return marker_id

    def marker_sizes(self) -> MarkerSizes:
        return MarkerSizes(self.default_size, {i: s for i, s in self.sizes.items() if s != self.default_size})

    def fiducial_len_override(self) -> str:
        """aruco_detect's ``fiducial_len_override`` for the tags whose size is not the default."""
        return _ranges({i: s for i, s in self.sizes.items() if s != self.default_size})

    def ignore_fiducials(self) -> str:
        """aruco_detect's ``ignore_fiducials`` for :meth:`ignored_ids` (ranges)."""
        return _ranges({i: 0.0 for i in self.ignored_ids()}, with_value=False)


def _ranges(values: Mapping[int, float], with_value: bool = True) -> str:
    out: List[str] = []
    ids = sorted(values)
    i = 0
    while i < len(ids):
        j = i
        while j + 1 < len(ids) and ids[j + 1] == ids[j] + 1 and values[ids[j + 1]] == values[ids[i]]:
            j += 1
        span = str(ids[i]) if i == j else f"{ids[i]}-{ids[j]}"
        out.append(f"{span}: {values[ids[i]]:g}" if with_value else span)
        i = j + 1
    return ", ".join(out)


def _positive(value: Any, path: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
        raise ConfigError(f"expected a positive length in metres, got {value!r}", path=path, key=key)
    return float(value)


def _number(value: Any, path: str, key: str, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
        raise ConfigError(f"expected {what} (>= 0), got {value!r}", path=path, key=key)
    return float(value)


def _pose(node: Any, path: str, key: str) -> np.ndarray:
    try:
        t = np.array([float(node["position"][a]) for a in ("x", "y", "z")])
        r = np.array([float(node["rotation"][a]) for a in ("x", "y", "z")])
    except (TypeError, KeyError, ValueError):
        raise ConfigError("expected {position: {x, y, z}, rotation: {x, y, z}}", path=path, key=key) from None
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(r))):
        raise ConfigError("contains NaN or infinite values", path=path, key=key)
    return geo.transform_from_rvec_tvec(r, t)


def _override_noise(body: Mapping[str, Any], path: str, key: str) -> Optional[Tuple[np.ndarray, float]]:
    """A body's ``override_tag_position_noise`` / ``override_tag_rotation_noise`` (TagSLAM applies
    them to every tag of the body with a pose, in place of the tag's own noise, when both are > 0)."""
    p, r = body.get("override_tag_position_noise"), body.get("override_tag_rotation_noise")
    if p is None or r is None:
        return None
    for name, v in (("override_tag_position_noise", p), ("override_tag_rotation_noise", r)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise ConfigError(f"expected a number, got {v!r}", path=path, key=f"{key}.{name}")
    if p <= 0 or r <= 0:
        return None
    return np.full(3, float(p)), float(r)


@dataclass(frozen=True)
class TagslamOdometry:
    """The odometry of a ``tagslam.yaml``'s rig body (:func:`tagslam_odometry`).

    Attributes:
        topic: its nav_msgs/Odometry topic (``odom_topic``).
        T_body_odom: (4, 4) the pose of the odometry's frame in the rig body (identity when omitted).
        acceleration, acceleration_max: TagSLAM's adaptive noise bounds, m/s^2
            (``odom_acceleration_noise_min`` or the older ``odom_acceleration``, default 5;
            ``odom_acceleration_noise_max``, default 10 x the minimum).
        angular_acceleration, angular_acceleration_max: the same for the rotation, rad/s^2.
        translation_noise, rotation_noise: TagSLAM's fixed per-message sigmas (``odom_translation_noise``,
            ``odom_rotation_noise``, m and rad; 0 when omitted: TagSLAM then uses the adaptive noise,
            as it does unless both are set).
    """

    topic: str
    T_body_odom: np.ndarray
    acceleration: float = 5.0
    acceleration_max: float = 50.0
    angular_acceleration: float = 5.0
    angular_acceleration_max: float = 50.0
    translation_noise: float = 0.0
    rotation_noise: float = 0.0

    @property
    def base_to_odom(self) -> Tuple[float, float, float, float, float, float]:
        """``T_body_odom`` as ``mapping.odometry.base_to_odom`` (x, y, z, then the rotation vector)."""
        rvec, tvec = geo.rvec_tvec_from_transform(self.T_body_odom)
        return tuple(float(v) for v in np.r_[tvec, rvec])

    def link_noise(self) -> Dict[str, Any]:
        """``mapping.odometry`` keys for TagSLAM's noise of these messages (``noise_model:
        per_message``: a sigma per message, summed over the messages a link spans)."""
        return {"noise_model": "per_message", "message_acceleration": self.acceleration,
                "message_acceleration_max": self.acceleration_max,
                "message_angular_acceleration": self.angular_acceleration,
                "message_angular_acceleration_max": self.angular_acceleration_max,
                "message_translation_noise": self.translation_noise, "message_rotation_noise": self.rotation_noise}

    def stated_link_noise(self) -> Dict[str, Any]:
        """:meth:`link_noise` judged as TagSLAM judges it: at the frames (``message_sampling:
        frames``), one odometry message per frame as its synchronizer pairs them (the messages one
        by one would weigh a 30 Hz odometry 15 times more: docs/mapping.md)."""
        return {**self.link_noise(), "message_sampling": "frames"}


def tagslam_odometry(path: str, rig_body: str) -> Optional[TagslamOdometry]:
    """The odometry of the rig body of a ``tagslam.yaml`` (:class:`TagslamOdometry`), or None when it
    has none: the topic of its nav_msgs/Odometry, the pose of the odometry's frame in the rig body
    (``mapping.odometry.base_to_odom`` when the ring's base frame is the rig body; identity when the
    file omits it, as TagSLAM assumes), and TagSLAM's noise parameters with TagSLAM's defaults."""
    data = load_yaml_file(path)
    if not isinstance(data, Mapping):
        raise ConfigError("expected a mapping", path=path)
    for i, (name, body) in enumerate(_bodies(data, path)):
        if name != rig_body or not body.get("odom_topic"):
            continue
        T = np.eye(4)
        if body.get("T_body_odom") is not None:
            T = _pose(body["T_body_odom"], path, f"bodies[{i}].{name}.T_body_odom")

        def value(key: str, default: float, positive: bool = True) -> float:
            v = body.get(key, default)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) \
                    or (v <= 0 if positive else False):
                raise ConfigError(f"expected a {'positive ' if positive else ''}number, got {v!r}", path=path,
                                  key=f"bodies[{i}].{name}.{key}")
            return float(v)

        # TagSLAM's rules: the older name gives the minimum's default, the maximum is 10 x the
        # minimum unless set; a fixed noise (<= 0: not set) replaces the adaptive one only when both are set.
        acc = value("odom_acceleration_noise_min", value("odom_acceleration", 5.0))
        ang = value("odom_angular_acceleration_noise_min", value("odom_angular_acceleration", 5.0))
        fixed = [max(value(k, -1.0, positive=False), 0.0) for k in ("odom_translation_noise", "odom_rotation_noise")]
        if not (fixed[0] > 0 and fixed[1] > 0):
            fixed = [0.0, 0.0]
        return TagslamOdometry(str(body["odom_topic"]), T, acc, value("odom_acceleration_noise_max", 10.0 * acc),
                               ang, value("odom_angular_acceleration_noise_max", 10.0 * ang), fixed[0], fixed[1])
    return None


def tagslam_pixel_noise(path: str) -> Optional[float]:
    """A ``tagslam.yaml``'s corner noise (``tagslam_parameters.pixel_noise``, px), or None when it
    states none: what TagSLAM weighs the images with against its odometry and its priors."""
    data = load_yaml_file(path)
    if not isinstance(data, Mapping):
        raise ConfigError("expected a mapping", path=path)
    return _pixel_noise(data, path)


def _pixel_noise(data: Mapping[str, Any], path: str) -> Optional[float]:
    params = data.get("tagslam_parameters")
    if isinstance(params, Mapping) and params.get("pixel_noise") is not None:
        return _positive(params["pixel_noise"], path, "tagslam_parameters.pixel_noise")
    return None


def _noise(node: Mapping[str, Any], defaults: Any, path: str, key: str) -> Tuple[np.ndarray, float]:
    """(position std (3,), rotation std) of a TagSLAM pose: its own noise, else body_defaults'."""
    defaults = defaults if isinstance(defaults, Mapping) else {}
    out = []
    for name in ("position_noise", "rotation_noise"):
        value = node.get(name, defaults.get(name, 0.05 if name == "position_noise" else 0.01))
        try:
            v = (np.array([float(value[a]) for a in ("x", "y", "z")]) if isinstance(value, Mapping)
                 else np.full(3, float(value)))
        except (TypeError, KeyError, ValueError):
            raise ConfigError("expected a number or {x, y, z}", path=path, key=f"{key}.{name}") from None
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise ConfigError(f"expected positive values, got {value!r}", path=path, key=f"{key}.{name}")
        out.append(v)
    return out[0], float(out[1].max())


def tagslam_anchors(tags: TagslamTags, exclude: Set[int] = frozenset(), source: str = "tagslam.yaml",
                    full_pose: bool = True):
    """The tags whose poses ``tagslam.yaml`` fixes (surveyed) as anchors (:class:`anchors.AnchorSet`)
    for ``build-map --anchors``, or None when it fixes none. Each anchor is the tag's full pose, as
    TagSLAM uses it: position with its ``position_noise`` as std, orientation with its
    ``rotation_noise`` (the body's ``override_tag_*_noise`` when it sets them). With full poses one
    anchored tag places a group of tags that no image links to the others (:class:`mapping.MapBuilder`
    seeds it from the anchor). ``full_pose=False``: positions only (a single fixed tag still keeps
    its rotation, since one position cannot fix a frame). ``exclude``: ids not to anchor (ignored,
    moving)."""
    from ..anchors import Anchor, AnchorSet

    ids = sorted(i for i in tags.known_poses if i not in exclude)
    if not ids:
        return None
    full = full_pose or len(ids) == 1
    out = []
    for i in ids:
        T = tags.known_poses[i]
        pos_std, rot_std = tags.known_noise.get(i, (np.full(3, 0.05), 0.01))
        out.append(Anchor(i, T[:3, 3].copy(), pos_std, T[:3, :3].copy() if full else None,
                          rot_std if full else None, "TagSLAM known pose", f"tag {i}"))
    return AnchorSet(out, frame_id="tagslam", source=source)


def _ids(value: Any, path: str, key: str) -> Set[int]:
    if value is None:
        return set()
    if not isinstance(value, list) or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        raise ConfigError(f"expected a list of tag ids, got {value!r}", path=path, key=key)
    return set(value)


def _bodies(data: Mapping[str, Any], path: str) -> List[Tuple[str, Mapping[str, Any]]]:
    bodies = data.get("bodies")
    if not isinstance(bodies, list):
        raise ConfigError("expected a list of bodies (- name: {...})", path=path, key="bodies")
    out = []
    for i, b in enumerate(bodies):
        if not isinstance(b, Mapping) or len(b) != 1 or not isinstance(next(iter(b.values())), Mapping):
            raise ConfigError("expected a one-key mapping name: {...}", path=path, key=f"bodies[{i}]")
        name, body = next(iter(b.items()))
        out.append((str(name), body))
    return out


def _board(name: str, kind: str, grid: Mapping[str, Any], size: float, path: str, key: str) -> Board:
    """The layout of a ``board`` / ``staggered_board`` body (TagSLAM's): :func:`boards.grid_board`."""
    try:
        start, rows, cols = (int(grid[k]) for k in ("tag_start_id", "tag_rows", "tag_columns"))
    except (KeyError, TypeError, ValueError):
        raise ConfigError("expected tag_start_id, tag_rows, tag_columns", path=path, key=f"{key}.{kind}") from None
    spacing = grid.get("tag_spacing")
    if isinstance(spacing, bool) or not isinstance(spacing, (int, float)) or not spacing >= 0:
        raise ConfigError(f"expected the gap between tags over their side (>= 0), got {spacing!r}", path=path,
                          key=f"{key}.{kind}.tag_spacing")
    if rows < 1 or cols < 1:
        raise ConfigError(f"expected tag_rows and tag_columns >= 1, got {rows} and {cols}", path=path,
                          key=f"{key}.{kind}")
    T_board_body = _pose(grid["pose"], path, f"{key}.{kind}.pose") if grid.get("pose") is not None else None
    return grid_board(name, start, rows, cols, size, float(spacing), staggered=kind == "staggered_board",
                      T_board_body=T_board_body)


def _play(grid: Mapping[str, Any], path: str, key: str) -> Tuple[float, float]:
    """(``tag_position_noise`` m, ``tag_rotation_noise`` rad) of a board description, 0 when absent."""
    out = []
    for k in ("tag_position_noise", "tag_rotation_noise"):
        v = grid.get(k, 0.0)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0 or not np.isfinite(v):
            raise ConfigError(f"expected a std >= 0, got {v!r}", path=path, key=f"{key}.{k}")
        out.append(float(v))
    if (out[0] > 0) != (out[1] > 0):
        raise ConfigError(f"expected tag_position_noise and tag_rotation_noise both 0 (a rigid board) or both > 0 "
                          f"(tags loose on the board), got {out[0]!r} and {out[1]!r}", path=path, key=key)
    return out[0], out[1]


def tagslam_boards(path: str, rig_bodies: Tuple[str, ...] = (), play: bool = True) -> BoardSet:
    """The static ``board`` and ``staggered_board`` bodies of a ``tagslam.yaml`` as boards
    (:mod:`~aruco_ring_localization.boards`): tags ``tag_size * (1 + tag_spacing)`` apart, row by row
    from ``tag_start_id`` (a staggered board: every other cell). TagSLAM's ``tag_position_noise``
    (m) / ``tag_rotation_noise`` (rad), the play between a tag and its board, become the board's
    ``tag_position_std`` / ``tag_rotation_std_deg`` (a loose board; absent or 0: rigid); ``play``
    False takes every layout as exact. ConfigError names the file and key of a bad entry."""
    data = load_yaml_file(path)
    if not isinstance(data, Mapping):
        raise ConfigError("expected a mapping", path=path)
    out: List[Board] = []
    for i, (name, body) in enumerate(_bodies(data, path)):
        kind = str(body.get("type", "simple"))
        if kind not in ("board", "staggered_board") or not body.get("is_static", False) or name in rig_bodies:
            continue
        key = f"bodies[{i}].{name}"
        grid = body.get(kind)
        if not isinstance(grid, Mapping):
            raise ConfigError(f"expected the {kind} description", path=path, key=f"{key}.{kind}")
        size = _positive(grid.get("tag_size", body.get("default_tag_size")), path, f"{key}.{kind}.tag_size")
        board = _board(name, kind, grid, size, path, key)
        pos, rot = _play(grid, path, f"{key}.{kind}")
        if play and pos > 0:
            board = Board(board.name, board.layout, tag_position_std=pos, tag_rotation_std_deg=float(np.degrees(rot)))
        out.append(board)
    try:
        return BoardSet(out, source=path)
    except GeometryError as e:
        raise ConfigError(str(e), path=path, key="bodies") from None


def read_tagslam_tags(path: str, rig_bodies: Tuple[str, ...] = ()) -> TagslamTags:
    """Read the tags of a ``tagslam.yaml``; ConfigError names the file and key of a bad entry.

    Args:
        rig_bodies: names of the bodies that carry the cameras (their tags, if any, are
            ``moving`` too); bodies that are not ``is_static`` are moving whatever their name.
    """
    data = load_yaml_file(path)
    if not isinstance(data, Mapping):
        raise ConfigError("expected a mapping", path=path)
    bodies = _bodies(data, path)
    default_body = data.get("default_body")
    names = [n for n, _ in bodies]
    if default_body is not None and default_body not in names:
        raise ConfigError(f"names no body of 'bodies' ({', '.join(names)})", path=path, key="default_body")
    default_size = None
    out = TagslamTags(default_size=0.0)
    for i, (name, body) in enumerate(bodies):
        key = f"bodies[{i}].{name}"
        static = bool(body.get("is_static", False)) and name not in rig_bodies
        (out.static_bodies if static else out.moving_bodies).append(name)
        out.ignore |= _ids(body.get("ignore_tags"), path, f"{key}.ignore_tags")
        size = body.get("default_tag_size")
        if size is not None:
            size = _positive(size, path, f"{key}.default_tag_size")
            if name == default_body or (default_body is None and default_size is None and static):
                default_size = size
        ids: Dict[int, float] = {}
        override = _override_noise(body, path, key)
        for j, tag in enumerate(body.get("tags") or []):
            tkey = f"{key}.tags[{j}]"
            if not isinstance(tag, Mapping) or isinstance(tag.get("id"), bool) or not isinstance(tag.get("id"), int):
                raise ConfigError("expected {id: N, size: L, pose: ...}", path=path, key=tkey)
            tsize = tag.get("size", size)
            if tsize is None:
                raise ConfigError("no size and no default_tag_size in its body", path=path, key=f"{tkey}.size")
            ids[tag["id"]] = _positive(tsize, path, f"{tkey}.size")
            if static and tag.get("pose") is not None and body.get("pose") is not None:
                T_w_body = _pose(body["pose"], path, f"{key}.pose")
                out.known_poses[tag["id"]] = T_w_body @ _pose(tag["pose"], path, f"{tkey}.pose")
                out.known_noise[tag["id"]] = override or _noise(tag["pose"], data.get("body_defaults"), path,
                                                                f"{tkey}.pose")
        kind = str(body.get("type", "simple"))
        if kind in ("board", "staggered_board"):
            grid = body.get(kind)
            if not isinstance(grid, Mapping):
                raise ConfigError(f"expected the {kind} description", path=path, key=f"{key}.{kind}")
            try:
                start, rows, cols = (int(grid[k]) for k in ("tag_start_id", "tag_rows", "tag_columns"))
            except (KeyError, TypeError, ValueError):
                raise ConfigError("expected tag_start_id, tag_rows, tag_columns", path=path, key=f"{key}.{kind}") from None
            bsize = _positive(grid.get("tag_size", size), path, f"{key}.{kind}.tag_size")
            for m in _board(name, kind, grid, bsize, path, key).layout:
                ids[m] = bsize
        out.sizes.update(ids)
        if not static:
            out.moving |= set(ids)
    for i, r in enumerate(data.get("tag_id_remap") or []):
        key = f"tag_id_remap[{i}]"
        try:
            mid = int(r["id"])
            for j, m in enumerate(r["remaps"]):
                out.remaps.append((mid, int(m["remap_id"]), float(m["start_time"]), float(m["end_time"])))
        except (TypeError, KeyError, ValueError):
            raise ConfigError("expected {id, remaps: [{remap_id, start_time, end_time}]}", path=path, key=key) from None
    if default_size is None:
        raise ConfigError("no default_tag_size in the default body (or in any static body)", path=path,
                          key="default_body")
    out.default_size = default_size
    out.default_body = None if default_body is None else str(default_body)
    params = data.get("tagslam_parameters")
    out.pixel_noise = _pixel_noise(data, path)
    if isinstance(params, Mapping) and params.get("minimum_viewing_angle") is not None:
        out.minimum_viewing_angle = _number(params["minimum_viewing_angle"], path,
                                            "tagslam_parameters.minimum_viewing_angle", "an angle in degrees")
    if isinstance(params, Mapping) and params.get("minimum_tag_area") is not None:
        out.minimum_tag_area = _number(params["minimum_tag_area"], path, "tagslam_parameters.minimum_tag_area",
                                       "an area in square pixels")
    return out


def marker_sizes_from(fiducial_len: float, fiducial_len_override: str = "", tagslam_file: str = "") -> MarkerSizes:
    """Marker sides from aruco_detect's parameters, or a ``tagslam.yaml`` (its sizes, then the
    ``fiducial_len_override`` entries on top; ``fiducial_len`` is the default only without a file)."""
    if not tagslam_file:
        return MarkerSizes.parse(fiducial_len, fiducial_len_override)
    base = read_tagslam_tags(tagslam_file).marker_sizes()
    return MarkerSizes(base.default, {**base.overrides, **parse_size_overrides(fiducial_len_override)})


#: TagSLAM's corner k of a tag is the package's corner ``TAGSLAM_CORNER[k]`` (TagSLAM numbers them
#: from (-s/2, -s/2) counter-clockwise in the tag's frame, the package from (-s/2, +s/2) clockwise:
#: :func:`markers.marker_corners`); TagSLAM's corner -1 is the centre (None).
TAGSLAM_CORNER = {0: 3, 1: 2, 2: 1, 3: 0, -1: None}


def _named_entries(data: Mapping[str, Any], name: str, path: str) -> List[Tuple[str, str, Mapping[str, Any]]]:
    """The ``- label: {...}`` entries of a tagslam.yaml list (key, label, fields)."""
    nodes = data.get(name)
    if nodes is None:
        return []
    if not isinstance(nodes, list):
        raise ConfigError("expected a list of '- name: {...}' entries", path=path, key=name)
    out = []
    for i, n in enumerate(nodes):
        if not isinstance(n, Mapping) or len(n) != 1 or not isinstance(next(iter(n.values())), Mapping):
            raise ConfigError("expected a one-key mapping name: {...}", path=path, key=f"{name}[{i}]")
        label, fields = next(iter(n.items()))
        out.append((f"{name}[{i}]", str(label), fields))
    return out


def _tagslam_field(fields: Mapping[str, Any], field_name: str, path: str, key: str, kind: type) -> Any:
    v = fields.get(field_name)
    ok = isinstance(v, int) if kind is int else isinstance(v, (int, float)) and bool(np.isfinite(v))
    if isinstance(v, bool) or not ok:
        raise ConfigError(f"expected {'an integer' if kind is int else 'a number'}, got {v!r}", path=path,
                          key=f"{key}.{field_name}")
    return kind(v)


def _tagslam_corner(fields: Mapping[str, Any], field_name: str, path: str, key: str) -> Any:
    c = _tagslam_field(fields, field_name, path, key, int)
    if c not in TAGSLAM_CORNER:
        raise ConfigError(f"expected a corner 0-3 or -1 (the centre), got {c}", path=path, key=f"{key}.{field_name}")
    corner = TAGSLAM_CORNER[c]
    return "centre" if corner is None else corner


def _tagslam_direction(fields: Mapping[str, Any], path: str, key: str) -> List[float]:
    v = fields.get("direction")
    try:
        d = np.array([float(x) for x in v], dtype=float) if isinstance(v, list) and len(v) == 3 \
            and not any(isinstance(x, bool) for x in v) else None
    except (TypeError, ValueError):
        d = None
    if d is None or not np.all(np.isfinite(d)) or abs(float(np.linalg.norm(d)) - 1.0) > 1e-5:
        raise ConfigError(f"expected a unit vector [x, y, z], got {v!r}", path=path, key=f"{key}.direction")
    return [float(x) for x in d]


def tagslam_measurements(path: str, exclude: Set[int] = frozenset(), source: str = ""):
    """The survey measurements of a ``tagslam.yaml`` as :class:`anchors.Measurements` (the anchors
    file's ``distances`` and ``planes``), or None when it has none:

    * ``distance_measurements`` (``tag1``/``corner1`` to ``tag2``/``corner2``, ``distance``,
      ``noise`` as the std): a distance between the two corners, TagSLAM's corner numbers converted
      to the package's (:data:`TAGSLAM_CORNER`);
    * ``plane_measurements`` (``tags``, ``direction``, ``distance``, ``noise``): TagSLAM holds each
      tag's *centre* on the plane ``direction . p = distance``: a plane of centres;
    * ``coordinate_measurements`` (``tag``, ``corner``, ``direction``, ``length``, ``noise``): one
      corner on the plane ``direction . p = length``: a plane of that one corner.

    Measurements of tags in ``exclude`` (ignored, moving) are left out. ConfigError names the file
    and the entry."""
    import dataclasses

    from ..anchors import measurements_from_dict

    data = load_yaml_file(path)
    if not isinstance(data, Mapping):
        raise ConfigError("expected a mapping", path=path)
    dists, planes, dkeys, pkeys = [], [], [], []
    for key, label, f in _named_entries(data, "distance_measurements", path):
        t1, t2 = (_tagslam_field(f, k, path, key, int) for k in ("tag1", "tag2"))
        if t1 in exclude or t2 in exclude:
            continue
        dists.append({"from": {"marker": t1, "corner": _tagslam_corner(f, "corner1", path, key)},
                      "to": {"marker": t2, "corner": _tagslam_corner(f, "corner2", path, key)},
                      "distance": _tagslam_field(f, "distance", path, key, float),
                      "std": _tagslam_field(f, "noise", path, key, float), "instrument": f"TagSLAM {label}"})
        dkeys.append(f"{key} ({label})")
    for key, label, f in _named_entries(data, "plane_measurements", path):
        tags = f.get("tags")
        if not isinstance(tags, list) or not all(isinstance(t, int) and not isinstance(t, bool) for t in tags):
            raise ConfigError(f"expected a list of tag ids, got {tags!r}", path=path, key=f"{key}.tags")
        tags = [t for t in tags if t not in exclude]
        if tags:
            pkeys.append(f"{key} ({label})")
            planes.append({"markers": tags, "normal": _tagslam_direction(f, path, key),
                           "std": _tagslam_field(f, "noise", path, key, float),
                           "distance": _tagslam_field(f, "distance", path, key, float), "points": "centres",
                           "instrument": f"TagSLAM {label}"})
    for key, label, f in _named_entries(data, "coordinate_measurements", path):
        t = _tagslam_field(f, "tag", path, key, int)
        if t in exclude:
            continue
        corner = _tagslam_corner(f, "corner", path, key)
        pkeys.append(f"{key} ({label})")
        planes.append({"markers": [t], "normal": _tagslam_direction(f, path, key),
                       "std": _tagslam_field(f, "noise", path, key, float),
                       "distance": _tagslam_field(f, "length", path, key, float),
                       "points": "centres" if corner == "centre" else corner, "instrument": f"TagSLAM {label}"})
    if not dists and not planes:
        return None
    out = measurements_from_dict({"distances": dists, "planes": planes}, source=source or path)
    # Messages and the map's record name TagSLAM's entries.
    out.distances = [dataclasses.replace(d, key=k) for d, k in zip(out.distances, dkeys)]
    out.planes = [dataclasses.replace(p, key=k) for p, k in zip(out.planes, pkeys)]
    return out
