"""``aruco_ring export-tum``: a reference trajectory of a bag (a pose topic or a tf chain) as a TUM file.

For ``aruco_ring evaluate``: the simulator's ``sim/ground_truth`` (PoseStamped), gmapping's pose
as tf (``--tf map base_link``), a robot_localization or amcl output (Odometry,
PoseWithCovarianceStamped). Read through ``ros/bag_source.py`` (:func:`read_reference`).
"""
from __future__ import annotations

import argparse
import sys

from ..evaluation.trajectories import tum_text, trajectory, write_tum

COMMAND = "export-tum"
HELP = "write a pose topic (PoseStamped, PoseWithCovarianceStamped, Odometry) or a tf chain of a bag as TUM"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="the bag file")
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--topic", help="a geometry_msgs/PoseStamped, PoseWithCovarianceStamped or nav_msgs/Odometry "
                                      "topic: one pose per message, at its header stamp")
    what.add_argument("--tf", nargs=2, metavar=("PARENT", "CHILD"),
                      help="the tf chain PARENT -> CHILD (/tf and /tf_static), at each /tf stamp on the way, "
                           "e.g. --tf map base_link for gmapping's robot pose")
    parser.add_argument("--out", default="-", help="TUM file to write (atomically); '-': standard output (default)")
    parser.add_argument("--progress", action="store_true", help="progress bar on stderr even when it is not a terminal")


def run(args: argparse.Namespace) -> int:
    from ..ros.bag_source import read_reference   # rosbag only when the command runs

    stamps, poses, what = read_reference(args.bag, topic=args.topic, tf=tuple(args.tf) if args.tf else None,
                                         progress=args.progress or None)
    traj = trajectory(stamps, poses)
    header = f"aruco_ring export-tum {args.bag}: {what}\nt x y z qx qy qz qw"
    if args.out == "-":
        sys.stdout.write(tum_text(traj, header))
    else:
        write_tum(args.out, traj, header)
    sys.stderr.write(f"export-tum: {what}, {stamps[-1] - stamps[0]:.1f} s"
                     f"{'' if args.out == '-' else ' -> ' + args.out}\n")
    return 0
