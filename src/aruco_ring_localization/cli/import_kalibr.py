"""``aruco_ring import-kalibr``: a Kalibr camchain or TagSLAM's cameras.yaml -> ring.yaml + camera_info/.

Reads the intrinsics (``intrinsics [fx, fy, cx, cy]``, ``distortion_model`` radtan / equidistant /
plumb_bob / rational_polynomial / none, ``resolution``) and the camera poses (TagSLAM
``camera_poses.yaml``, Kalibr ``T_cam_imu`` or ``T_cn_cnm1``), writes one camera_info file per
camera and the ring file (docs/formats.md, "Importers"). A camera without a pose is an error
naming it. With ``--tagslam tagslam.yaml`` it also prints the marker sizes and ignored ids in
aruco_detect's ``fiducial_len`` / ``fiducial_len_override`` / ``ignore_fiducials`` syntax, and with
``--anchors-out FILE`` writes the tag poses it fixes (surveyed) as an anchors file for
``build-map --anchors`` (:func:`importers.tagslam_anchors`: full poses with TagSLAM's noise).
TagSLAM's ``wiggle_rotation`` / ``wiggle_translation`` go to the ring file as each camera's
``wiggle`` (a note says so: ``calibrate-ring`` then calibrates the fixed pose each wiggles about).
"""
from __future__ import annotations

import argparse
import sys

from ..anchors import anchors_yaml
from ..fileio import atomic_write_text
from ..importers import read_rig, read_tagslam_tags, tagslam_anchors, write_ring_files
from ..ring import ring_summary

COMMAND = "import-kalibr"
HELP = "convert a Kalibr camchain (or TagSLAM cameras.yaml + camera_poses.yaml) to ring.yaml + camera_info/"
DESCRIPTION = __doc__.split("\n\n")[1] if __doc__ else HELP


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("camchain", help="Kalibr camchain.yaml / camchain-imucam.yaml, or TagSLAM cameras.yaml")
    parser.add_argument("--out", required=True, help="ring YAML to write (atomically)")
    parser.add_argument("--camera-poses", default=None,
                        help="TagSLAM camera_poses.yaml (default: the one beside CAMCHAIN, if any)")
    parser.add_argument("--camera-info-dir", default=None,
                        help="directory of the camera_info files (default: camera_info/ beside --out)")
    parser.add_argument("--base-frame", default="rig", help="name of the rig's base frame in the ring file")
    parser.add_argument("--tagslam", default=None, help="tagslam.yaml: print its tag sizes and ignored tags")
    parser.add_argument("--anchors-out", default=None, metavar="FILE",
                        help="with --tagslam: write the tag poses tagslam.yaml fixes as an anchors file (build-map "
                             "--anchors), full poses with TagSLAM's noise")


def run(args: argparse.Namespace) -> int:
    if args.anchors_out and not args.tagslam:
        sys.stderr.write("import-kalibr: --anchors-out needs --tagslam tagslam.yaml (the tag poses it fixes)\n")
        return 2
    rig = read_rig(args.camchain, camera_poses=args.camera_poses, base_frame=args.base_frame)
    ring = rig.ring()
    files = write_ring_files(ring, args.out, args.camera_info_dir)
    out = sys.stdout
    out.write(f"imported {len(ring)} cameras from {rig.source}\n")
    for c in rig.cameras:
        out.write(f"  {c.name}: pose from {c.pose_source}, topics under /{c.namespace}\n")
    out.write("\n".join(ring_summary(ring)) + "\n")
    out.write(f"base frame '{ring.base_frame}' = {rig.base_definition}. This is the rig's frame, not a ground "
              f"robot's base_link with z up: map with frame 'marker' (the mapper drops its planar prior by "
              f"itself when the rig tilts), or put the rig's mounting into the extrinsics (docs/real_robot.md, "
              f"section 8).\n")
    for note in rig.notes:
        out.write(f"note: {note}\n")
    out.write("wrote " + ", ".join(files) + "\n")
    if args.tagslam:
        tags = read_tagslam_tags(args.tagslam)
        out.write(f"{args.tagslam}: fiducial_len {tags.default_size:g}\n"
                  f"  fiducial_len_override \"{tags.fiducial_len_override()}\"\n"
                  f"  ignore_fiducials \"{tags.ignore_fiducials()}\"   (TagSLAM's ignore_tags and the tags of moving "
                  f"bodies {', '.join(tags.moving_bodies) or '-'}"
                  f"{'; no default_body: every tag no body lists, as TagSLAM ignores them' if tags.undeclared_ignored else ''})\n")
        if args.anchors_out:
            anchors = tagslam_anchors(tags, tags.ignore | tags.moving, source=args.tagslam)
            if anchors is None:
                sys.stderr.write(f"import-kalibr: {args.tagslam} fixes no tag pose on a static body: no anchors "
                                 f"written to {args.anchors_out}\n")
                return 1
            atomic_write_text(args.anchors_out, anchors_yaml(anchors, f"TagSLAM's known tag poses of {args.tagslam} "
                                                                      f"(full poses, TagSLAM's noise)"),
                              keep_backup=False)
            out.write(f"wrote {args.anchors_out}: {len(anchors.anchors)} anchored tags (build-map --anchors)\n")
    return 0
