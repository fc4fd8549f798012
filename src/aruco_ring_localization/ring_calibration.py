"""Ring calibration from rough values: :func:`calibrate_ring`.

Input: ring frames of the robot turning on the spot and driving among markers (a bag through
``aruco_ring calibrate-ring``), the rough ring (a drawing's values, off by up to ~5 cm and ~10 deg
per camera), the marker sizes, optionally the robot's odometry (``T_odom_base`` over time) and a
known marker map. Output: every camera's ``T_base_cam`` free in 6-DOF, its std, and warnings
naming the motion that was missing when something could not be determined.

Steps:

1. **Single-marker poses.** Every detection gets its IPPE pose ``T_cam_marker``
   (:func:`pnp.solve_marker_ippe_undistorted`); ambiguous, far or badly fitting ones are not used
   for the initialisation (they still enter the adjustment).
2. **Per-camera motion.** Each camera alone chains the markers it sees into its own world and
   follows itself through it (segments restart when it loses every known marker): its relative
   motions ``A_ij = T_cam(i)^-1 T_cam(j)`` between frames ``i`` and ``j`` of one segment.
3. **Hand-eye per camera.** The robot's motion ``B_ij`` (odometry when given, else the mean of what
   every camera's motion says through its current extrinsics) relates to it by
   ``B_ij X = X A_ij`` with ``X = T_base_cam``; ``X`` is solved by robust nonlinear least squares
   from the rough value (a 6-parameter problem, well inside its basin from 10 deg). Without
   odometry the robot's motion and the cameras are re-estimated in turn (3 rounds).
4. **Joint bundle adjustment** (:func:`bundle_adjustment.bundle_adjust`) of every corner: markers,
   one robot pose per frame used, every camera's extrinsics with loose priors (5 cm, 5 deg) around
   the hand-eye values (they only hold the ring's common motion, the gauge; the data decide the
   cameras relative to each other). Observations that still reproject badly are dropped and the
   adjustment redone once.
4b. **A declared wiggle** (the ring file's per-camera ``wiggle``, e.g. TagSLAM's
   ``wiggle_rotation`` / ``wiggle_translation`` through ``import-kalibr``; ``options.wiggle`` "off"
   ignores it): such a camera is not rigid on the ring, and its extrinsics are the fixed pose it
   wiggles about, not a rigid ring's best fit (which weighs the frames by what they see and is
   pulled towards the poses of the frames that see most). On ``wiggle_max_frames`` robot poses of
   the adjustment, fewer when they would make more than ``wiggle_max_poses`` (frame, wiggling
   camera) poses (evenly spread: the stage's cost grows with those poses), every
   (frame, wiggling camera) gets its own pose tied to the camera's fixed pose by a prior of the
   declared std (:func:`wiggle_adjust`, 1 px corner noise and no robust loss: the model the
   declared std belong to); the fixed poses by alternation from the rigid answer, each the
   (over-relaxed) mean of its per-frame poses (:func:`solve_wiggle`). The rigid answer is kept
   (:attr:`RingCalibration.rigid_ring`). The stage sees the observations the rigid adjustment kept.
5. **base_link from the motion.** The ring is then placed in base_link: its z axis along the
   robot's rotation axis (turning), its origin (x, y) at the centre of the turns on the spot; with
   odometry the full pose by hand-eye against it (heading included), with a known map in a
   ``floor`` frame the height too (base_link on the floor). What the motion cannot give stays the
   rough ring's, and a warning says which motion was missing.

Per-camera std: the adjustment's covariance of each camera with the ring's common motion (the
gauge) projected out, in the camera's optical frame (the ring file's ``extrinsics_std``
convention): how well each camera is known relative to the others (the ring's common
motion, i.e. base_link's definition, is what the warnings are about). Scaled by the measured
corner noise and inflated for the correlation of a marker's residuals from one frame to the next
(:func:`residual_lag1_correlation`): a detector errs alike on near-identical views. A wiggling
camera's adds the declared wiggle over the square root of its frames in the wiggle stage (the
fixed pose is the mean of that many per-frame poses).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from . import geometry as geo
from .bundle_adjustment import BAOptions, BAProblem, BAResult, bundle_adjust, camera_cov_in_optical_frames
from .detections import RingFrame
from .errors import ConfigError, GeometryError, MeasurementError
from .marker_map import MarkerMap
from .markers import MarkerSizes
from .pnp import solve_marker_ippe_undistorted
from .ring import CameraRing, RingCamera

logger = logging.getLogger(__name__)

#: Frame lags (in used frames) of the relative motions of the hand-eye step.
PAIR_LAGS = (1, 3, 8, 20)


@dataclass(frozen=True)
class CalibrationOptions:
    """Settings of :func:`calibrate_ring` (``aruco_ring calibrate-ring``'s options)."""

    max_frames: int = 400            # frames used, evenly spread over the recording
    max_reprojection_px: float = 2.0   # single-marker poses fitting worse do not initialise
    max_ambiguity: float = 0.6       # IPPE ambiguity ratio above which a pose does not initialise
    max_distance: float = 6.0        # m; farther detections do not initialise
    min_camera_frames: int = 10      # a camera with markers in fewer frames keeps its rough values
    min_turn_deg: float = 45.0       # less total turning than this: the rotation axis / turn centre are not seen
    min_travel: float = 0.5          # m; less driving than this (with odometry): heading from the rough ring
    pixel_noise: float = 0.5         # px, the adjustment's corner noise
    prior_trans: float = 0.05        # m, the adjustment's priors around the hand-eye values (gauge only)
    prior_rot_deg: float = 5.0       # deg, idem
    max_obs_rms_px: float = 3.0      # observations reprojecting worse after the first adjustment are dropped
    handeye_rounds: int = 3          # without odometry: robot motion / cameras re-estimated in turn
    handeye_max_trans: float = 0.10  # m; a hand-eye answer farther from the rough value is not kept
    handeye_max_rot_deg: float = 15.0  # deg; idem
    loss: str = "huber"              # the adjustment's robust loss (BAOptions.loss), scale 3 x pixel_noise
    # Declared wiggle (the ring's per-camera ``wiggle``): "auto" solves it when a camera declares one,
    # "off" calibrates a rigid ring whatever the ring file says.
    wiggle: str = "auto"
    wiggle_max_frames: int = 200     # robot poses of the rigid adjustment used by the wiggle stage (evenly spread)
    wiggle_max_poses: int = 800      # and at most this many (frame, wiggling camera) poses: its cost grows with them
    wiggle_rounds: int = 4           # alternation rounds (per-frame poses, then the fixed poses)
    wiggle_relax: float = 2.0        # over-relaxation of the fixed poses' step (see relaxed_step)
    wiggle_pixel_noise: float = 1.0  # px; with the declared std it sets the model (TagSLAM's: 1 px)
    wiggle_loss: str = "linear"      # the wiggle stage's loss (TagSLAM's: none)

    def __post_init__(self) -> None:
        if self.wiggle not in ("auto", "off"):
            raise ConfigError(f"expected auto or off, got {self.wiggle!r}", key="wiggle")
        if self.wiggle_max_frames < 3 or self.wiggle_max_poses < 3 or self.wiggle_rounds < 1 or not self.wiggle_relax > 0:
            raise ConfigError(f"wiggle_max_frames >= 3, wiggle_max_poses >= 3, wiggle_rounds >= 1 and wiggle_relax > 0 "
                              f"expected, got {self.wiggle_max_frames}, {self.wiggle_max_poses}, {self.wiggle_rounds}, "
                              f"{self.wiggle_relax}",
                              key="wiggle_max_frames")


@dataclass
class RingCalibration:
    """What :func:`calibrate_ring` found.

    Attributes:
        ring: the calibrated ring (the rough ring's cameras with new ``T_base_cam`` and
            ``extrinsics_std``).
        std: {camera: (6,) std, rotation about the optical x, y, z (rad), translation along them (m)}.
        warnings: what the recording could not determine, naming the missing motion.
        handeye: {camera: T_base_cam} after the hand-eye initialisation (before the adjustment).
        frames_used, camera_frames: frames in the adjustment; frames with markers per camera.
        turn_deg, travel_m: total turning and driving of the robot in the frames used.
        rms_px_before, rms_px_after: the adjustment's corner RMS.
        ba: the adjustment's result.
        station_stamps: the stamp of each of the adjustment's robot poses (``ba.T_W_stations``).
        rigid_ring: the rigid ring's answer when the wiggle stage ran (``ring`` is then the fixed
            poses the cameras wiggle about), else None (``ring`` is the rigid answer).
        wiggle: the wiggle stage (:class:`WiggleFit`), or None when no camera declares wiggle
            (or ``options.wiggle`` is "off").
    """

    ring: CameraRing
    std: Dict[str, np.ndarray]
    warnings: List[str]
    handeye: Dict[str, np.ndarray]
    frames_used: int
    camera_frames: Dict[str, int]
    turn_deg: float
    travel_m: float
    rms_px_before: float
    rms_px_after: float
    ba: Optional[BAResult] = None
    extra: Dict[str, float] = field(default_factory=dict)
    station_stamps: List[float] = field(default_factory=list)
    rigid_ring: Optional[CameraRing] = None
    wiggle: Optional["WiggleFit"] = None


@dataclass
class _Det:
    frame: int
    camera: str
    marker: int
    xy: np.ndarray          # (4, 2) undistorted normalised
    focal: np.ndarray       # (2,)
    lens: np.ndarray        # (4, 2, 2)
    T_cam_marker: Optional[np.ndarray]   # None: not good enough to initialise


# --- 1. detections ------------------------------------------------------------------------------

def _select_frames(frames: Sequence[RingFrame], max_frames: int) -> List[RingFrame]:
    with_obs = [f for f in frames if f.observation_count() > 0] if frames else []
    with_obs.sort(key=lambda f: f.stamp)
    if len(with_obs) <= max_frames:
        return with_obs
    idx = np.unique(np.linspace(0, len(with_obs) - 1, max_frames).round().astype(int))
    return [with_obs[i] for i in idx]


def _detections(frames: Sequence[RingFrame], ring: CameraRing, sizes: MarkerSizes,
                opts: CalibrationOptions) -> List[_Det]:
    out: List[_Det] = []
    for k, f in enumerate(frames):
        for name, cf in f.cameras.items():
            if name not in ring.names:
                continue
            model = cf.model or ring[name].model
            focal = np.array([model.fx, model.fy])
            for o in cf.observations:
                xy = model.normalize(o.corners)
                if xy.shape != (4, 2) or not np.all(np.isfinite(xy)):
                    continue
                size = sizes(o.marker_id)
                T = None
                try:
                    cand = solve_marker_ippe_undistorted(xy, size, focal, mirror=True)
                    if (cand.error <= opts.max_reprojection_px and cand.ambiguity <= opts.max_ambiguity
                            and np.linalg.norm(cand.T_cam_marker[:3, 3]) <= opts.max_distance):
                        T = cand.T_cam_marker
                except (GeometryError, MeasurementError, ValueError):
                    continue
                out.append(_Det(k, name, int(o.marker_id), xy, focal, model.pixel_jacobian(xy), T))
    return out


# --- 2. per-camera motion -------------------------------------------------------------------------

def camera_trajectory(dets: Sequence[_Det]) -> Dict[int, Tuple[int, np.ndarray]]:
    """{frame: (segment, T_world_cam)} of one camera from its own detections (each ``T_cam_marker``).

    The camera's world is the camera's pose at the segment's first frame; markers are placed when
    first seen, the camera at each frame is the mean of what its known markers say; a frame seeing
    no known marker starts a new segment (its own world).
    """
    by_frame: Dict[int, List[_Det]] = {}
    for d in dets:
        if d.T_cam_marker is not None:
            by_frame.setdefault(d.frame, []).append(d)
    out: Dict[int, Tuple[int, np.ndarray]] = {}
    known: Dict[int, np.ndarray] = {}
    seg = -1
    for k in sorted(by_frame):
        ds = by_frame[k]
        ests = [known[d.marker] @ geo.inverse(d.T_cam_marker) for d in ds if d.marker in known]
        if ests:
            T = _robust_mean(ests)
        else:
            seg += 1
            known = {}
            T = np.eye(4)
        out[k] = (seg, T)
        for d in ds:
            if d.marker not in known:
                known[d.marker] = T @ d.T_cam_marker
    return out


def _robust_mean(Ts: Sequence[np.ndarray], max_dev: float = 0.05) -> np.ndarray:
    if len(Ts) == 1:
        return np.asarray(Ts[0])
    P = np.array([T[:3, 3] for T in Ts])
    med = np.median(P, axis=0)
    keep = [T for T, p in zip(Ts, P) if np.linalg.norm(p - med) <= max(max_dev, 0.0)]
    return geo.average_transforms(keep or list(Ts))


def relative_motions(traj: Dict[int, Tuple[int, np.ndarray]], lags: Sequence[int] = PAIR_LAGS
                     ) -> Dict[Tuple[int, int], np.ndarray]:
    """{(i, j): T_cam(i)^-1 T_cam(j)} for frames ``lag`` apart (in the camera's frames) in one segment."""
    ks = sorted(traj)
    out: Dict[Tuple[int, int], np.ndarray] = {}
    for a, i in enumerate(ks):
        for lag in lags:
            b = a + lag
            if b >= len(ks):
                break
            j = ks[b]
            if traj[j][0] != traj[i][0]:
                continue
            out[(i, j)] = geo.inverse(traj[i][1]) @ traj[j][1]
    return out


# --- 3. hand-eye --------------------------------------------------------------------------------

def solve_hand_eye(B: Sequence[np.ndarray], A: Sequence[np.ndarray], X0: np.ndarray,
                   rot_noise: float = np.radians(0.3), trans_noise: float = 0.005,
                   prior_trans: Tuple[float, float, float] = (1.0, 1.0, 0.05)) -> Tuple[np.ndarray, np.ndarray]:
    """``X`` (4x4) with ``B_k X = X A_k`` for the robot motions ``B`` and the camera motions ``A``.

    Robust (soft L1) least squares from ``X0``: ``X = (exp(w) R0, t0 + dt)``; residuals the rotation
    ``log(R_X^T R_B R_X R_A^T) / rot_noise`` and the translation
    ``(R_B t_X + t_B - R_X t_A - t_X) / trans_noise``, plus a weak prior pulling ``dt`` to zero with
    ``prior_trans`` std per base axis (what the motion does not determine, e.g. the height of a
    camera when the robot only turns about z, stays ``X0``'s). Returns (X, 6x6 covariance of
    (w, dt) from the Gauss-Newton information).
    """
    B = np.asarray(B, dtype=float)
    A = np.asarray(A, dtype=float)
    if len(B) == 0:
        return np.asarray(X0, dtype=float).copy(), np.diag([1.0] * 3 + list(np.square(prior_trans)))
    R0, t0 = X0[:3, :3], X0[:3, 3]
    RB, tB, RA, tA = B[:, :3, :3], B[:, :3, 3], A[:, :3, :3], A[:, :3, 3]
    ps = np.asarray(prior_trans, dtype=float)

    def res(x: np.ndarray) -> np.ndarray:
        R = geo.so3_exp(x[:3]) @ R0
        t = t0 + x[3:]
        E = np.einsum("ji,njk,kl,nml->nim", R, RB, R, RA)     # R^T R_B R R_A^T
        r_rot = Rotation.from_matrix(E).as_rotvec() / rot_noise
        r_t = (np.einsum("nij,j->ni", RB, t) + tB - np.einsum("ij,nj->ni", R, tA) - t) / trans_noise
        return np.concatenate([r_rot.ravel(), r_t.ravel(), x[3:] / ps])

    sol = least_squares(res, np.zeros(6), loss="soft_l1", f_scale=3.0, x_scale=np.r_[[0.05] * 3, [0.02] * 3])
    X = np.eye(4)
    X[:3, :3] = geo.so3_exp(sol.x[:3]) @ R0
    X[:3, 3] = t0 + sol.x[3:]
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(J.T @ J)
    return X, cov


def _mean_motion(Ts: Sequence[np.ndarray]) -> np.ndarray:
    return _robust_mean(Ts, max_dev=0.05) if len(Ts) > 2 else geo.average_transforms(Ts)


# --- observability ----------------------------------------------------------------------------------

def motion_extent(T_W_base: Sequence[np.ndarray]) -> Tuple[float, float, np.ndarray]:
    """(total turn, deg; travelled distance, m; mean rotation axis in the base frame, unit) of a
    sequence of robot poses (consecutive relative motions summed)."""
    turn = 0.0
    travel = 0.0
    axis = np.zeros(3)
    for a, b in zip(T_W_base[:-1], T_W_base[1:]):
        D = geo.inverse(a) @ b
        w = Rotation.from_matrix(D[:3, :3]).as_rotvec()
        turn += float(np.linalg.norm(w))
        travel += float(np.linalg.norm(D[:3, 3]))
        # Sign-consistent accumulation (the rotation axis up to its direction).
        axis += w if (w @ axis) >= 0 else -w
    n = float(np.linalg.norm(axis))
    return float(np.degrees(turn)), travel, (axis / n if n > 0 else np.array([0.0, 0.0, 1.0]))


def observability_warnings(turn_deg: float, travel_m: float, has_odometry: bool, has_floor_map: bool,
                           camera_frames: Dict[str, int], opts: CalibrationOptions,
                           rough_height: float = float("nan")) -> List[str]:
    """The warnings of a calibration, each naming the motion (or input) that was missing."""
    out: List[str] = []
    if turn_deg < opts.min_turn_deg:
        out.append(f"no rotation: the robot turned only {turn_deg:.0f} deg in the recording (< {opts.min_turn_deg:g}): "
                   "base_link's z axis (the ring's tilt) and its origin (x, y) relative to the cameras, and every "
                   "camera's position relative to the others, are poorly determined and lean on the rough ring; "
                   "turn the robot on the spot (a full turn) among markers")
    if not has_floor_map:
        out.append(f"planar motion only: the height (z) of the ring above base_link is not observable from a robot "
                   f"driving on a floor; kept from the rough ring (mean camera height {rough_height:.3f} m); give "
                   "--map with a map in a floor frame, or measure one camera's height")
    if not has_odometry:
        out.append("no odometry: base_link's heading relative to the cameras is not observable from the images; "
                   "kept from the rough ring (the mean of its cameras' headings; each camera's heading relative to "
                   "the others is calibrated); record odom in the bag, or measure one camera's heading")
    elif travel_m < opts.min_travel:
        out.append(f"no driving: the robot travelled {travel_m:.2f} m (< {opts.min_travel:g} m): the heading of "
                   "base_link against the odometry is weakly determined; drive straight among markers too")
    for name, n in sorted(camera_frames.items()):
        if n < opts.min_camera_frames:
            out.append(f"{name}: markers in only {n} frames (< {opts.min_camera_frames}): its extrinsics stay near "
                       f"the rough values; drive or turn so that {name} sees markers")
    return out


# --- 5. base_link from the motion --------------------------------------------------------------------

def _turn_centre(T_W_s: Sequence[np.ndarray], axis: np.ndarray, min_angle: float = np.radians(1.0)) -> Optional[np.ndarray]:
    """The point (rig frame, in the plane through the origin orthogonal to ``axis``) that stays
    still while the robot turns: least squares of ``(R_ij - I) p = -t_ij`` over consecutive motions
    with a turn, reweighted (pairs that also drove are outliers)."""
    rows, rhs = [], []
    for a, b in zip(T_W_s[:-1], T_W_s[1:]):
        D = geo.inverse(a) @ b
        if geo.rotation_angle(D[:3, :3]) < min_angle:
            continue
        rows.append(D[:3, :3] - np.eye(3))
        rhs.append(-D[:3, 3])
    if len(rows) < 3:
        return None
    M, y = np.concatenate(rows), np.concatenate(rhs)
    P = np.eye(3) - np.outer(axis, axis)
    M = M @ P
    w = np.ones(len(rows))
    p = np.zeros(3)
    for _ in range(5):
        W = np.repeat(w, 3)
        p = np.linalg.lstsq(M * W[:, None], y * W, rcond=None)[0]
        r = np.linalg.norm((M @ p - y).reshape(-1, 3), axis=1)
        s = max(1.4826 * float(np.median(r)), 1e-4)
        w = 1.0 / np.maximum(1.0, r / (2.0 * s))
    return P @ p


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a to unit vector b."""
    v = np.cross(a, b)
    s, c = float(np.linalg.norm(v)), float(a @ b)
    if s < 1e-12:
        return np.eye(3)
    return geo.so3_exp(v / s * np.arctan2(s, c))


def _odometry_at(odometry: Sequence[Tuple[float, np.ndarray]], stamps: Sequence[float], max_dt: float = 0.06
                 ) -> Dict[int, np.ndarray]:
    """{frame index: T_odom_base} at each stamp, interpolated between the two nearest odometry poses."""
    ts = np.array([t for t, _ in odometry])
    order = np.argsort(ts)
    ts = ts[order]
    Ts = [odometry[i][1] for i in order]
    out: Dict[int, np.ndarray] = {}
    for k, t in enumerate(stamps):
        j = int(np.searchsorted(ts, t))
        if j == 0 or j >= len(ts):
            jj = min(max(j, 0), len(ts) - 1)
            if abs(ts[jj] - t) <= max_dt:
                out[k] = np.asarray(Ts[jj])
            continue
        t0, t1 = ts[j - 1], ts[j]
        if t1 - t0 > 2 * max_dt + 1e-9 and min(t - t0, t1 - t) > max_dt:
            continue
        u = 0.0 if t1 <= t0 else (t - t0) / (t1 - t0)
        D = geo.inverse(Ts[j - 1]) @ Ts[j]
        w = Rotation.from_matrix(D[:3, :3]).as_rotvec()
        step = np.eye(4)
        step[:3, :3] = geo.so3_exp(u * w)
        step[:3, 3] = u * D[:3, 3]
        out[k] = np.asarray(Ts[j - 1]) @ step
    return out


# --- 4b. declared wiggle ---------------------------------------------------------------------------

@dataclass
class WiggleFit:
    """The wiggle stage of :func:`calibrate_ring` (cameras that declare ``wiggle`` in the ring file).

    Attributes:
        fixed: {camera: T_base_cam} the fixed pose each camera wiggles about, in the rigid
            adjustment's base frame (the ring's common motion as the rigid answer's).
        wiggling: the cameras that declared wiggle (the others keep one pose for every frame).
        sigma: (rotation rad, translation m) of the priors tying each per-frame pose to the fixed one.
        frames: robot poses used (a subsample of the rigid adjustment's); camera_frames: per camera.
        rounds: per round the model's cost (corners + priors, in sigmas squared), its parts and the
            corner RMS (px) of the per-frame adjustment.
        cpu_s: CPU time of the stage (utime + stime).
    """

    fixed: Dict[str, np.ndarray]
    wiggling: List[str]
    sigma: Tuple[float, float]
    frames: int
    camera_frames: Dict[str, int]
    rounds: List[Dict[str, float]]
    cpu_s: float


def wiggle_adjust(res: BAResult, prob: BAProblem, fixed: Sequence[np.ndarray], wiggling: Sequence[bool],
                  rot_sigma: float, trans_sigma: float, pixel_noise: float = 1.0, loss: str = "linear",
                  stations: Optional[Sequence[int]] = None, max_nfev: int = 60) -> Dict[str, object]:
    """One adjustment of the wiggle model on an adjustment's observations (``res`` solved ``prob``).

    Every (robot pose, camera) of a wiggling camera gets its own ``T_base_cam``, tied to the camera's
    ``fixed`` pose by a prior of std ``rot_sigma`` (rad) / ``trans_sigma`` (m); a camera that does
    not wiggle keeps one pose for every frame (same prior: loose, the data decide it). Markers and
    robot poses are free, started from ``res`` (the robot poses moved so that the cameras start
    where ``res`` has them on average). ``stations``: the robot poses used (default all).

    Returns {"per_cam": {camera index: [T_base_cam per frame]}, "rms_px", "cost_corners",
    "cost_priors", "cost"} (costs in sigmas squared).
    """
    fixed = np.asarray(fixed, dtype=float)
    C = len(fixed)
    wig = np.asarray(wiggling, dtype=bool)
    keep = np.ones(len(prob.obs_station), dtype=bool) if stations is None else np.isin(prob.obs_station, stations)
    st_u, st_i = np.unique(prob.obs_station[keep], return_inverse=True)
    m_u, m_i = np.unique(prob.obs_marker[keep], return_inverse=True)
    cam = prob.obs_camera[keep]
    key = np.where(wig[cam], st_i * C + cam, -1 - cam)
    pairs, inv = np.unique(key, return_inverse=True)
    pair_cam = np.where(pairs >= 0, pairs % C, -1 - pairs).astype(int)
    D = geo.average_transforms([res.T_base_cams[k] @ geo.inverse(fixed[k]) for k in range(C)])
    fm = prob.fixed_marker
    fixed_marker = int(np.searchsorted(m_u, fm)) if fm is not None and fm in m_u else 0
    sub = BAProblem(T_W_markers=res.T_W_markers[m_u], sizes=np.asarray(prob.sizes)[m_u],
                    T_W_stations=res.T_W_stations[st_u] @ D, T_base_cams=fixed[pair_cam],
                    obs_marker=m_i.astype(int), obs_station=st_i.astype(int), obs_camera=inv.astype(int),
                    obs_xy=prob.obs_xy[keep], obs_focal=prob.obs_focal[keep], fixed_marker=fixed_marker,
                    fixed_station=None, obs_lens=None if prob.obs_lens is None else prob.obs_lens[keep])
    out = bundle_adjust(sub, BAOptions(pixel_noise=pixel_noise, loss=loss, refine_extrinsics=True,
                                       extrinsics_trans_sigma=trans_sigma,
                                       extrinsics_rot_sigma_deg=float(np.degrees(rot_sigma)),
                                       covariance=False, max_nfev=max_nfev))
    per_cam: Dict[int, List[np.ndarray]] = {}
    prior = 0.0
    for k, c in enumerate(pair_cam):
        T = out.T_base_cams[k]
        per_cam.setdefault(int(c), []).append(T)
        d = geo.inverse(fixed[c]) @ T
        prior += (geo.rotation_angle(d[:3, :3]) / rot_sigma) ** 2 + float(
            np.sum(((T[:3, 3] - fixed[c][:3, 3]) / trans_sigma) ** 2))
    corners = float(np.sum(out.per_obs_rms_px ** 2) * 8 / pixel_noise ** 2)
    return {"per_cam": per_cam, "rms_px": float(out.rms_px_after), "cost_corners": corners, "cost_priors": prior,
            "cost": corners + prior}


def relaxed_step(fixed: np.ndarray, mean: np.ndarray, relax: float) -> np.ndarray:
    """``fixed`` moved ``relax`` times its way to ``mean`` (1: onto it; 2: over-relaxed, twice as far:
    the alternation's error shrinks by roughly half a round, so a step of 2 lands near its fixed
    point), on SE(3) as rotation vector and translation."""
    d = geo.inverse(fixed) @ mean
    r, t = geo.rvec_tvec_from_transform(d)
    return fixed @ geo.transform_from_rvec_tvec(relax * np.asarray(r), relax * np.asarray(t))


def solve_wiggle(res: BAResult, prob: BAProblem, start: Sequence[np.ndarray], wiggling: Sequence[bool],
                 rot_sigma: float, trans_sigma: float, rounds: int = 4, relax: float = 2.0, pixel_noise: float = 1.0,
                 loss: str = "linear", stations: Optional[Sequence[int]] = None, callback=None
                 ) -> Tuple[List[np.ndarray], List[Dict[str, object]]]:
    """The fixed poses of the wiggle model by alternation from ``start``: the per-frame poses given
    the fixed ones (:func:`wiggle_adjust`), then each camera's fixed pose moved to the mean of its
    per-frame poses (their optimum given them; :func:`relaxed_step`). Block coordinate descent on
    the joint problem. ``callback(round, fixed, fit)`` is called with each round's fit (a bench
    measures the walk). Returns (fixed poses, each round's fit)."""
    fixed = [np.asarray(T, dtype=float) for T in start]
    fits = []
    for r in range(rounds):
        f = wiggle_adjust(res, prob, fixed, wiggling, rot_sigma, trans_sigma, pixel_noise, loss, stations)
        if callback is not None:
            callback(r, fixed, f)
        fits.append(f)
        fixed = [relaxed_step(fixed[k], geo.average_transforms(f["per_cam"][k]), relax) if k in f["per_cam"]
                 else fixed[k] for k in range(len(fixed))]
    return fixed, fits


def declared_wiggle(ring: CameraRing) -> Optional[Tuple[List[bool], float, float]]:
    """(wiggling flag per camera, rotation rad, translation m) of the ring's declared wiggle; None when
    no camera declares one. The adjustment has one prior std for every camera: cameras declaring
    different values get the median of the declared ones (a warning says so)."""
    w = [c.wiggle for c in ring]
    declared = [v for v in w if v is not None]
    if not declared:
        return None
    rot = float(np.median([v[0] for v in declared]))
    trans = float(np.median([v[1] for v in declared]))
    if len(set(declared)) > 1:
        logger.warning("calibrate-ring: the cameras declare different wiggles %s: the wiggle stage uses their median, "
                       "%.4g rad / %.4g m, for every wiggling camera", sorted(set(declared)), rot, trans)
    return [v is not None for v in w], rot, trans


def _wiggle_stage(res: BAResult, names: List[str], wiggling: List[bool], rot: float, trans: float,
                  opts: CalibrationOptions) -> WiggleFit:
    """The wiggle stage on ``wiggle_max_frames`` robot poses of the rigid adjustment ``res``, from its
    answer; the fixed poses aligned back on the rigid answer's common motion (the gauge)."""
    import time

    c0 = time.process_time()
    prob = res.problem        # type: ignore[attr-defined]
    S = len(res.T_W_stations)
    n_frames = min(opts.wiggle_max_frames, max(3, opts.wiggle_max_poses // max(1, sum(wiggling))), S)
    stations = np.unique(np.linspace(0, S - 1, n_frames).round().astype(int))
    rigid = list(res.T_base_cams)
    fixed, fits = solve_wiggle(res, prob, rigid, wiggling, rot, trans, rounds=opts.wiggle_rounds,
                               relax=opts.wiggle_relax, pixel_noise=opts.wiggle_pixel_noise, loss=opts.wiggle_loss,
                               stations=stations)
    E = geo.average_transforms([rigid[k] @ geo.inverse(fixed[k]) for k in range(len(names))])
    fixed = [E @ T for T in fixed]
    in_st = np.isin(prob.obs_station, stations)
    cam_frames = {c: int(len(np.unique(prob.obs_station[in_st & (prob.obs_camera == k)])))
                  for k, c in enumerate(names)}
    rounds = [{k: float(f[k]) for k in ("cost", "cost_corners", "cost_priors", "rms_px")} for f in fits]
    return WiggleFit(fixed={c: fixed[k] for k, c in enumerate(names)},
                     wiggling=[c for c, w in zip(names, wiggling) if w], sigma=(rot, trans), frames=len(stations),
                     camera_frames=cam_frames, rounds=rounds, cpu_s=time.process_time() - c0)


# --- the whole -------------------------------------------------------------------------------------

def calibrate_ring(frames: Sequence[RingFrame], rough: CameraRing, sizes: MarkerSizes,
                   odometry: Optional[Sequence[Tuple[float, np.ndarray]]] = None,
                   marker_map: Optional[MarkerMap] = None,
                   options: Optional[CalibrationOptions] = None) -> RingCalibration:
    """Calibrate every camera's ``T_base_cam`` from a recording (see the module docstring).

    Args:
        frames: ring frames of the recording (any order; those without detections are skipped).
        rough: the ring with its rough extrinsics (and the intrinsics, used when a frame's camera
            carries no model of its own).
        sizes: marker sides (the scale).
        odometry: optional [(stamp, T_odom_base)] of the robot (gives base_link's heading).
        marker_map: optional known map (initialises the markers; a ``floor`` map gives the height).
        options: :class:`CalibrationOptions`.

    Raises:
        MeasurementError: too few usable frames or detections.
    """
    opts = options or CalibrationOptions()
    used = _select_frames(frames, opts.max_frames)
    if len(used) < 3:
        raise MeasurementError(f"ring calibration needs frames with markers: {len(used)} of {len(frames)} frames "
                               "have any detection")
    dets = _detections(used, rough, sizes, opts)
    names = rough.names
    X = {c: rough[c].T_base_cam.copy() for c in names}
    camera_frames = {c: len({d.frame for d in dets if d.camera == c and d.T_cam_marker is not None}) for c in names}
    # 2. each camera's own motion.
    motions = {c: relative_motions(camera_trajectory([d for d in dets if d.camera == c])) for c in names}
    calibrated = [c for c in names if camera_frames[c] >= opts.min_camera_frames and motions[c]]
    if not calibrated:
        raise MeasurementError(f"ring calibration: no camera saw markers in {opts.min_camera_frames} frames or more "
                               f"(frames with markers per camera: {camera_frames})")
    # 3. hand-eye, against the odometry or the cameras' mean motion.
    odo = _odometry_at(odometry, [f.stamp for f in used]) if odometry else {}
    has_odo = len(odo) >= 3
    rounds = 1 if has_odo else max(1, opts.handeye_rounds)
    for _ in range(rounds):
        if has_odo:
            Bm = {p: geo.inverse(odo[p[0]]) @ odo[p[1]] for c in calibrated for p in motions[c]
                  if p[0] in odo and p[1] in odo}
        else:
            per_pair: Dict[Tuple[int, int], List[np.ndarray]] = {}
            for c in calibrated:
                for p, A in motions[c].items():
                    per_pair.setdefault(p, []).append(X[c] @ A @ geo.inverse(X[c]))
            Bm = {p: _mean_motion(v) for p, v in per_pair.items() if len(v) >= (2 if len(calibrated) > 1 else 1)}
        for c in calibrated:
            ps = [p for p in motions[c] if p in Bm]
            if len(ps) < 3:
                continue
            Xc, _ = solve_hand_eye([Bm[p] for p in ps], [motions[c][p] for p in ps], X[c])
            # A hand-eye answer farther from the drawing than a drawing can be off (single-marker
            # poses of small, far markers are noisy, a flipped one slipped through) is not kept.
            dt, dr = geo.pose_distance(rough[c].T_base_cam, Xc)
            if dt <= opts.handeye_max_trans and dr <= np.radians(opts.handeye_max_rot_deg):
                X[c] = Xc
            else:
                logger.info("calibrate-ring: %s: hand-eye answer %.0f mm / %.1f deg from the rough value: not kept",
                            c, 1000 * dt, np.degrees(dr))
    handeye = {c: X[c].copy() for c in names}
    # 4. initial robot poses and markers, then the adjustment.
    T_W_s, T_W_m = _initial_world(dets, X, len(used), odo)
    if marker_map is not None:
        T_W_m = _markers_from_map(T_W_m, marker_map)
    res, keep = _adjust(dets, X, {c: rough[c].T_base_cam for c in names}, T_W_s, T_W_m, sizes, names, opts)
    X_ba = {c: res.T_base_cams[k] for k, c in enumerate(names)}
    # 4b. a declared wiggle: the fixed poses the cameras wiggle about (the rigid answer kept beside).
    declared = declared_wiggle(rough) if opts.wiggle == "auto" else None
    wfit = _wiggle_stage(res, names, *declared, opts) if declared is not None else None
    if wfit is not None:
        logger.info("calibrate-ring: wiggle (%s: %.3g rad / %.3g m) on %d frames, cost %s, %.0f s CPU",
                    ", ".join(wfit.wiggling), wfit.sigma[0], wfit.sigma[1], wfit.frames,
                    " -> ".join(f"{r['cost']:.1f}" for r in wfit.rounds), wfit.cpu_s)
    # Common motion of the ring against the rough values: the priors' pull only, taken out (what the
    # motion determines of it is put back below).
    D = geo.inverse(geo.average_transforms([X_ba[c] @ geo.inverse(rough[c].T_base_cam) for c in calibrated]))
    X_ba = {c: D @ T for c, T in X_ba.items()}
    stations = sorted(keep)
    T_W_st = [res.T_W_stations[i] @ geo.inverse(D) for i in range(len(res.T_W_stations))]
    turn_deg, travel, axis = motion_extent(T_W_st)
    # 5. base_link from the motion.
    G = np.eye(4)       # T_rig_base: the base frame in the rig's current base frame
    if has_odo:
        st_frames = [keep[i] for i in range(len(T_W_st))]
        pairs = [(a, b) for a in range(len(T_W_st)) for b in (a + 5, a + 15, a + 30) if b < len(T_W_st)
                 and st_frames[a] in odo and st_frames[b] in odo]
        if len(pairs) >= 3:
            Bs = [geo.inverse(T_W_st[a]) @ T_W_st[b] for a, b in pairs]           # rig motions
            Os = [geo.inverse(odo[st_frames[a]]) @ odo[st_frames[b]] for a, b in pairs]
            # Delta G = G O: hand-eye with the rig motion as "B" and odometry as "A".
            G, _ = solve_hand_eye(Bs, Os, np.eye(4), rot_noise=np.radians(0.2), trans_noise=0.01,
                                  prior_trans=(1.0, 1.0, 1e-4))
    elif turn_deg >= opts.min_turn_deg:
        R_tilt = _rotation_between(np.array([0.0, 0.0, 1.0]), axis if axis[2] >= 0 else -axis)
        c = _turn_centre(T_W_st, R_tilt[:, 2])
        G[:3, :3] = R_tilt
        if c is not None:
            G[:3, 3] = c
    floor_map = marker_map is not None and marker_map.frame_convention == "floor"
    if floor_map:
        G = _height_from_map(G, T_W_st, res, marker_map, [m for m in sorted(T_W_m)])
    G_inv = geo.inverse(G)
    final = {c: G_inv @ X_ba[c] for c in names}
    final_rigid = dict(final)
    if wfit is not None:
        # The fixed poses share the rigid answer's common motion (aligned in _wiggle_stage): the same D, G.
        final = {c: G_inv @ D @ wfit.fixed[c] for c in names}
    # Cameras the recording does not calibrate keep their rough values.
    for c in names:
        if c not in calibrated:
            final[c] = rough[c].T_base_cam.copy()
            final_rigid[c] = final[c]
    std = _camera_std(res, res.problem, names, calibrated, rough)
    std_rigid = dict(std)
    if wfit is not None:
        # The fixed pose is the mean of the per-frame poses: at least the declared wiggle over the
        # square root of the frames the camera was seen in (independent wiggles) on top.
        w_var = np.square([wfit.sigma[0]] * 3 + [wfit.sigma[1]] * 3)
        for c in wfit.wiggling:
            if c in calibrated:
                std[c] = np.sqrt(np.square(std[c]) + w_var / max(wfit.camera_frames[c], 1))
    rough_height = float(np.mean([rough[c].T_base_cam[2, 3] for c in names]))
    warnings = observability_warnings(turn_deg, travel, has_odo, floor_map, camera_frames, opts, rough_height)
    for w in warnings:
        logger.warning("calibrate-ring: %s", w)
    cams = [RingCamera(c.name, c.frame_id, c.model, final[c.name], c.namespace, tuple(float(v) for v in std[c.name]),
                       c.wiggle) for c in rough]
    rigid_ring = None
    if wfit is not None:
        rigid_ring = CameraRing([RingCamera(c.name, c.frame_id, c.model, final_rigid[c.name], c.namespace,
                                            tuple(float(v) for v in std_rigid[c.name])) for c in rough],
                                rough.base_frame)
    extra = {k: float(res.extra[k]) for k in ("residual_lag1_correlation", "std_inflation") if k in res.extra}
    if wfit is not None:
        extra.update(wiggle_frames=float(wfit.frames), wiggle_cpu_s=wfit.cpu_s,
                     wiggle_rms_px=wfit.rounds[-1]["rms_px"])
    return RingCalibration(ring=CameraRing(cams, rough.base_frame), std=std, warnings=warnings, handeye=handeye,
                           frames_used=len(stations), camera_frames=camera_frames, turn_deg=turn_deg,
                           travel_m=travel, rms_px_before=res.rms_px_before, rms_px_after=res.rms_px_after, ba=res,
                           station_stamps=[float(used[keep[i]].stamp) for i in stations],
                           extra=extra, rigid_ring=rigid_ring, wiggle=wfit)


def _initial_world(dets: Sequence[_Det], X: Dict[str, np.ndarray], n_frames: int, odo: Dict[int, np.ndarray]
                   ) -> Tuple[Dict[int, np.ndarray], Dict[int, np.ndarray]]:
    """Robot pose per frame and marker poses, grown in time order through the extrinsics ``X``."""
    by_frame: Dict[int, List[_Det]] = {}
    for d in dets:
        if d.T_cam_marker is not None:
            by_frame.setdefault(d.frame, []).append(d)
    T_W_s: Dict[int, np.ndarray] = {}
    T_W_m: Dict[int, np.ndarray] = {}
    last: Optional[int] = None
    for k in range(n_frames):
        ds = by_frame.get(k, [])
        ests = [T_W_m[d.marker] @ geo.inverse(X[d.camera] @ d.T_cam_marker) for d in ds if d.marker in T_W_m]
        if ests:
            T = _robust_mean(ests)
        elif last is None and ds:
            T = np.eye(4)
        elif last is not None and k in odo and last in odo:
            T = T_W_s[last] @ geo.inverse(odo[last]) @ odo[k]
        else:
            continue
        T_W_s[k] = T
        last = k
        for d in ds:
            if d.marker not in T_W_m:
                T_W_m[d.marker] = T @ X[d.camera] @ d.T_cam_marker
    return T_W_s, T_W_m


def _markers_from_map(T_W_m: Dict[int, np.ndarray], marker_map: MarkerMap) -> Dict[int, np.ndarray]:
    """The known map's markers expressed in W (fitted on the markers both have), others kept."""
    known = {e.marker_id: e.T_map_marker for e in marker_map}
    common = [m for m in T_W_m if m in known]
    if len(common) < 3:
        return T_W_m
    T_W_map = geo.rigid_fit([known[m][:3, 3] for m in common], [T_W_m[m][:3, 3] for m in common])
    return {m: (T_W_map @ known[m] if m in known else T) for m, T in T_W_m.items()}


def _problem(dets: Sequence[_Det], X: Dict[str, np.ndarray], T_W_s: Dict[int, np.ndarray],
             T_W_m: Dict[int, np.ndarray], sizes: MarkerSizes, names: List[str], mask: Optional[np.ndarray] = None):
    use = [d for i, d in enumerate(dets) if d.frame in T_W_s and d.marker in T_W_m and (mask is None or mask[i])]
    frames = sorted({d.frame for d in use})
    mids = sorted({d.marker for d in use})
    fi = {f: i for i, f in enumerate(frames)}
    mi = {m: i for i, m in enumerate(mids)}
    ci = {c: i for i, c in enumerate(names)}
    prob = BAProblem(
        T_W_markers=np.stack([T_W_m[m] for m in mids]), sizes=np.array([sizes(m) for m in mids]),
        T_W_stations=np.stack([T_W_s[f] for f in frames]), T_base_cams=np.stack([X[c] for c in names]),
        obs_marker=np.array([mi[d.marker] for d in use]), obs_station=np.array([fi[d.frame] for d in use]),
        obs_camera=np.array([ci[d.camera] for d in use]), obs_xy=np.stack([d.xy for d in use]),
        obs_focal=np.stack([d.focal for d in use]), obs_lens=np.stack([d.lens for d in use]),
        fixed_marker=0, fixed_station=None)
    return prob, frames, use


def _adjust(dets, X, X_prior, T_W_s, T_W_m, sizes, names, opts: CalibrationOptions
            ) -> Tuple[BAResult, Dict[int, int]]:
    """The adjustment from the extrinsics ``X``, priors centred on ``X_prior``; returns it and
    {station index: frame index}."""
    ba = BAOptions(pixel_noise=opts.pixel_noise, loss=opts.loss, refine_extrinsics=True, extrinsics_trans_sigma=opts.prior_trans,
                   extrinsics_rot_sigma_deg=opts.prior_rot_deg, max_nfev=100, covariance=False)
    prob, frames, use = _problem(dets, X, T_W_s, T_W_m, sizes, names)
    prob.T_base_cams_start = prob.T_base_cams
    prob.T_base_cams = np.stack([X_prior[c] for c in names])
    res = bundle_adjust(prob, ba)
    rms_first = res.rms_px_before
    bad = res.per_obs_rms_px > max(opts.max_obs_rms_px, 4.0 * float(np.median(res.per_obs_rms_px)))
    if np.any(bad):
        logger.info("calibrate-ring: %d of %d observations dropped (RMS > %.1f px) and adjusted again",
                    int(bad.sum()), len(bad), opts.max_obs_rms_px)
        X2 = {c: res.T_base_cams[k] for k, c in enumerate(names)}
        S2 = {f: res.T_W_stations[i] for i, f in enumerate(frames)}
        mids = sorted({d.marker for d in use})
        M2 = {m: res.T_W_markers[i] for i, m in enumerate(mids)}
        keep_ids = {id(d) for d, b in zip(use, bad) if not b}
        mask = np.array([id(d) in keep_ids for d in dets])
        prob2, frames, use = _problem(dets, X2, S2, M2, sizes, names, mask)
        # The priors stay centred where they were; the start is the first solution.
        prob2.T_base_cams_start = prob2.T_base_cams
        prob2.T_base_cams = np.stack([X_prior[c] for c in names])
        res = bundle_adjust(prob2, ba)
        res.rms_px_before = rms_first         # the RMS at the initialisation, before either pass
    res.marker_ids = sorted({d.marker for d in use})       # type: ignore[attr-defined]
    res.problem = prob2 if np.any(bad) else prob            # type: ignore[attr-defined]
    return res, {i: f for i, f in enumerate(frames)}


def _height_from_map(G: np.ndarray, T_W_st: Sequence[np.ndarray], res: BAResult, marker_map: MarkerMap,
                     _mids) -> np.ndarray:
    """Shift base_link along its z so that it sits on the known map's floor (z = 0) on average."""
    # The map frame in W from the adjusted markers: fit the markers' positions.
    known = {e.marker_id: e.T_map_marker[:3, 3] for e in marker_map}
    return _shift_to_floor(G, T_W_st, res, known)


def _shift_to_floor(G, T_W_st, res, known) -> np.ndarray:
    mids = getattr(res, "marker_ids", None)
    if mids is None:
        return G
    common = [k for k, m in enumerate(mids) if m in known]
    if len(common) < 3:
        return G
    T_map_W = geo.rigid_fit([res.T_W_markers[k][:3, 3] for k in common], [known[mids[k]] for k in common])
    z = [float((T_map_W @ T @ G)[2, 3]) for T in T_W_st]
    out = G.copy()
    out[:3, 3] -= float(np.mean(z)) * G[:3, 2]
    return out


def residual_lag1_correlation(r: np.ndarray, camera: np.ndarray, marker: np.ndarray, station: np.ndarray,
                              max_rho: float = 0.95) -> float:
    """Correlation of each observation's residual vector (N, 8) with the next observation of the
    same marker by the same camera (in station order): ``sum r_k . r_k+1 / sum |r_k|^2`` over all
    such pairs, clipped to [0, ``max_rho``]; 0 without pairs."""
    order = np.lexsort((station, marker, camera))
    same = (camera[order][1:] == camera[order][:-1]) & (marker[order][1:] == marker[order][:-1])
    a, b = r[order][:-1][same], r[order][1:][same]
    den = float(np.sum(a * a) + np.sum(b * b)) / 2.0
    if len(a) == 0 or den <= 0.0:
        return 0.0
    return float(np.clip(np.sum(a * b) / den, 0.0, max_rho))


def _camera_std(res: BAResult, prob: BAProblem, names: List[str], calibrated: List[str], rough: CameraRing
                ) -> Dict[str, np.ndarray]:
    """Per-camera std (optical frame, rotation rad then translation m) with the gauge fixed.

    The gauge (every camera moved by the same small motion g = (phi, rho) of the base frame, the
    robot poses by its inverse: ``w_c = -phi``, ``dt_c = [t_c]x phi - rho``) is fixed by "the
    cameras' mean motion is zero" (``K x = 0``, ``K Gm = I``) added as a stiff constraint to the
    corners' information at the solution (the priors left out: they only held the gauge), then
    inverted: how well each camera is known relative to the others.
    """
    from .bundle_adjustment import _Model

    out: Dict[str, np.ndarray] = {c: np.asarray(rough[c].extrinsics_std, dtype=float) for c in names}
    at = BAProblem(T_W_markers=res.T_W_markers, sizes=prob.sizes, T_W_stations=res.T_W_stations,
                   T_base_cams=res.T_base_cams, obs_marker=prob.obs_marker, obs_station=prob.obs_station,
                   obs_camera=prob.obs_camera, obs_xy=prob.obs_xy, obs_focal=prob.obs_focal,
                   fixed_marker=prob.fixed_marker, fixed_station=prob.fixed_station, obs_lens=prob.obs_lens)
    model = _Model(at, BAOptions(pixel_noise=1.0, refine_extrinsics=True))
    x0 = np.zeros(model.n_params)
    r_all = model.residuals(x0)
    w = np.zeros(model.n_res)
    w[: model.n_obs_res] = 1.0                      # the corners only (the priors left out)
    H = model.normal_equations(x0, r_all, w)[0]
    C = len(names)
    cols = np.concatenate([model.col_c[k] + np.arange(6) for k in range(C)])
    # The cameras' information with the markers and robot poses marginalised (a Schur complement:
    # H itself, 6 x 1,500 stations wide, is never dense), then the gauge constraint on the cameras.
    try:
        Hc = model.marginal_information(H, cols)
    except (RuntimeError, np.linalg.LinAlgError):
        return out
    K = np.zeros((6, 6 * C))
    for k in range(C):
        t = res.T_base_cams[k][:3, 3]
        K[:3, 6 * k:6 * k + 3] = -np.eye(3) / C
        K[3:, 6 * k:6 * k + 3] = -geo.skew(t) / C
        K[3:, 6 * k + 3:6 * k + 6] = -np.eye(3) / C
    scale = float(np.max(H.diagonal()))
    try:
        cov_cams = np.linalg.inv(Hc + scale * (K.T @ K))
    except np.linalg.LinAlgError:
        return out
    # Corner residuals in px (pixel_noise 1): the measured corner variance.
    n = model.n_obs_res
    r = r_all[:n]
    s2 = float(r @ r) / max(n - model.n_params, 1)
    # The covariance above assumes every frame's corner errors independent. A detector's are not:
    # the same marker seen again from nearly the same place errs nearly the same way (the rendered
    # lab: lag-1 correlation ~0.8, and the std was 2-3x too small). Inflate by the variance factor
    # of an AR(1) series, (1 + rho) / (1 - rho), rho measured from the residuals.
    rho = residual_lag1_correlation(r.reshape(-1, 8), prob.obs_camera, prob.obs_marker, prob.obs_station)
    inflation = (1.0 + rho) / (1.0 - rho)
    res.extra["residual_lag1_correlation"] = rho
    res.extra["std_inflation"] = float(np.sqrt(inflation))
    cov = camera_cov_in_optical_frames(inflation * s2 * cov_cams, res.T_base_cams)
    for k, c in enumerate(names):
        if c in calibrated:
            out[c] = np.sqrt(np.clip(np.diag(cov[6 * k:6 * k + 6, 6 * k:6 * k + 6]), 0.0, None))
    return out
