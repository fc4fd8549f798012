"""Is the gap to TagSLAM's camera poses its per-frame "wiggle"? A re-enactment of its camera model.

The model itself is the package's (``calibrate-ring``'s wiggle stage: :func:`ring_calibration.wiggle_adjust`,
:func:`ring_calibration.solve_wiggle`); this script measures its walk against TagSLAM's poses.
TagSLAM's cameras.yaml of tests 5 and 6 gives every camera ``wiggle_rotation: 0.01`` (rad) and
``wiggle_translation: 0.01`` (m): each frame gets its own camera pose, tied to the camera's nominal
pose (the one in reference.bag) by a prior with those sigmas, with a corner noise of 1 px and no
robust loss. This script poses that model on our observations (:func:`wiggle_fit`): one camera pose
per (frame, camera) with a prior around a nominal ring, markers and rig poses free; and finds the
model's nominal ring by alternating (the adjustment with the priors around the nominal, then each
camera's nominal the mean of its per-frame poses: block coordinate descent on the joint problem, whose
nominal optimum given the per-frame poses is their mean). Started from our rigid calibration, does
it walk towards TagSLAM's camera poses?

Run: ``python bench/calibration_real_wiggle.py test_6 [frames] [rounds] [relax]`` (prints JSON).
"""
from __future__ import annotations

import os
import sys
import time
from typing import Dict, List, Sequence

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
sys.path.insert(0, HERE)

from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization.ring_calibration import CalibrationOptions, solve_wiggle, wiggle_adjust  # noqa: E402


def wiggle_fit(cal, nominal: Sequence[np.ndarray], rot_sigma: float = 0.01, trans_sigma: float = 0.01,
               pixel_noise: float = 1.0, max_nfev: int = 60) -> Dict[str, object]:
    """TagSLAM's wiggle model on the calibration's observations around the ``nominal`` ring, every
    camera wiggling (:func:`ring_calibration.wiggle_adjust`, the package's wiggle stage)."""
    return wiggle_adjust(cal.ba, cal.ba.problem, nominal, [True] * len(nominal), rot_sigma, trans_sigma,
                         pixel_noise=pixel_noise, loss="linear", max_nfev=max_nfev)


def rel_errors(a: Sequence[np.ndarray], b: Sequence[np.ndarray]) -> List[tuple]:
    """(mm, deg) of ``T_cam0_camk`` in ``a`` against ``b``, k = 1..C-1."""
    out = []
    for k in range(1, len(a)):
        d = geo.pose_distance(geo.inverse(a[0]) @ a[k], geo.inverse(b[0]) @ b[k])
        out.append((round(1000 * d[0], 2), round(float(np.degrees(d[1])), 3)))
    return out


def walk(cal, start: Sequence[np.ndarray], tagslam: Sequence[np.ndarray], ours: Sequence[np.ndarray], rounds: int,
         relax: float = 1.0) -> List[Dict[str, object]]:
    """The alternation from ``start`` (:func:`ring_calibration.solve_wiggle`, TagSLAM's 0.01 rad / 0.01 m,
    1 px, no robust loss): per round the wiggle fit's cost and the nominal ring's distance to
    TagSLAM's and to ours (``relax``: :func:`ring_calibration.relaxed_step`)."""
    steps: List[Dict[str, object]] = []

    def measure(_round, nominal, f) -> None:
        steps.append({"cost": round(f["cost"], 1), "cost_corners": round(f["cost_corners"], 1),
                      "cost_priors": round(f["cost_priors"], 1), "rms_px": round(f["rms_px"], 4),
                      "vs_tagslam": rel_errors(nominal, tagslam), "vs_ours": rel_errors(nominal, ours)})

    nominal, _ = solve_wiggle(cal.ba, cal.ba.problem, start, [True] * len(start), 0.01, 0.01, rounds=rounds,
                              relax=relax, pixel_noise=1.0, loss="linear", callback=measure)
    steps.append({"vs_tagslam": rel_errors(nominal, tagslam), "vs_ours": rel_errors(nominal, ours)})
    return steps


if __name__ == "__main__":
    import json
    import logging

    import bench_calibration_real as bcr

    logging.basicConfig(level=logging.WARNING)
    test = sys.argv[1] if len(sys.argv) > 1 else "test_6"
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 150
    rounds = int(sys.argv[3]) if len(sys.argv) > 3 else 4
    relax = float(sys.argv[4]) if len(sys.argv) > 4 else 1.0
    bcr.OUT = os.path.join(bcr.ROOT, "results", "bench", "real_calibration_wiggle")
    c0 = time.process_time()
    r = bcr.calibrate_test(test, max_frames=n, options=CalibrationOptions(wiggle="off"))
    names = r["ring"].names
    tagslam = [r["ring"][c].T_base_cam for c in names]
    ours = list(r["cal"].ba.T_base_cams)
    out = {"test": test, "frames": r["used"], "rigid_errs": r["errs"],
           "relax": relax, "from_ours": walk(r["cal"], ours, tagslam, ours, rounds, relax),
           "from_tagslam": walk(r["cal"], tagslam, tagslam, ours, 2),
           "cpu_s": time.process_time() - c0, "load": os.getloadavg()}
    for k, v in out.items():
        print(k, json.dumps(v, default=float))
