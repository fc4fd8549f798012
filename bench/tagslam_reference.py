"""TagSLAM's answer for one recording of shared/data/tagslam_test (its ``reference.bag``).

``reference.bag`` holds TagSLAM's optimized solution: the rig (body) poses as nav_msgs/Odometry on
``/tagslam/odom/body_<rig>`` (frame ``map``) and, on ``/tf``, ``map -> <static body> -> tag_<id>``
and ``<rig> -> camK`` (the camera poses TagSLAM calibrated or kept). Tag and camera poses are
constant over the bag; the last message is used. The tag frame is the package's marker frame
(x right, y up, z out of the tag: test/unit/test_apriltag.py shows it by reprojection).

The detections are read through the package's bag source (:func:`ring_frames`: the one reader
``aruco_ring build-map`` and ``localize`` use), TagSLAM's tag id remapping applied.

Bags are bzip2-compressed in the shared folder: :func:`cached_bag` decompresses each one once
into ``results/cache/tagslam/<test>/`` (ignored by git).
"""
from __future__ import annotations

import bz2
import os
import shutil
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
DATA = os.environ.get("TAGSLAM_TEST_DATA", os.path.join(os.path.dirname(os.path.dirname(ROOT)), "shared", "data",
                                                          "tagslam_test", "tests"))
if not os.path.isdir(DATA):
    DATA = "/work/shared/data/tagslam_test/tests"
CACHE = os.path.join(ROOT, "results", "cache", "tagslam")


def cached_bag(test: str, name: str) -> str:
    """Path of ``<name>.bag`` of ``test``, decompressed into the cache on first use."""
    out = os.path.join(CACHE, test, f"{name}.bag")
    if not os.path.exists(out):
        os.makedirs(os.path.dirname(out), exist_ok=True)
        tmp = out + ".part"
        with bz2.open(os.path.join(DATA, test, f"{name}.bag.bz2"), "rb") as src, open(tmp, "wb") as dst:
            shutil.copyfileobj(src, dst, 1 << 20)
        os.replace(tmp, out)
    return out


@dataclass
class Reference:
    """TagSLAM's solution (all ``T_<to>_<from>``, 4x4).

    Attributes:
        tags: id -> ``T_map_tag`` of every tag on a static body.
        cameras: camera name -> ``T_rig_cam``.
        rig_body: name of the rig body.
        stamps, T_map_rig: the rig's poses (s; (N, 4, 4)).
    """

    tags: Dict[int, np.ndarray] = field(default_factory=dict)
    cameras: Dict[str, np.ndarray] = field(default_factory=dict)
    rig_body: str = "rig"
    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    T_map_rig: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))


def _T(tr) -> np.ndarray:
    from aruco_ring_localization import geometry as geo

    t, q = tr.translation, tr.rotation
    return geo.transform_from_translation_quaternion([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])


def load_reference(bag_path: str, rig_body: str, static_bodies: List[str]) -> Reference:
    """Read ``reference.bag`` (see the module docstring)."""
    import rosbag

    from aruco_ring_localization import geometry as geo

    last: Dict[tuple, np.ndarray] = {}
    stamps, poses = [], []
    odom = f"/tagslam/odom/body_{rig_body}"
    with rosbag.Bag(bag_path) as bag:
        for topic, msg, _ in bag.read_messages(topics=["/tf", odom]):
            if topic == "/tf":
                for ts in msg.transforms:
                    last[(ts.header.frame_id.lstrip("/"), ts.child_frame_id.lstrip("/"))] = _T(ts.transform)
            else:
                p = msg.pose.pose
                stamps.append(msg.header.stamp.to_sec())
                poses.append(geo.transform_from_translation_quaternion(
                    [p.position.x, p.position.y, p.position.z],
                    [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]))
    ref = Reference(rig_body=rig_body)
    parent = {c: (p, T) for (p, c), T in last.items()}

    def in_map(frame: str):
        T, n = np.eye(4), frame
        while n in parent and n != "map":
            p, Tp = parent[n]
            T, n = Tp @ T, p
        return T if n == "map" else None

    for (p, c), T in last.items():
        if c.startswith("tag_") and p in static_bodies:
            T_map = in_map(c)
            if T_map is not None:
                ref.tags[int(c[4:])] = T_map
        elif p == rig_body and c.startswith("cam"):
            ref.cameras[c] = T
    order = np.argsort(stamps)
    ref.stamps = np.asarray(stamps, dtype=float)[order]
    ref.T_map_rig = np.asarray(poses).reshape(-1, 4, 4)[order]
    return ref


def write_tum_poses(path: str, stamps, poses, header: str = "") -> None:
    """``t x y z qx qy qz qw`` per pose (full 6-DOF TUM, evo's format)."""
    from aruco_ring_localization import geometry as geo
    from aruco_ring_localization.fileio import atomic_write_text

    lines = [f"# {header}"] if header else []
    for t, T in zip(stamps, poses):
        q = geo.quaternion_from_matrix(T)
        lines.append(f"{t:.9f} " + " ".join(f"{v:.9f}" for v in list(T[:3, 3]) + list(q)))
    atomic_write_text(path, "\n".join(lines) + "\n", keep_backup=False)


def read_tum_poses(path: str):
    """(stamps (N,), poses (N, 4, 4)) of a 6-DOF TUM file."""
    from aruco_ring_localization import geometry as geo

    rows = np.loadtxt(path, comments="#", ndmin=2)
    poses = np.array([geo.transform_from_translation_quaternion(r[1:4], r[4:8]) for r in rows])
    return rows[:, 0], poses


def ring_frames(bag_path: str, ring, ignore: str = "", remap: Optional[Callable[[int, float], int]] = None,
                slop: float = 0.005) -> list:
    """The ring frames of a bag of detections as the bag source hands them to build-map's pipeline.

    The mapper's input settings offline: the ring file's extrinsics and (without camera_info in the
    bag) intrinsics, stamps grouped within ``slop`` (TagSLAM's rigs are hardware-synchronized: a few
    ms), ``ignore`` ids dropped (aruco_detect syntax); ``remap`` (id, stamp) -> id is TagSLAM's
    ``tag_id_remap``, applied to the detections before they enter the pipeline.
    """
    from aruco_ring_localization.config import with_overrides
    from aruco_ring_localization.detections import MarkerObservation
    from aruco_ring_localization.pipeline import MappingPipeline
    from aruco_ring_localization.ros.bag_source import BagSource
    from aruco_ring_localization.schemas import MapperConfig

    class _Recorder(MappingPipeline):
        """The mapper's pipeline, keeping the ring frames it adds (and remapping ids first)."""

        def __init__(self, config, ring_):
            super().__init__(config, ring_)
            self.recorded: list = []

        def on_detections(self, camera, stamp, observations, now):
            if remap is not None:
                observations = [MarkerObservation(remap(o.marker_id, stamp), o.corners) for o in observations]
            return super().on_detections(camera, stamp, observations, now)

        def _add(self, frames):
            self.recorded.extend(frames)
            return len(frames)

    config = with_overrides(MapperConfig(), {"input.use_tf": False, "input.camera_info_fallback": True,
                                             "input.slop": slop, "input.timeout": max(4 * slop, 0.1),
                                             "input.ignore_fiducials": ignore})
    pipeline = _Recorder(config, ring)
    with BagSource(bag_path, ring, progress=False, out=_NullOut()) as source:
        source.run(pipeline, command="tagslam_reference")
    return pipeline.recorded


class _NullOut:
    """The bag source's summary lines, to the debug log."""

    def write(self, text: str) -> None:
        if text.strip():
            import logging

            logging.getLogger(__name__).debug(text.rstrip())

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False


def load_test(test: str):
    """(source directory, rig body name, :class:`importers.TagslamTags`, :class:`Reference`) of ``test``."""
    import yaml

    from aruco_ring_localization.importers import read_tagslam_tags

    src = os.path.join(DATA, test)
    with open(os.path.join(src, "cameras.yaml"), encoding="utf-8") as fh:
        cams = yaml.safe_load(fh)
    rig_body = next(iter(cams.values())).get("rig_body", "rig")
    tags = read_tagslam_tags(os.path.join(src, "tagslam.yaml"), rig_bodies=(rig_body,))
    return src, rig_body, tags, load_reference(cached_bag(test, "reference"), rig_body, tags.static_bodies)


def write_camera_poses(ref: Reference, path: str, header: str = "") -> str:
    """TagSLAM's camera poses of ``ref`` as a TagSLAM ``camera_poses.yaml`` (what the importer reads)."""
    import yaml

    from aruco_ring_localization import geometry as geo

    poses = {}
    for cam, T in sorted(ref.cameras.items()):
        r, t = geo.rvec_tvec_from_transform(T)
        poses[cam] = {"pose": {"position": dict(zip("xyz", map(float, t))), "rotation": dict(zip("xyz", map(float, r)))}}
    with open(path, "w", encoding="utf-8") as fh:
        if header:
            fh.write(f"# {header}\n")
        yaml.safe_dump(poses, fh, sort_keys=True)
    return path


def export_test_data(test: str, out_dir: str, every: int = 1, max_frames: int = 0,
                     start: Optional[float] = None, stop: Optional[float] = None,
                     odometry: bool = False) -> List[str]:
    """Copy what a unit test needs of ``test`` into ``out_dir`` (small, self-contained).

    Files: ``cameras.yaml`` and ``tagslam.yaml`` (as published), ``camera_poses.yaml`` (TagSLAM's
    optimized camera poses, in TagSLAM's format), ``tags.yaml`` (TagSLAM's tag poses as a marker
    map), ``rig_poses.tum`` (its rig poses) and ``tag_detections.bag`` (every ``every``-th frame,
    at most ``max_frames``, bz2-compressed chunks: rosbag reads it directly); ``start`` / ``stop``
    (s, the detections' stamps): only the frames in that window. ``odometry``: the bag also holds
    the rig body's odometry (tagslam.yaml's ``odom_topic``, unchanged messages) from 0.5 s before the
    first kept frame to 0.5 s after the last.
    """
    import rosbag
    import yaml

    from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap

    src, _, tags, ref = load_test(test)
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(src, "cameras.yaml"), encoding="utf-8") as fh:
        cams = yaml.safe_load(fh)
    written = []
    for name in ("cameras.yaml", "tagslam.yaml"):
        shutil.copyfile(os.path.join(src, name), os.path.join(out_dir, name))
        written.append(name)
    write_camera_poses(ref, os.path.join(out_dir, "camera_poses.yaml"),
                       f"TagSLAM's optimized camera poses of {test} (reference.bag, rig -> camK)")
    sizes = tags.marker_sizes()
    m = MarkerMap([MarkerEntry(i, T, sizes(i)) for i, T in sorted(ref.tags.items())], frame_id="map",
                  method=f"TagSLAM ({test} reference.bag)", frame_definition="TagSLAM's map frame")
    m.save(os.path.join(out_dir, "tags.yaml"))
    topics = ["/" + str(c.get("tagtopic", "")).lstrip("/") for c in cams.values()]
    kept_stamps = set()
    with rosbag.Bag(cached_bag(test, "tag_detections")) as bag, \
            rosbag.Bag(os.path.join(out_dir, "tag_detections.bag"), "w", compression="bz2") as out:
        stamps = sorted({msg.header.stamp.to_nsec() for _, msg, _ in bag.read_messages(topics=topics)})
        stamps = [x for x in stamps if (start is None or x >= start * 1e9) and (stop is None or x <= stop * 1e9)]
        keep = stamps[::every][: max_frames or None]
        kept_stamps = set(keep)
        for topic, msg, t in bag.read_messages(topics=topics):
            if msg.header.stamp.to_nsec() in kept_stamps:
                out.write(topic, msg, t)
        if odometry and keep:
            from aruco_ring_localization.importers.tagslam import tagslam_odometry

            found = tagslam_odometry(os.path.join(src, "tagslam.yaml"), ref.rig_body)
            if found is None:
                raise ValueError(f"{test}: its rig body has no odom_topic")
            lo, hi = keep[0] - 0.5e9, keep[-1] + 0.5e9
            for topic, msg, t in bag.read_messages(topics=[found.topic]):
                if lo <= msg.header.stamp.to_nsec() <= hi:
                    out.write(topic, msg, t)
    sel = [k for k, s in enumerate(ref.stamps) if int(round(s * 1e9)) in kept_stamps or
           min(abs(int(round(s * 1e9)) - x) for x in kept_stamps) < 1000]
    write_tum_poses(os.path.join(out_dir, "rig_poses.tum"), ref.stamps[sel], ref.T_map_rig[sel],
                    header=f"TagSLAM's rig poses T_map_rig of {test} (reference.bag)")
    written += ["camera_poses.yaml", "tags.yaml", "tag_detections.bag", "rig_poses.tum"]
    return written
