"""Per-camera detections -> ring frames, without ROS: the logic behind ``ros/ring_input.py``.

:class:`RingInputCore` takes each camera's detections as they arrive (camera name, stamp,
observations), checks that the camera is usable (intrinsics known, extrinsics known), drops
malformed detections (:func:`frames.sanitize_observations`: NaN corners, degenerate quads,
duplicate ids in one image, ignored ids) and feeds a :class:`frames.RingFrameAssembler`, which
groups the cameras by stamp and lets a group go out after a timeout when a camera is silent.

Intrinsics: the latest ``camera_info`` of each camera (:meth:`set_camera_model`); a camera with
none yet is skipped, unless ``camera_info_fallback`` is set, in which case the ring file's model is
used. Extrinsics: ``T_base_cam`` set once per camera (:meth:`set_extrinsics`, from tf in the ROS
adapter) or, with ``extrinsics_from_ring``, the ring file's. :attr:`ring` is the ring with the
extrinsics in force; each emitted :class:`frames.CameraFrame` carries its camera's model.
"""
from __future__ import annotations

import logging
from typing import Collection, Dict, List, Optional, Sequence, Tuple

import numpy as np

from . import geometry as geo
from .camera import CameraModel
from .frames import CameraFrame, MarkerObservation, RingFrame, RingFrameAssembler, sanitize_observations
from .rig import CameraRing

logger = logging.getLogger(__name__)

#: Reasons a whole camera frame is skipped (keys of :attr:`RingInputCore.skipped`).
SKIP_NO_CAMERA_INFO = "no camera_info"
SKIP_NO_EXTRINSICS = "no extrinsics"


class RingInputCore:
    """Assemble ring frames from per-camera detections.

    Args:
        ring: the calibrated ring (names, frames, fallback intrinsics and extrinsics).
        camera_names: ring camera names to use (default: all of the ring's).
        slop: stamps within this (s) belong to one ring frame.
        timeout: an incomplete group goes out this long (s, caller's clock) after its first member.
        ignore_ids: marker ids never passed on.
        camera_info_fallback: use the ring file's intrinsics while no camera_info has arrived.
        extrinsics_from_ring: use the ring file's extrinsics instead of waiting for
            :meth:`set_extrinsics`.
    """

    def __init__(self, ring: CameraRing, camera_names: Optional[Sequence[str]] = None, slop: float = 0.03,
                 timeout: float = 0.25, ignore_ids: Collection[int] = (), camera_info_fallback: bool = False,
                 extrinsics_from_ring: bool = False):
        names = list(camera_names) if camera_names else ring.names
        unknown = [n for n in names if n not in ring.names]
        if unknown:
            raise ValueError(f"cameras {unknown} are not in the ring (known: {ring.names})")
        self.calibrated_ring = ring
        self.camera_names = names
        self.ignore_ids = frozenset(int(i) for i in ignore_ids)
        self.camera_info_fallback = bool(camera_info_fallback)
        self.extrinsics_from_ring = bool(extrinsics_from_ring)
        self.assembler = RingFrameAssembler(names, slop=slop, timeout=timeout)
        self._models: Dict[str, CameraModel] = {}
        self._extrinsics: Dict[str, np.ndarray] = (
            {n: ring[n].T_base_cam for n in names} if extrinsics_from_ring else {})
        self._ring = ring
        #: camera -> {reason: count} of detections dropped by sanitize_observations.
        self.rejected: Dict[str, Dict[str, int]] = {n: {} for n in names}
        #: camera -> {reason: count} of whole camera frames skipped (no camera_info / no extrinsics).
        self.skipped: Dict[str, Dict[str, int]] = {n: {} for n in names}
        self.frames_in = 0
        self.ring_frames_out = 0

    # --- calibration in force ---------------------------------------------------------------

    def set_camera_model(self, camera: str, model: CameraModel) -> None:
        """The intrinsics from this camera's latest camera_info."""
        self._models[camera] = model

    def camera_model(self, camera: str) -> Optional[CameraModel]:
        """Intrinsics in force for ``camera`` (camera_info, or the ring's with the fallback), or None."""
        model = self._models.get(camera)
        if model is None and self.camera_info_fallback:
            model = self.calibrated_ring[camera].model
        return model

    def set_extrinsics(self, camera: str, T_base_cam: np.ndarray) -> None:
        """``T_base_cam`` (4x4) of ``camera`` (from tf); updates :attr:`ring`."""
        T = geo.validate_transform(T_base_cam, f"extrinsics of {camera}")
        self._extrinsics[camera] = T
        self._ring = self.calibrated_ring.with_extrinsics(self._extrinsics)

    def has_extrinsics(self, camera: str) -> bool:
        return camera in self._extrinsics

    @property
    def ring(self) -> CameraRing:
        """The ring with the extrinsics in force (tf's where known, the file's for the others)."""
        return self._ring

    # --- data -------------------------------------------------------------------------------

    def add_detections(self, camera: str, stamp: float, observations: Sequence[MarkerObservation],
                       now: float) -> Tuple[List[RingFrame], Optional[str], Dict[str, int]]:
        """Take one camera's detections at ``stamp`` (s); ``now`` is the caller's clock (s).

        Returns:
            (ring frames ready to go out, the reason the camera frame was skipped or None,
            counts of the detections dropped in this frame by reason).
        """
        self.frames_in += 1
        if camera not in self.skipped:
            return self.poll(now), f"unknown camera {camera}", {}
        model = self.camera_model(camera)
        reason = None
        if model is None:
            reason = SKIP_NO_CAMERA_INFO
        elif camera not in self._extrinsics:
            reason = SKIP_NO_EXTRINSICS
        if reason is not None:
            self.skipped[camera][reason] = self.skipped[camera].get(reason, 0) + 1
            return self.poll(now), reason, {}
        kept, dropped = sanitize_observations(observations, self.ignore_ids, model.width, model.height)
        for k, v in dropped.items():
            self.rejected[camera][k] = self.rejected[camera].get(k, 0) + v
        out = self.assembler.add(CameraFrame(camera, float(stamp), kept, model), now)
        self.ring_frames_out += len(out)
        return out, None, dropped

    def poll(self, now: float) -> List[RingFrame]:
        """Ring frames whose timeout has expired (call periodically)."""
        out = self.assembler.poll(now)
        self.ring_frames_out += len(out)
        return out

    def silent_cameras(self, now: float, silence: float = 1.0) -> List[str]:
        """Cameras from which nothing usable has arrived for ``silence`` s (or ever)."""
        return self.assembler.silent_cameras(now, silence)
