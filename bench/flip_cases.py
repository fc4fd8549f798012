"""Lab cases where a pose can flip: the single-marker IPPE ambiguity and the joint problem's minima.

Shared by ``bench_localization.py`` (``flips_filtered``) and ``test/unit/test_flips.py``. Each case
is a short seeded sequence of corners-mode ring frames with markers placed on purpose; it runs
through :class:`pipeline.LocalizationPipeline` (the node's: localizer, gate, filter) and counts

* ``filtered_flips``: frames whose filtered (x, y, yaw) is more than 0.5 m or 10 deg from the
  truth (in a case that starts from a wrong pose, from the gate's re-initialisation on --
  ``recovered_at``, the frame it happened -- since nothing can be right before; every frame
  when it never re-initialises);
* ``accepted_flips``: measurements that wrong which the gate let into the filter;
* ``step_excess``: how far (m) the filtered output moved between two frames beyond what the
  gate allowed for that frame (0: it never moved more than the motion model allows).

The cases (each on the lab's pinhole ring and on a seeded equidistant fisheye ring):

* ``far_face_on``: one 0.2 m marker 5 m ahead of cam0, seen face-on, nothing else; from no pose
  and from the true initial pose (both IPPE poses are decimetres off and biased the same way).
* ``two_cameras``: two markers, each seen by one camera only (geometries drawn at random,
  kept where the estimator before this model flipped), robot still, no initial pose.
* ``kidnap``: the track holds a wrong pose -- the mirror image of the truth about the only
  marker's plane, or 3 m beside it -- while the robot sees one marker obliquely (clear in the
  image): a prediction that picks IPPE poses would keep or re-initialise on the flip.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.camera import CameraModel
from aruco_ring_localization.config import with_overrides
from aruco_ring_localization.detections import CameraFrame, MarkerObservation, RingFrame
from aruco_ring_localization.localization import LocalizationParams
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap
from aruco_ring_localization.markers import marker_corners
from aruco_ring_localization.pipeline import LocalizationPipeline, feed_ring_frame
from aruco_ring_localization.ring import CameraRing, RingCamera
from aruco_ring_localization.schemas import LocalizerConfig
from aruco_ring_localization.simulation.scene import marker_pose

SIZE = 0.2            # marker side, m
FLIP_DISTANCE = 0.5   # m
FLIP_ANGLE = np.radians(10.0)
PERIOD = 0.1          # s between ring frames


def observe(ring: CameraRing, markers: Dict[int, np.ndarray], T_map_base: np.ndarray, stamp: float,
            rng: np.random.Generator, noise: float) -> RingFrame:
    """Noisy corners of every marker a camera sees (in front, facing it within 75 deg, inside the image)."""
    frame = RingFrame(stamp=stamp)
    corners = marker_corners(SIZE)
    for cam in ring.cameras:
        T_cam_map = geo.inverse(T_map_base @ cam.T_base_cam)
        obs = []
        for mid, T_map_marker in markers.items():
            T_cm = T_cam_map @ T_map_marker
            pc = geo.transform_points(T_cm, corners)
            c = T_cm[:3, 3]
            if np.any(pc[:, 2] < 0.2) or -(T_cm[:3, 2] @ c) / np.linalg.norm(c) < np.cos(np.radians(75.0)):
                continue
            px = cam.model.project(pc)
            if np.all(cam.model.in_image(px, 3.0)):
                obs.append(MarkerObservation(mid, px + rng.normal(0.0, noise, px.shape)))
        frame.cameras[cam.name] = CameraFrame(cam.name, stamp, obs)
    return frame


def fisheye_ring(ring: CameraRing, seed: int = 0) -> CameraRing:
    """The ring with seeded equidistant (fisheye) intrinsics, about 190 deg across 1280x960."""
    rng = np.random.default_rng(seed)
    cams = []
    for c in ring.cameras:
        f = 330.0 + rng.normal(0.0, 5.0)
        K = np.array([[f, 0.0, 640.0 + rng.normal(0.0, 3.0)], [0.0, f, 480.0 + rng.normal(0.0, 3.0)], [0, 0, 1.0]])
        D = np.array([-0.02, 0.004, -0.001, 0.0002]) + rng.normal(0.0, 1e-4, 4)
        cams.append(RingCamera(c.name, c.frame_id, CameraModel(K, D, "equidistant", 1280, 960, c.name),
                               c.T_base_cam, c.namespace, c.extrinsics_std))
    return CameraRing(cams, ring.base_frame)


@dataclass
class FlipCase:
    name: str
    markers: Dict[int, np.ndarray]
    truth: List[np.ndarray]              # T_map_base per frame
    initial: Optional[Tuple[float, float, float]] = None   # track started here first (x, y, yaw)
    wrong_start: bool = False            # ``initial`` is wrong: count from the re-initialisation on
    noise: float = 0.3


def _path(x: float, y: float, yaw: float, speed: float, n: int) -> List[np.ndarray]:
    return [geo.transform_from_se2(x + speed * PERIOD * k, y, yaw + 0.02 * np.sin(0.3 * k)) for k in range(n)]


def cases() -> List[FlipCase]:
    far = {1: marker_pose([5.0, 0.1, 0.75], np.pi)}
    out = [FlipCase("far_face_on", far, _path(0.0, 0.0, 0.0, 0.05, 60)),
           FlipCase("far_face_on_initialised", far, _path(0.0, 0.0, 0.0, 0.05, 60), initial=(0.0, 0.0, 0.0))]
    two = {"a": [([2.132, -2.811, 1.073], 1.665), ([2.214, 4.351, 0.617], 4.933)],
           "b": [([0.655, -4.303, 0.45], 1.237), ([1.045, 5.011, 0.724], 5.056)],
           "c": [([4.501, 0.289, 1.138], 2.578), ([-3.311, 2.66, 1.097], 6.045)],
           "d": [([4.039, 3.04, 0.524], 4.327), ([-3.809, -2.677, 0.626], 6.923)]}
    for key, spec in two.items():
        mk = {i + 1: marker_pose(p, f) for i, (p, f) in enumerate(spec)}
        out.append(FlipCase(f"two_cameras_{key}", mk, [np.eye(4)] * 20, noise=0.5))
    # One marker at the origin facing +x, seen by cam0 from 1.5 m at 30 deg off its normal: the
    # image tells its two IPPE poses apart (0.2-0.3 against 2-4 px at 0.5 px noise), the mirror
    # pose is 1.5 m away.
    one = {10: marker_pose([0.0, 0.0, 0.75], 0.0)}
    a = np.radians(30.0)
    x, y, yaw = 1.5 * np.cos(a), 1.5 * np.sin(a), np.pi + a
    truth = [geo.transform_from_se2(x, y, yaw)] * 30
    out.append(FlipCase("kidnap_to_mirror", one, truth, initial=(x, -y, -yaw), wrong_start=True, noise=0.5))
    out.append(FlipCase("kidnap_beside", one, truth, initial=(x + 0.5, -y - 2.0, -yaw), wrong_start=True, noise=0.5))
    return out


def _wrong(T: np.ndarray, se2: Sequence[float]) -> bool:
    t = geo.se2_from_transform(T)
    return bool(np.hypot(se2[0] - t[0], se2[1] - t[1]) > FLIP_DISTANCE
                or abs(geo.wrap_angle(se2[2] - t[2])) > FLIP_ANGLE)


def pipeline(ring: CameraRing, marker_map: MarkerMap, params: Optional[LocalizationParams] = None
             ) -> LocalizationPipeline:
    """The node's pipeline (its defaults) on the ring file's calibration, estimator ``params``."""
    config = with_overrides(LocalizerConfig(), {"input.use_tf": False, "input.camera_info_fallback": True})
    return LocalizationPipeline(replace(config, estimator=params or LocalizationParams()), ring, marker_map)


def run_case(case: FlipCase, ring: CameraRing, params: Optional[LocalizationParams] = None, seed: int = 0) -> dict:
    """The case through a fresh pipeline; counts as in the module doc."""
    marker_map = MarkerMap([MarkerEntry(i, T, SIZE) for i, T in case.markers.items()])
    pipe = pipeline(ring, marker_map, params)
    rng = np.random.default_rng(seed)
    if case.initial is not None:
        pipe.on_initial_pose(case.initial, 0.0)
    stats = {"frames": len(case.truth), "outputs": 0, "filtered_flips": 0, "accepted_flips": 0, "ambiguous": 0,
             "step_excess": 0.0, "recovered_at": -1}
    settled = not case.wrong_start
    unsettled_wrong = 0
    last = pipe.filter.pose.copy() if pipe.filter.initialized else None
    for k, T in enumerate(case.truth):
        stamp = PERIOD * (k + 1)
        feed_ring_frame(pipe, observe(ring, case.markers, T, stamp, rng, case.noise))
        out = pipe.last_track
        if out is None or abs(out.stamp - stamp) > 1e-9:
            raise RuntimeError(f"{case.name}: the pipeline tracked no ring frame at {stamp:.1f} s")
        loc = out.localization
        stats["ambiguous"] += int(loc.ambiguous)
        if loc.ok and out.decision is not None and out.decision.accepted and _wrong(T, loc.se2):
            stats["accepted_flips"] += 1
        if not settled and out.decision is not None and out.decision.reason == "reinitialized":
            settled = True
            stats["recovered_at"] = k
        if out.pose is None:
            continue
        stats["outputs"] += 1
        if _wrong(T, out.pose):
            if settled:
                stats["filtered_flips"] += 1
            else:
                unsettled_wrong += 1
        if last is not None and out.decision is not None and out.decision.reason == "accepted":
            step = float(np.hypot(*(out.pose[:2] - last[:2])))
            stats["step_excess"] = max(stats["step_excess"], step - out.decision.allowed_distance)
        last = out.pose.copy()
    if not settled:
        stats["filtered_flips"] += unsettled_wrong
    return stats
