"""``aruco_ring detect IMAGE --camera-info FILE``: run the detector node's detection on an image file.

Prints, per marker, the id, the 4 corners (aruco_detect order, raw pixels) and the pose of the
marker in the camera's optical frame (``T_camera_marker``) with aruco_detect's quality figures;
with ``--json``, one object::

    {"markers": [{"id": 1, "corners": [[x0, y0], [x1, y1], [x2, y2], [x3, y3]],
                  "T_camera_marker": [[...4 numbers...], x4 rows], "image_error": ...,
                  "object_error": ..., "fiducial_area": ...}, ...]}

Exit codes: 0 success (also when no marker is found), 1 unreadable image, bad camera_info or a bad
option (message on stderr naming the file or option).
"""
from __future__ import annotations

import argparse
import json
import sys

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import default
from ..detection import Detector, DetectorParams, CORNER_REFINEMENT, dictionary_name, image_to_gray, marker_poses
from ..errors import ArucoRingError
from ..markers import MarkerSizes
from ..schemas import DetectorConfig

COMMAND = "detect"
HELP = "detect ArUco markers in an image file (ids, corners, marker poses)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("image", help="image file (PNG, JPEG, ...; colour images are converted to grey)")
    parser.add_argument("--camera-info", required=True,
                        help="camera intrinsics YAML (camera_calibration_parsers format, e.g. config/camera_info/cam0.yaml)")
    parser.add_argument("--dictionary", type=int, default=default(DetectorConfig, "dictionary"),
                        help="OpenCV predefined dictionary index (default %(default)s = DICT_5X5_1000)")
    parser.add_argument("--fiducial-len", type=float, default=default(DetectorConfig, "fiducial_len"),
                        help="marker side (black square), m (default %(default)s, as the detector node)")
    parser.add_argument("--fiducial-len-override", default="", help="per-id sides, e.g. '1-10: 0.05, 12: 0.06'")
    parser.add_argument("--corner-refinement", default=default(DetectorConfig, "corner_refinement"),
                        choices=sorted(CORNER_REFINEMENT),
                        help="corner refinement (default lines; subpix = aruco_detect's)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def run(args: argparse.Namespace) -> int:
    try:
        model = CameraModel.from_yaml(args.camera_info)
        sizes = MarkerSizes.parse(args.fiducial_len, args.fiducial_len_override)
        detector = Detector(DetectorParams(dictionary=args.dictionary, corner_refinement=args.corner_refinement))
    except (ArucoRingError, OSError) as exc:
        sys.stderr.write(f"detect: {exc}\n")
        return 1
    img = cv2.imread(args.image, cv2.IMREAD_COLOR)
    if img is None:
        sys.stderr.write(f"detect: {args.image}: cannot read the image (missing file or unknown format)\n")
        return 1
    # the same path as the node: decoded to BGR, then grey (as aruco_detect's cv_bridge)
    gray = image_to_gray("bgr8", img.shape[1], img.shape[0], img.strides[0], img.tobytes())
    if (model.width, model.height) != (gray.shape[1], gray.shape[0]):
        sys.stderr.write(f"detect: warning: image is {gray.shape[1]}x{gray.shape[0]} but {args.camera_info} is for "
                         f"{model.width}x{model.height}: poses are wrong\n")
    observations = detector.detect(gray)
    poses = {p.marker_id: p for p in marker_poses(observations, model, sizes)}
    markers = []
    for obs in observations:
        entry = {"id": int(obs.marker_id), "corners": [[float(x), float(y)] for x, y in obs.corners]}
        p = poses.get(obs.marker_id)
        if p is not None:
            entry["T_camera_marker"] = [[float(v) for v in row] for row in p.T_cam_marker]
            entry["image_error"] = float(p.image_error)
            entry["object_error"] = float(p.object_error)
            entry["fiducial_area"] = float(p.fiducial_area)
        markers.append(entry)
    if args.json:
        sys.stdout.write(json.dumps({"markers": markers}) + "\n")
        return 0
    sys.stdout.write(f"{args.image}: {len(markers)} marker(s), {dictionary_name(args.dictionary)}, "
                     f"corner refinement {args.corner_refinement}\n")
    for m in markers:
        corners = " ".join(f"({x:.2f}, {y:.2f})" for x, y in m["corners"])
        sys.stdout.write(f"  id {m['id']:4d}  corners {corners}\n")
        if "T_camera_marker" in m:
            T = np.array(m["T_camera_marker"])
            t = T[:3, 3]
            sys.stdout.write(f"           t_camera_marker ({t[0]:+.4f}, {t[1]:+.4f}, {t[2]:+.4f}) m, distance "
                             f"{np.linalg.norm(t):.4f} m, image_error {m['image_error']:.4f} px^2, "
                             f"object_error {m['object_error']:.2e}, fiducial_area {m['fiducial_area']:.0f} px^2\n")
        else:
            sys.stdout.write("           no pose (degenerate corners)\n")
    return 0
