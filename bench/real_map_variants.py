"""Which of the package's mapping settings move a real recording's map? (issue 11, diagnostic)

Maps one recording as ``bench/bench_real.py`` does (TagSLAM's extrinsics and camera priors, its
anchors, measurements, boards and odometry; its pixel_noise with a survey), once per variant of the
mapping options, and prints each map's RMS against TagSLAM's tags and, when
``bench/real_objective.py --save`` (or ``bench/real_board_model.py --objective``) has written it,
against the minimum of TagSLAM's stated problem (``results/bench/real/<test>/objective_min.yaml``).
Nothing is saved: the sanity checks' verdict is printed.

A variant is ``name:key=value,...`` with ``MappingOptions`` keys, ``ba.<key>`` for the adjustment's
(``BAOptions``); the base options are bench_real's (every moving frame a station, tagslam.yaml's
odometry noise judged at the frames: ``message_sampling: frames``, TagSLAM's synchronizer; no robust
loss on the corners, bench_real's ``BA_LOSS``: ``ba.loss='huber'`` for the package's default; every
detection kept and every frame a station: ``max_reprojection_px=3,still_px=1.5`` for the package's);
``ODOM=package`` in the environment takes the package's odometry noise instead (bench_real
``--odom-noise package``); ``odo.<key>`` sets a key of the odometry links'
(``MappingOdometryOptions``, recordings with odometry only).

Usage: ``python bench/real_map_variants.py test_10 default: "huber:ba.loss='huber'"
"thinned:min_station_motion_px=10"``.
"""
from __future__ import annotations

import ast
import dataclasses
import os
import sys
import time
from typing import Any, Dict, Optional, Sequence, Tuple

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
sys.path.insert(0, HERE)

import bench_real  # noqa: E402
from aruco_ring_localization.evaluation.maps import map_error  # noqa: E402
from aruco_ring_localization.importers import tagslam_boards  # noqa: E402
from aruco_ring_localization.importers.tagslam import tagslam_anchors, tagslam_measurements  # noqa: E402
from aruco_ring_localization.mapping import MapBuilder, MappingOptions  # noqa: E402
from aruco_ring_localization.marker_map import MarkerMap, check_map  # noqa: E402


def _value(text: str) -> Any:
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


@dataclasses.dataclass
class Case:
    """One recording loaded as bench_real maps it: its inputs and TagSLAM's answer."""

    test: str
    out_dir: str
    src: str
    tags: Any
    ref: Any
    ring: Any
    sizes: Any
    frames: list
    truth: MarkerMap
    survey: Any
    meas: Any
    odo_opts: Any
    odo: Any
    layout: Any


def load_case(test: str) -> Case:
    """``test`` loaded with bench_real's options (``ODOM=package`` in the environment: the package's
    odometry noise)."""
    bench_real.ODOM_NOISE = os.environ.get("ODOM", bench_real.ODOM_NOISE)
    out_dir, src, tags, ref, ring, sizes, ignore, frames, truth = bench_real._load_case(test)
    yaml_path = os.path.join(src, "tagslam.yaml")
    survey = tagslam_anchors(tags, ignore, yaml_path)
    meas = tagslam_measurements(yaml_path, ignore)
    if meas is not None and survey is None:
        meas.planes = []
    odo_opts, odo = bench_real._odometry(test, src, ref.rig_body, frames)
    layout = tagslam_boards(yaml_path, rig_bodies=(ref.rig_body,))
    return Case(test, out_dir, src, tags, ref, ring, sizes, frames, truth, survey, meas, odo_opts, odo, layout)


def build_variant(case: Case, spec: str) -> Tuple[MapBuilder, MarkerMap, MarkerMap, Dict[str, Any]]:
    """Map ``case`` with the options of a variant's ``spec`` (``key=value,...``: see the module's
    doc): (the builder, the map, its detected markers, their error against TagSLAM's tags)."""
    kw: Dict[str, Any] = {}
    ba: Dict[str, Any] = {}
    odo_kw: Dict[str, Any] = {}
    for item in filter(None, spec.split(",")):
        key, _, val = item.partition("=")
        if key.startswith("odo."):
            odo_kw[key[4:]] = _value(val)
        elif key.startswith("ba."):
            ba[key[3:]] = _value(val)
        else:
            kw[key] = _value(val)
    options = MappingOptions(frame="marker", min_station_motion_px=bench_real.STATION_MOTION_PX)
    options = dataclasses.replace(options, ba=dataclasses.replace(options.ba, loss=bench_real.BA_LOSS),
                                  max_reprojection_px=bench_real.MAX_REPROJECTION_PX, still_px=bench_real.STILL_PX)
    if case.odo_opts is not None:
        options = dataclasses.replace(options, odometry=dataclasses.replace(case.odo_opts, **odo_kw))
    if (case.survey is not None or case.meas is not None) and case.tags.pixel_noise:
        ba.setdefault("pixel_noise", case.tags.pixel_noise)
    options = dataclasses.replace(options, ba=dataclasses.replace(options.ba, **ba), extrinsics_prior="ring", **kw)
    layout = case.layout if case.layout is not None and len(case.layout) else None
    b = MapBuilder(bench_real.mapping_ring(case.ring, case.src, options), case.sizes, options=options,
                   anchors=case.survey, boards=layout, measurements=case.meas)
    if case.odo:
        b.set_odometry(*case.odo)
    for f in case.frames:
        b.add_frame(f)
    m = b.build()
    det = MarkerMap([e for e in m if not e.surveyed_only], frame_id=m.frame_id)
    return b, m, det, map_error(det, case.truth, best_fit=True)


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) < 2:
        raise SystemExit(__doc__)
    case = load_case(args[0])
    minimum = os.path.join(case.out_dir, "objective_min.yaml")
    for variant in args[1:]:
        name, _, spec = variant.partition(":")
        t0 = time.process_time()
        b, m, det, err = build_variant(case, spec)
        line = (f"{case.test} {name}: map RMS {err['position_rms_mm']:.2f} / max {err['position_max_mm']:.2f} mm vs "
                f"TagSLAM's, stations {b.summary()['stations']}")
        if os.path.exists(minimum):
            line += f", {map_error(det, MarkerMap.load(minimum), best_fit=True)['position_rms_mm']:.2f} mm vs the minimum"
        problems = check_map(m, b.options.sanity)
        verdict = f"save refused ({'; '.join(sorted({p.split(':')[0] for p in problems}))})" if problems else "saves"
        print(f"{line}; {verdict}; {time.process_time() - t0:.0f} s CPU", flush=True)
    return 0

if __name__ == "__main__":
    sys.exit(main())
