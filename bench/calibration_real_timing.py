"""Is TagSLAM's per-frame "wiggle" of tests 5 / 6 a time offset between the cameras?

If camera k exposes ``dt_k`` after the frame's stamp (the bags' four detection topics carry the
same header stamp, so an offset would be hidden), it sees the world from the rig's pose at
``t + dt_k``: its pose in the rig frame seems to turn by ``dt_k * omega`` (omega: the rig's
angular velocity) in that frame, on top of its fixed extrinsics. TagSLAM's wiggle model (each
camera its own pose per frame, tied to a nominal pose by 0.01 rad / 0.01 m priors) would absorb
that; a rigid rig averages it out, weighted by where the markers are seen.

This script (``python bench/calibration_real_timing.py test_6 [first_frame] [frames]``) takes a
window of consecutive frames (30 Hz: the rig's angular velocity from neighbouring frames), runs
our calibration on it (:func:`ring_calibration.calibrate_ring`, rough ring as in
bench_calibration_real.py), then the wiggle fit around our answer
(:func:`calibration_real_wiggle.wiggle_fit`), and regresses each camera's per-frame rotation
deviation, less the four cameras' mean in that frame (the rig pose takes the common part), on the
rig's angular velocity: the slope is ``dt_k - mean(dt)`` (ms), and R^2 says how much of the wiggle
a time offset explains. Prints JSON.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import replace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
sys.path.insert(0, HERE)


def main(test: str, first: int, count: int) -> dict:
    import bench_calibration_real as bcr
    from calibration_real_wiggle import wiggle_fit

    from aruco_ring_localization.ring_calibration import CalibrationOptions, calibrate_ring
    from aruco_ring_localization.simulation.calibration_run import rough_ring

    ring, tags, _, frames = bcr.load_case(test, os.path.join(bcr.ROOT, "results", "bench", "real_calibration_timing",
                                                             test))
    names = ring.names
    C = len(names)
    frames = sorted((f for f in frames if f.observation_count() > 0), key=lambda f: f.stamp)[first:first + count]
    c0 = time.process_time()
    cal = calibrate_ring(frames, rough_ring(ring, seed=5), tags.marker_sizes(),
                         options=replace(CalibrationOptions(), max_frames=len(frames)))
    nominal = list(cal.ba.T_base_cams)
    fit = wiggle_fit(cal, nominal)
    # Per (station, camera) pose of the wiggle fit: rebuild the (station, camera) pairs as wiggle_fit does.
    prob = cal.ba.problem
    pairs = np.unique(prob.obs_station * C + prob.obs_camera)
    per = {}
    counters = {k: 0 for k in range(C)}
    for p in pairs:
        k = int(p % C)
        per[(int(p // C), k)] = fit["per_cam"][k][counters[k]]
        counters[k] += 1
    # The rig's angular velocity (rig frame, rad/s) at each station from its neighbours.
    T_s = cal.ba.T_W_stations
    t_s = np.asarray(cal.station_stamps)
    S = len(T_s)
    omega = np.full((S, 3), np.nan)
    for i in range(1, S - 1):
        dt = t_s[i + 1] - t_s[i - 1]
        if 0 < dt <= 0.1:
            omega[i] = Rotation.from_matrix(T_s[i - 1][:3, :3].T @ T_s[i + 1][:3, :3]).as_rotvec() / dt
    # Rotation deviation of each camera from its nominal, in the rig frame, less the frame's mean.
    rows = {k: ([], []) for k in range(C)}
    for i in range(S):
        if not np.all(np.isfinite(omega[i])):
            continue
        devs = {}
        for k in range(C):
            if (i, k) in per:
                d = per[(i, k)][:3, :3] @ nominal[k][:3, :3].T       # in the rig frame
                devs[k] = Rotation.from_matrix(d).as_rotvec()
        if len(devs) < 2:
            continue
        mean = np.mean(list(devs.values()), axis=0)
        for k, v in devs.items():
            rows[k][0].append(v - mean)
            rows[k][1].append(omega[i])
    out = {"test": test, "first": first, "frames": len(frames), "used": cal.frames_used,
           "rms_rigid_px": round(cal.rms_px_after, 4), "rms_wiggle_px": round(fit["rms_px"], 4),
           "omega_deg_s_median": float(np.degrees(np.nanmedian(np.linalg.norm(omega, axis=1)))),
           "cameras": {}}
    for k in range(C):
        y = np.asarray(rows[k][0])
        x = np.asarray(rows[k][1])
        if len(y) < 10:
            continue
        slope = float(np.sum(x * y) / np.sum(x * x))      # one scalar dt per camera, all axes
        res = y - slope * x
        r2 = 1.0 - float(np.sum(res ** 2) / np.sum(y ** 2))
        out["cameras"][names[k]] = {"n": len(y), "dt_rel_ms": round(1000 * slope, 2), "r2": round(r2, 3),
                                    "dev_rms_deg": round(float(np.degrees(np.sqrt(np.mean(np.sum(y ** 2, 1))))), 4)}
    out["cpu_s"] = round(time.process_time() - c0, 1)
    out["load"] = os.getloadavg()
    return out


if __name__ == "__main__":
    import json
    import logging

    logging.basicConfig(level=logging.ERROR)
    t = sys.argv[1] if len(sys.argv) > 1 else "test_6"
    a = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    n = int(sys.argv[3]) if len(sys.argv) > 3 else 200
    print(json.dumps(main(t, a, n), indent=1, default=float))
