"""Importers: other tools' files -> the package's types (ROS-free).

* :mod:`.rig` — a Kalibr camchain (``camchain.yaml``, ``camchain-imucam.yaml``) or TagSLAM's
  ``cameras.yaml`` + ``camera_poses.yaml`` -> :class:`~aruco_ring_localization.ring.CameraRing`
  (ring file + one camera_info file per camera).
* :mod:`.tagslam` — TagSLAM's ``tagslam.yaml``: tag sizes (``fiducial_len`` /
  ``fiducial_len_override``), ignored tags, the tags whose poses it fixes and its boards.
"""
from __future__ import annotations

from .rig import ImportedCamera, ImportedRig, read_rig, write_ring_files
from .tagslam import TagslamOdometry, TagslamTags, read_tagslam_tags, tagslam_anchors, tagslam_boards, tagslam_odometry, \
    tagslam_pixel_noise

__all__ = ["ImportedCamera", "ImportedRig", "read_rig", "write_ring_files", "TagslamTags", "read_tagslam_tags",
           "tagslam_anchors", "tagslam_boards", "tagslam_odometry", "tagslam_pixel_noise",
           "TagslamOdometry"]
