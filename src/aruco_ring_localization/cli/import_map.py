"""``aruco_ring import-map``: fiducial_slam ``map.txt`` <-> our YAML map."""
from __future__ import annotations

import argparse
import sys

from ..marker_map import MarkerMap

COMMAND = "import-map"
HELP = "convert a fiducial_slam map.txt to a YAML marker map (or back with --to-fiducial-slam)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", help="fiducial_slam map.txt (or, with --to-fiducial-slam, a YAML map)")
    parser.add_argument("--out", required=True, help="file to write (atomically)")
    parser.add_argument("--marker-size", type=float, default=None,
                        help="side of every marker, m (required when importing: map.txt has no sizes)")
    parser.add_argument("--frame-id", default="map", help="map frame name of the imported map")
    parser.add_argument("--to-fiducial-slam", action="store_true", help="export a YAML map to map.txt instead")


def run(args: argparse.Namespace) -> int:
    if args.to_fiducial_slam:
        m = MarkerMap.load(args.source)
        m.export_fiducial_slam(args.out)
        sys.stdout.write(f"exported {len(m)} markers to {args.out} (fiducial_slam map.txt; sizes are not "
                         f"part of that format)\n")
        return 0
    if args.marker_size is None or args.marker_size <= 0:
        sys.stderr.write("import-map: --marker-size L (m, > 0) is required: fiducial_slam maps store no sizes\n")
        return 2
    m = MarkerMap.import_fiducial_slam(args.source, args.marker_size, frame_id=args.frame_id)
    m.save(args.out)
    sys.stdout.write(f"imported {len(m)} markers from {args.source} to {args.out}\n")
    return 0
