"""A smoothed trajectory over a whole recording: every ring frame's pose from all the frames at once.

The localizer is causal: each ring frame is posed from its own corners (and a filter carries
the past forward). After the fact, a user post-processing a recording wants every pose from the
whole recording: the corners of every frame and the robot's odometry between consecutive
frames, solved together (what TagSLAM's rig poses are: the optimum of one batch problem). That
is a bundle adjustment (:mod:`bundle_adjustment`) with the map and the ring's extrinsics held as
given -- the localization setting (``BAProblem.hold_markers``) -- and one unknown per ring frame:

* **unknowns**: ``T_map_base`` of every ring frame, in SE(3) (``level``: a ground robot, each
  pose's z axis held along the map's by a prior of ``level_sigma_deg``);
* **corners**: every corner of every mapped marker seen, its reprojection residual in raw pixels
  over ``pixel_noise`` (the localizer's ``estimator/pixel_noise``), the lens's local scale
  included (``CameraModel.pixel_jacobian``, as the mapping); a Huber loss beyond ``robust_scale``
  noise sigmas, so that a detection off by many pixels (or a frame whose single marker fits its
  mirrored pose) pulls with a bounded force;
* **odometry**: a relative-pose factor between consecutive ring frames, the motion of the base
  frame ``X P_i^-1 P_j X^-1`` (``P``: the odometry's poses interpolated at the frames' stamps,
  ``X``: ``base_to_odom``, TagSLAM's ``T_body_odom``) with the mapping's noise model and its Huber
  loss per link (:meth:`mapping_odometry.OdometryTrack.links`, the ``mapping.odometry`` section).

Frames without a mapped marker stay in as odometry-only poses where the odometry links them to
frames that see one; a stretch that no link joins to an observed frame (a gap in the odometry and
no marker) has nothing to fix it and is left out (:attr:`SmoothedTrajectory.dropped`). The solver
starts from a given pose per frame (``localize --smooth``: the localizer's filtered output), frames
without one placed along the odometry from their neighbour.

The cameras are taken at the ring frame's stamp (synchronized cameras; the per-frame estimator's
compensation of free-running cameras is not repeated here).
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np

from . import geometry as geo
from .bundle_adjustment import BAOptions, BAProblem, MarkerPriors, RelativePoseFactors, bundle_adjust
from .config import in_radians, param, require_positive
from .detections import RingFrame
from .errors import ConfigError, GeometryError
from .mapping_odometry import MappingOdometryOptions, OdometryTrack
from .marker_map import MarkerMap
from .ring import CameraRing

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SmootherOptions:
    """The smoother's own settings (``localize --smooth``: the corners' noise is the localizer's
    ``estimator/pixel_noise``)."""

    pixel_noise: float = param(0.5, "1-sigma corner noise the corner residuals are divided by (localize --smooth: "
                                    "the localizer's estimator/pixel_noise)", unit="px")
    robust_scale: float = param(3.0, "Huber loss of the corner residuals beyond this many pixel_noise")
    level: bool = param(False, "a ground robot: every pose's z axis held along the map's z (roll, pitch ~0) "
                               "by a prior of level_sigma_deg")
    level_sigma_deg: float = param(0.5, "level: 1-sigma of each pose's tilt", unit="deg")
    reject_px: float = param(3.0, "after a solve, an observation (one marker in one image) whose RMS reprojection "
                                  "error exceeds this is dropped and the problem solved again (twice at most): "
                                  "a wrong detection the Huber loss only bounds (localize --smooth: the localizer's "
                                  "estimator/max_reprojection_error); 0: none", unit="px")
    max_nfev: int = param(100, "solver iteration cap (function evaluations)")

    level_sigma = in_radians("level_sigma_deg")

    def __post_init__(self) -> None:
        require_positive(self, "pixel_noise", "robust_scale", "level_sigma_deg", "max_nfev")
        if not (np.isfinite(self.reject_px) and self.reject_px >= 0):
            raise ConfigError(f"expected a number >= 0, got {self.reject_px!r}", key="reject_px")


@dataclass
class SmoothedTrajectory:
    """What :func:`smooth_trajectory` returns.

    Attributes:
        frame_index: (K,) the input frame of each smoothed pose (in time order).
        stamps: (K,) their stamps, s.
        T_map_base: (K, 4, 4) the smoothed poses.
        observed: (K,) whether the frame saw a mapped marker (else: placed by the odometry alone).
        dropped: input frames left out (no mapped marker and no odometry link to a frame with one,
            or a stamp another frame already has).
        links: odometry factors in the problem.
        rejected: observations dropped for their reprojection error (``reject_px``).
        rms_px_before, rms_px_after: RMS corner reprojection error (px) at the start and the solution.
        cpu_seconds: CPU time (utime + stime) of the assembly and the solve.
        status: the solver's stopping reason.
    """

    frame_index: np.ndarray
    stamps: np.ndarray
    T_map_base: np.ndarray
    observed: np.ndarray
    dropped: int = 0
    links: int = 0
    rejected: int = 0
    rms_px_before: float = float("nan")
    rms_px_after: float = float("nan")
    cpu_seconds: float = 0.0
    status: str = ""
    extra: Dict[str, float] = field(default_factory=dict)


@dataclass
class SmootherProblem:
    """The bundle adjustment :func:`smooth_trajectory` solves (:func:`smoother_problem`).

    Attributes:
        problem, options: the adjustment (markers held) and its solver settings.
        frame_index: (K,) the input frame of each station.
        stamps: (K,) the stations' stamps.
        observed: (K,) the station sees a mapped marker.
        dropped: input frames left out.
    """

    problem: BAProblem
    options: BAOptions
    frame_index: np.ndarray
    stamps: np.ndarray
    observed: np.ndarray
    dropped: int


def odometry_track(stamps: Sequence[float], poses: np.ndarray, topic: str = "odometry") -> OdometryTrack:
    """The odometry poses ``T_odom_body`` by stamp as a track; a clear error when there are fewer
    than two (no motion between two frames to measure)."""
    track = OdometryTrack(stamps, poses)
    if len(track) < 2:
        raise ConfigError(f"{topic}: {len(track)} usable odometry poses; the smoother needs the odometry between "
                          f"frames (without it the smoothed trajectory is the per-frame estimate: localize --output "
                          f"measurement)")
    return track


def _observations(frames: Sequence[RingFrame], ring: CameraRing, marker_map: MarkerMap) -> list:
    """Per observation of a mapped marker: (frame, camera index, marker id, xy, focal, lens)."""
    cams = {c.name: k for k, c in enumerate(ring)}
    found = []
    for f_idx, frame in enumerate(frames):
        for name, cf in frame.cameras.items():
            if name not in cams:
                continue
            model = cf.model or ring[name].model
            focal = np.array([model.fx, model.fy])
            for o in cf.observations:
                if int(o.marker_id) not in marker_map:
                    continue
                corners = np.asarray(o.corners, dtype=float).reshape(4, 2)
                if not np.all(np.isfinite(corners)):
                    continue
                xy = model.normalize(corners)
                if not np.all(np.isfinite(xy)):
                    continue
                found.append((f_idx, cams[name], int(o.marker_id), xy, focal, model.pixel_jacobian(xy)))
    return found


def _components(n: int, links: Optional[RelativePoseFactors]) -> np.ndarray:
    """(n,) a label per station: stations joined by links share one (union-find)."""
    parent = np.arange(n)

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    if links is not None:
        for i, j in zip(links.station_i, links.station_j):
            ri, rj = root(int(i)), root(int(j))
            if ri != rj:
                parent[max(ri, rj)] = min(ri, rj)
    return np.array([root(a) for a in range(n)])


def _initial_poses(order: List[int], initial: Sequence[Optional[np.ndarray]], links: Optional[RelativePoseFactors],
                   n: int) -> List[Optional[np.ndarray]]:
    """A start pose per station (``order``: the input frame of each): the given one, else carried
    along the odometry links from a neighbour that has one (forward, then backward)."""
    T: List[Optional[np.ndarray]] = []
    for f in order:
        g = initial[f] if f < len(initial) else None
        T.append(None if g is None or not np.all(np.isfinite(g)) else np.asarray(g, dtype=float))
    if links is None:
        return T
    fwd = {int(i): (int(j), Z) for i, j, Z in zip(links.station_i, links.station_j, links.T_ij)}
    bwd = {int(j): (int(i), Z) for i, j, Z in zip(links.station_i, links.station_j, links.T_ij)}
    for s in range(n):                      # forward: T_j = T_i Z
        if T[s] is None and s in bwd and T[bwd[s][0]] is not None:
            T[s] = T[bwd[s][0]] @ bwd[s][1]
    for s in range(n - 1, -1, -1):          # backward: T_i = T_j Z^-1
        if T[s] is None and s in fwd and T[fwd[s][0]] is not None:
            T[s] = T[fwd[s][0]] @ geo.inverse(fwd[s][1])
    return T


def smoother_problem(frames: Sequence[RingFrame], ring: CameraRing, marker_map: MarkerMap,
                     odometry: OdometryTrack, odometry_options: MappingOdometryOptions,
                     initial: Sequence[Optional[np.ndarray]], options: Optional[SmootherOptions] = None
                     ) -> SmootherProblem:
    """The problem :func:`smooth_trajectory` solves (same arguments), not solved."""
    opts = options or SmootherOptions()
    if len(odometry) < 2:
        raise ConfigError("no odometry: the smoothed trajectory would be the per-frame estimate")
    # One station per distinct stamp, in time order.
    order: List[int] = []
    seen_stamps = set()
    for f in sorted(range(len(frames)), key=lambda k: (float(frames[k].stamp), k)):
        s = float(frames[f].stamp)
        if s not in seen_stamps:
            seen_stamps.add(s)
            order.append(f)
    obs = _observations([frames[f] for f in order], ring, marker_map)
    if not obs:
        raise GeometryError("no ring frame sees a mapped marker: nothing places the trajectory on the map")
    stamps = np.array([float(frames[f].stamp) for f in order])
    links = odometry.links({s: float(stamps[s]) for s in range(len(order))}, odometry_options)
    if links is None:
        raise ConfigError("the odometry covers no two consecutive ring frames (stamps outside its span, or gaps "
                          f"longer than max_gap {odometry_options.max_gap} s): nothing to smooth with")
    observed = np.zeros(len(order), dtype=bool)
    observed[[o[0] for o in obs]] = True
    # Keep the stations of the link-joined stretches that see a marker somewhere.
    comp = _components(len(order), links)
    anchored = set(comp[observed].tolist())
    start = _initial_poses(order, initial, links, len(order))
    keep = np.array([comp[s] in anchored and start[s] is not None for s in range(len(order))])
    # A stretch whose frames have no start at all (no filtered pose anywhere in it) cannot start.
    new_index = -np.ones(len(order), dtype=int)
    new_index[keep] = np.arange(int(keep.sum()))
    li, lj = new_index[links.station_i], new_index[links.station_j]
    ok = (li >= 0) & (lj >= 0)
    factors = RelativePoseFactors(li[ok], lj[ok], links.T_ij[ok], links.sigma[ok], robust_scale=links.robust_scale)
    obs = [o for o in obs if keep[o[0]]]
    if not obs:
        raise GeometryError("no ring frame that sees a mapped marker has a start pose")
    ids = sorted({o[2] for o in obs})
    m_index = {m: k for k, m in enumerate(ids)}
    priors = None
    if opts.level:
        priors = MarkerPriors(level_station=np.arange(int(keep.sum())), level_sigma=float(opts.level_sigma))
    prob = BAProblem(
        T_W_markers=np.stack([marker_map.T_map_marker(m) for m in ids]),
        sizes=np.array([marker_map[m].size for m in ids]),
        T_W_stations=np.stack([start[s] for s in range(len(order)) if keep[s]]),
        T_base_cams=np.stack([c.T_base_cam for c in ring]),
        obs_marker=np.array([m_index[o[2]] for o in obs]),
        obs_station=np.array([new_index[o[0]] for o in obs]),
        obs_camera=np.array([o[1] for o in obs]),
        obs_xy=np.stack([o[3] for o in obs]),
        obs_focal=np.stack([o[4] for o in obs]),
        obs_lens=np.stack([o[5] for o in obs]),
        fixed_marker=None, hold_markers=True, priors=priors,
        odometry=factors if len(factors) else None)
    ba = BAOptions(pixel_noise=opts.pixel_noise, loss="huber", robust_scale=opts.robust_scale,
                   covariance=False, max_nfev=opts.max_nfev, solver="lm")
    kept = np.flatnonzero(keep)
    return SmootherProblem(prob, ba, np.array([order[s] for s in kept], dtype=int), stamps[kept], observed[kept],
                           len(frames) - len(kept))


def _rejectable(prob: BAProblem, rms_px: np.ndarray, reject_px: float) -> np.ndarray:
    """(N,) the observations above ``reject_px`` RMS, except those whose station's link-joined
    stretch would be left without any observation (nothing would hold it on the map then)."""
    bad = np.asarray(rms_px) > reject_px
    if not np.any(bad):
        return bad
    comp = _components(len(prob.T_W_stations), prob.odometry)
    obs_comp = comp[prob.obs_station]
    still = set(obs_comp[~bad].tolist())
    return bad & np.isin(obs_comp, list(still))


def _without(prob: BAProblem, keep: np.ndarray, T_W_stations: np.ndarray) -> BAProblem:
    """``prob`` with only the observations ``keep``, started from ``T_W_stations``."""
    return dataclasses.replace(prob, T_W_stations=T_W_stations, obs_marker=prob.obs_marker[keep],
                               obs_station=prob.obs_station[keep], obs_camera=prob.obs_camera[keep],
                               obs_xy=prob.obs_xy[keep], obs_focal=prob.obs_focal[keep],
                               obs_lens=prob.obs_lens[keep] if prob.obs_lens is not None else None)


def smooth_trajectory(frames: Sequence[RingFrame], ring: CameraRing, marker_map: MarkerMap,
                      odometry: OdometryTrack, odometry_options: MappingOdometryOptions,
                      initial: Sequence[Optional[np.ndarray]], options: Optional[SmootherOptions] = None
                      ) -> SmoothedTrajectory:
    """Every ring frame's ``T_map_base`` from all the frames' corners and the odometry between them
    (module docstring), the map and the ring held.

    Args:
        frames: the ring frames, any order (their stamps order them; equal stamps: the first kept).
        ring: the ring (extrinsics, and the intrinsics of cameras whose frames carry none).
        marker_map: the map, held.
        odometry: the odometry body's poses ``T_odom_body`` (:func:`odometry_track`).
        odometry_options: ``mapping.odometry`` (``base_to_odom``, the links' noise model, ``max_gap``).
        initial: per input frame a start pose ``T_map_base`` (4, 4) or None (placed along the odometry).
        options: :class:`SmootherOptions`.

    Raises:
        ConfigError: fewer than two odometry poses, or no link between two frames.
        GeometryError: no frame sees a mapped marker.
    """
    c0 = time.process_time()
    opts = options or SmootherOptions()
    built = smoother_problem(frames, ring, marker_map, odometry, odometry_options, initial, opts)
    prob = built.problem
    res = bundle_adjust(prob, built.options)
    rms0, rejected = res.rms_px_before, 0
    for _ in range(2 if opts.reject_px > 0 else 0):
        bad = _rejectable(prob, res.per_obs_rms_px, opts.reject_px)
        if not np.any(bad):
            break
        rejected += int(bad.sum())
        prob = _without(prob, ~bad, res.T_W_stations)
        res = bundle_adjust(prob, built.options)
    odo = prob.odometry
    observed = np.zeros(len(built.stamps), dtype=bool)
    observed[prob.obs_station] = True
    out = SmoothedTrajectory(frame_index=built.frame_index, stamps=built.stamps, T_map_base=res.T_W_stations,
                             observed=observed, dropped=built.dropped, links=len(odo) if odo is not None else 0,
                             rejected=rejected, rms_px_before=rms0, rms_px_after=res.rms_px_after,
                             cpu_seconds=time.process_time() - c0, status=res.status)
    logger.info("smoother: %d frames (%d with a mapped marker, %d by the odometry alone), %d odometry links, "
                "%d frames left out, %d observations rejected: RMS %.3f -> %.3f px (%.2f s CPU; %s)",
                len(out.stamps), int(out.observed.sum()), int((~out.observed).sum()), out.links, out.dropped,
                out.rejected, out.rms_px_before, out.rms_px_after, out.cpu_seconds, out.status)
    return out


__all__ = ["SmootherOptions", "SmootherProblem", "SmoothedTrajectory", "smoother_problem", "smooth_trajectory",
           "odometry_track"]
