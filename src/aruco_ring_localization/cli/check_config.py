"""``aruco_ring check-config``: validate a ring file (and a map) and summarise them for people.

A map also goes through the sanity checks every save applies (:func:`marker_map.check_map`:
finite values, markers inside a hall-sized box, reprojection RMS, refined extrinsics within
their prior, here also against the ring file's calibration, anchors and survey measurements);
a failed check is an error.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from ..anchors import measurement_lines
from ..errors import ConfigError
from ..marker_map import MarkerMap, check_map
from ..ring import CameraRing, ring_summary

COMMAND = "check-config"
HELP = "validate ring/camera_info/map files and print a summary"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ring", required=True, help="ring YAML file (e.g. config/ring.yaml)")
    parser.add_argument("--map", dest="map_file", help="marker map YAML file to check as well")


def run(args: argparse.Namespace) -> int:
    ok = True
    ring = None
    try:
        ring = CameraRing.load(args.ring)
        sys.stdout.write(f"ring {args.ring}: OK\n" + "\n".join(ring_summary(ring)) + "\n")
    except ConfigError as exc:
        sys.stdout.write(f"ring: ERROR {exc}\n")
        ok = False
    if args.map_file:
        try:
            m = MarkerMap.load(args.map_file)
            problems = check_map(m, ring=ring if ring is not None and ring.base_frame == m.ring_base_frame else None)
            survey = m.quality.get("survey_measurements")
            status = "OK" if not problems else "ERROR (fails its sanity checks)"
            frame = (f"surveyed frame ({m.anchors.get('kind')}, anchors of {m.anchors.get('source')})"
                     if m.anchors is not None else f"reference marker {m.reference_marker}")
            sys.stdout.write(f"map {args.map_file}: {status}, {len(m)} markers in frame '{m.frame_id}', "
                             f"{frame}, method '{m.method}', frame convention "
                             f"'{m.frame_convention or 'not recorded'}'\n")
            for p in problems:
                sys.stdout.write(f"  check failed: {p}\n")
            for line in measurement_lines(survey):
                sys.stdout.write(f"  {line}\n")
            ok = ok and not problems
            ambiguous = [e.marker_id for e in m if e.ambiguous]
            if ambiguous:
                sys.stdout.write(f"  orientation ambiguous (one viewpoint; better IPPE solution kept): {ambiguous}\n")
            if m.surveyed_only_ids:
                sys.stdout.write(f"  surveyed only (never detected while mapping: the survey's pose and std, no "
                                 f"observation behind them): {m.surveyed_only_ids}\n")
            for e in m:
                t = e.T_map_marker[:3, 3]
                sys.stdout.write(f"  marker {e.marker_id:4d} size {e.size:.3f} m at ({t[0]:+.3f}, {t[1]:+.3f}, "
                                 f"{t[2]:+.3f}) m, position std {1000 * float(np.max(e.position_std)):.1f} mm, "
                                 + ("surveyed only\n" if e.surveyed_only else f"{e.observations} observations\n"))
        except ConfigError as exc:
            sys.stdout.write(f"map: ERROR {exc}\n")
            ok = False
    return 0 if ok else 1
