"""Why the joint estimator's per-frame pose differs from TagSLAM's on a real recording (issue 11).

``python bench/real_loc_consistency.py test_8 [--variants] [--max-frames N]``: on TagSLAM's map with TagSLAM's
extrinsics (bench_real's ``--loc-only`` case), every multi-camera frame with a TagSLAM rig pose:

1. **The consistency test** (``estimator/exact_when_consistent``, :func:`localization.extrinsics_consistency`)
   at the exact-extrinsics optimum started from TagSLAM's pose: its F against the
   ``1 - consistency_alpha`` quantile of F(6(C-1), 2N-6C), and how many frames pass.
2. **Where the residual sits**: the squared residuals of that optimum split by nested per-group
   poses (Gauss-Newton reductions, linearised): *within a marker* (what a pose per marker leaves,
   2 dof per marker), *between markers of one camera* (a pose per marker against a pose per camera,
   6(M_c-1) dof), *between cameras* (a pose per camera against the rig pose, 6(C-1) dof), each in
   px RMS per degree of freedom. Pixel noise alone gives the same figure in all three; the test's
   denominator pools the first two, its numerator is the third. With the between-markers part as
   the denominator instead (errors that move a marker's corners together: the map's, a tag's
   detection bias) the same test is counted too.
3. **Leave one camera out** (frames with 3 or more cameras): each estimator's pose from the other
   cameras, scored by the held-out camera's RMS reprojection error through the rigid ring: no
   reference needed, the lower predicts an unseen camera better. TagSLAM's pose (which saw every
   camera) beside it.
4. **The joint estimate against its own covariance**: position error against TagSLAM's pose, the
   stated position std (square root of the trace), and the NEES of the position (chi^2(3): median 2.37).
5. **The window's test** (``estimator/persistence_window``, :class:`localization.CalibrationPersistence`):
   the default joint estimator's correlation rho of each camera's own pose correction between frames
   in which it sees no common marker, after each multi-camera frame: its percentiles, the frames
   solved without the calibration's uncertainty once it cleared it, and the same estimator
   without the window (``persistence_window: 0``) beside it in sections 3 and 4.
6. **The cameras' per-frame jitter measured from the data** (``estimator/estimate_vibration``,
   :class:`localization.VibrationEstimate`): after each multi-camera frame the window's estimate of
   the declared vibration's scale ``kappa^2`` (with its standard error and pairs), the jitter it
   says (``kappa`` times ``extrinsic_jitter_deg``) and the scale the next frames are solved with;
   the estimator with it on (``estimate_vibration: true``; off by default) beside the default in
   sections 3 and 4, whose position NEES against TagSLAM's pose also gives the share of frames
   within chi^2(3)'s 95 % bound (7.81). Sections 5 and 6 run that estimator.

``--variants`` adds estimators with a smaller ``extrinsics_std`` in the ring, without the vibration
term, and with other ``consistency_alpha`` (sections 3 and the error against TagSLAM).
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import Dict, List, Sequence, Tuple

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
sys.path.insert(0, HERE)

import bench_real  # noqa: E402
from aruco_ring_localization import geometry as geo  # noqa: E402
from aruco_ring_localization import localization as L  # noqa: E402
from aruco_ring_localization.detections import RingFrame  # noqa: E402
from aruco_ring_localization.errors import ArucoRingError  # noqa: E402


def _reduction(J: np.ndarray, r: np.ndarray, w: np.ndarray, groups: Sequence[Tuple[int, int]]) -> float:
    """How much a separate 6-DOF pose per group of corners (rows ``[a, b)``) lowers the weighted
    squared residuals (one Gauss-Newton step, linearised)."""
    total = 0.0
    for a, b in groups:
        Jg = J[a:b].reshape(-1, 6)
        rg = r[a:b].reshape(-1)
        wg = np.repeat(w[a:b], 2)
        G = (Jg * wg[:, None]).T @ Jg
        g = (Jg * wg[:, None]).T @ rg
        total += float(g @ np.linalg.pinv(G, hermitian=True) @ g)
    return total


def _rms(problem: L.JointProblem, T_map_base: np.ndarray) -> float:
    r, _ = problem.residuals(geo.inverse(T_map_base), jacobian=False)
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def main(argv: Sequence[str] = ()) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("test")
    p.add_argument("--variants", action="store_true")
    p.add_argument("--max-frames", type=int, default=0, help="the first N ring frames only (0: all)")
    a = p.parse_args(list(argv) or None)
    _, _, _, ref, ring, _, _, frames, truth = bench_real._load_case(a.test, a.max_frames)
    reference = {int(round(t * 1e6)): T for t, T in zip(ref.stamps, ref.T_map_rig)}
    joint = L.RingLocalizer(ring, truth, L.LocalizationParams(fusion="joint"))
    alpha = joint.params.consistency_alpha

    # 1 and 2: at the exact-extrinsics optimum.
    F: List[Tuple[float, float]] = []
    parts = {"within a marker": [0.0, 0], "between markers of one camera": [0.0, 0], "between cameras": [0.0, 0]}
    passed_h = counted_h = 0
    for f in frames:
        k = int(round(f.stamp * 1e6))
        if k not in reference:
            continue
        views = joint._gather(f, {})
        if len(views) < 2:
            continue
        exact = joint._problem(list(views.values())).exact()
        try:
            _, fit, _ = exact.solve(geo.inverse(reference[k]), joint.params.robust_scale, joint.params.max_iterations)
        except ArucoRingError:
            continue
        test = L.extrinsics_consistency(exact, fit)
        if test is None:
            continue
        F.append((test[0], L._f_quantile(1.0 - alpha, test[1], test[2])))
        r = np.where(np.isfinite(fit.r), fit.r, 0.0)
        cams = [(int(exact.offsets[i]), int(exact.offsets[i + 1])) for i in range(len(exact.views))]
        marks = [(s, s + 4) for (a0, b0) in cams for s in range(a0, b0, 4)]
        q = float(np.sum(fit.w * np.sum(r * r, axis=1)))
        rc, rm = _reduction(fit.J, r, fit.w, cams), _reduction(fit.J, r, fit.w, marks)
        M, C = len(marks), len(cams)
        for name, (v, d) in (("within a marker", (q - rm, 2 * M)),
                             ("between markers of one camera", (rm - rc, 6 * (M - C))),
                             ("between cameras", (rc, 6 * (C - 1)))):
            parts[name][0] += v
            parts[name][1] += d
        if M > C:
            counted_h += 1
            d1, dm = 6 * (C - 1), 6 * (M - C)
            passed_h += int((rc / d1) / ((rm - rc) / dm) <= L._f_quantile(1.0 - alpha, d1, dm))
    Fa = np.array(F)
    ratio = Fa[:, 0] / Fa[:, 1]
    print(f"{a.test}: 1. consistency test on {len(Fa)} multi-camera frames (exact optimum from TagSLAM's pose): "
          f"F median {np.median(Fa[:, 0]):.2f}, quantile median {np.median(Fa[:, 1]):.2f}; F / quantile "
          f"p10 / p50 / p90 {np.percentile(ratio, 10):.2f} / {np.median(ratio):.2f} / {np.percentile(ratio, 90):.2f}; "
          f"passes {int(np.sum(ratio <= 1.0))}")
    print("   2. residual per degree of freedom (px RMS): " + "; ".join(
        f"{n} {np.sqrt(v / max(d, 1)):.3f} ({d} dof)" for n, (v, d) in parts.items()))
    print(f"      the test with the between-markers part as its denominator: passes {passed_h} of {counted_h} "
          "frames with more markers than cameras")

    # 3 and 4: the estimators.
    est: Dict[str, L.RingLocalizer] = {
        "exact (joint_exact_extrinsics)": L.RingLocalizer(ring, truth,
                                                          L.LocalizationParams(fusion="joint_exact_extrinsics")),
        "joint (default)": joint,
        "joint without the window (persistence_window 0)": L.RingLocalizer(
            ring, truth, L.LocalizationParams(fusion="joint", persistence_window=0)),
        "joint, the vibration estimated (estimate_vibration true)": L.RingLocalizer(
            ring, truth, L.LocalizationParams(fusion="joint", estimate_vibration=True))}
    if a.variants:
        def variant(std_m: float, std_deg: float, **kw) -> L.RingLocalizer:
            return L.RingLocalizer(ring.with_extrinsics_std(std_m, std_deg), truth,
                                   L.LocalizationParams(fusion="joint", **kw))
        est["joint, exact_when_consistent false"] = L.RingLocalizer(
            ring, truth, L.LocalizationParams(fusion="joint", exact_when_consistent=False))
        est["joint, no vibration term"] = variant(0.002, 0.2, extrinsic_jitter_deg=0.0, extrinsic_jitter_m=0.0)
        est["joint, extrinsics_std 1 mm / 0.1 deg"] = variant(0.001, 0.1)
        est["joint, extrinsics_std 0.5 mm / 0.05 deg"] = variant(0.0005, 0.05)
        est["joint, 0.5 mm / 0.05 deg, no vibration"] = variant(0.0005, 0.05, extrinsic_jitter_deg=0.0,
                                                                 extrinsic_jitter_m=0.0)
        est["joint, consistency_alpha 1e-6"] = L.RingLocalizer(ring, truth, L.LocalizationParams(
            fusion="joint", consistency_alpha=1e-6))
        est["joint, consistency_alpha 1e-12"] = L.RingLocalizer(ring, truth, L.LocalizationParams(
            fusion="joint", consistency_alpha=1e-12))
    scorer = L.RingLocalizer(ring, truth, L.LocalizationParams(fusion="joint_exact_extrinsics"))
    held: Dict[str, List[float]] = {n: [] for n in list(est) + ["TagSLAM's pose (saw every camera)"]}
    for f in frames:
        k = int(round(f.stamp * 1e6))
        views = scorer._gather(f, {})
        if k not in reference or len(views) < 3:
            continue
        for c in views:
            sub = RingFrame(f.stamp, {n: cf for n, cf in f.cameras.items() if n != c})
            one = L.JointProblem([views[c]])
            row = {}
            for n, loc in est.items():
                try:
                    res = loc.process(sub)
                except ArucoRingError:
                    break
                if not res.ok:
                    break
                row[n] = _rms(one, res.T_map_base)
            else:
                row["TagSLAM's pose (saw every camera)"] = _rms(one, reference[k])
                for n, v in row.items():
                    held[n].append(v)
    print("   3. leave one camera out: the held-out camera's RMS reprojection (px), median / mean / p90 over "
          f"{len(held['joint (default)'])} (frame, camera) pairs:")
    for n, v in held.items():
        x = np.array(v)
        print(f"      {n}: {np.median(x):.3f} / {np.mean(x):.3f} / {np.percentile(x, 90):.3f}")
    print("   4. every frame, all cameras: position error against TagSLAM's rig pose (median mm):")
    for n, loc in est.items():
        err, sig, nees = [], [], []
        for f in frames:
            k = int(round(f.stamp * 1e6))
            if k not in reference:
                continue
            try:
                res = loc.process(f)
            except ArucoRingError:
                continue
            if not res.ok:
                continue
            d = reference[k][:3, 3] - res.T_map_base[:3, 3]
            err.append(1000.0 * float(np.linalg.norm(d)))
            if res.covariance is not None:
                Cp = res.covariance[:3, :3]
                sig.append(1000.0 * float(np.sqrt(np.trace(Cp))))
                nees.append(float(d @ np.linalg.solve(Cp, d)))
        extra = (f"; stated position std median {np.median(sig):.2f} mm, position NEES median {np.median(nees):.2f} "
                 f"(chi^2(3) median 2.37), within 7.81 (95 %) {100.0 * np.mean(np.array(nees) <= 7.81):.0f} %") if sig else ""
        print(f"      {n}: {np.median(err):.2f} mm over {len(err)} frames{extra}")


    # 5: the window's test, every frame in order (the window is the estimator's own).
    loc = L.RingLocalizer(ring, truth, L.LocalizationParams(fusion="joint", estimate_vibration=True))
    rho, multi, cleared, exact_in, first, vib = [], 0, 0, 0, None, []
    for f in frames:
        try:
            res = loc.process(f)
        except ArucoRingError:
            continue
        if not res.ok or len(res.used_cameras) < 2:
            continue
        multi += 1
        exact_in += int(res.extrinsics_consistent)
        cleared += int(res.calibration_cleared)
        if res.calibration_cleared and first is None:
            first = multi
        r, pairs = loc.last_persistence
        if pairs >= loc.params.persistence_min_pairs:
            rho.append(r)
        k2, se, vpairs = loc.last_vibration
        if vpairs:
            vib.append((k2, se, vpairs, loc.vibration_scale))
    if rho:
        x = np.array(rho)
        print(f"   5. the window ({loc.params.persistence_window} frames): rho p10 / p50 / p90 {np.percentile(x, 10):.3f} / "
              f"{np.median(x):.3f} / {np.percentile(x, 90):.3f} over {len(x)} frames with a verdict (persistence_max "
              f"{loc.params.persistence_max}); the calibration cleared in {cleared} of {multi} multi-camera frames "
              f"(the first: the {first}th), exact in {exact_in}")
    else:
        print(f"   5. the window: no verdict in {multi} multi-camera frames (wiggling cameras, or each camera saw "
              "the same markers all along)")
    if vib:
        V = np.array(vib)
        enough = V[:, 2] >= loc.params.vibration_min_pairs
        deg = loc.params.extrinsic_jitter_deg
        k2 = np.median(V[:, 0])
        print(f"   6. the vibration estimate: kappa^2 median {k2:.3f} (standard error median {np.median(V[:, 1]):.3f}, "
              f"pairs median {np.median(V[:, 2]):.0f}; {int(enough.sum())} of {len(V)} frames with "
              f"{loc.params.vibration_min_pairs} or more): jitter {deg * np.sqrt(max(k2, 0.0)):.4f} deg against the "
              f"declared {deg} deg; the scale solved with: median {np.median(V[:, 3]):.3f}, below 1 in "
              f"{int(np.sum(V[:, 3] < 1.0))} frames")
    else:
        print("   6. the vibration estimate: no pair of frames (no camera saw the same markers in consecutive "
              "multi-camera frames, or no vibration declared)")


if __name__ == "__main__":
    main(sys.argv[1:])
