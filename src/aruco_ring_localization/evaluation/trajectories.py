"""Trajectories against a reference, on evo: TUM files, time association, alignment, APE.

A trajectory is evo's :class:`evo.core.trajectory.PoseTrajectory3D` (stamps in s, 4x4 poses
``T_frame_body``). What this module adds to evo is the package's conventions around it:

- :func:`read_tum` (evo's reader, errors that name the file and the line) and :func:`write_tum`
  (evo's writer, written atomically, with ``#`` header lines);
- :func:`associate`: evo's nearest-stamp association within ``max_dt`` s;
- :func:`fit_alignment`: ``none`` (the strict convention: the two files are compared in their
  own frames), ``se3`` (evo's Umeyama alignment, no scale) or ``se2`` (a rotation about z and a
  translation in x, y: evo's Umeyama alignment of the 2D positions; for a robot turning on the
  spot, where positions cannot fix the rotation, the circular mean of the yaw differences). evo
  has no SE(2) alignment of its own; ``evo_ape --project_to_plane xy --align`` runs the 3D
  Umeyama on flattened positions, which fails on a straight drive (rank-1 positions) where the
  2D fit is well defined. A fitted alignment absorbs any constant error of the estimate's frame:
  it is a diagnostic, never the headline;
- :func:`ape`: evo's absolute pose error (translation part, rotation angle), with median, p95,
  max, RMS and mean;
- planar pose pairs (:class:`MatchedPairs`, (x, y, yaw) in m and rad) for the paper's tables,
  which compare "only the rotation on the Z-axis of the robot" (paper §III-B), with signed
  per-axis errors (:func:`pose_errors`) that evo does not give.

Typical use (what ``aruco_ring evaluate`` does)::

    ref, est = read_tum("ref.tum"), read_tum("est.tum")
    ref, est = associate(ref, est, max_dt=0.05)
    alignment = fit_alignment(ref, est, "none")          # or "se2", "se3": diagnostics
    errors = ape(ref, alignment.apply(est))
    stats = errors.statistics()                          # median, p95, max, RMS, mean
"""
from __future__ import annotations

import copy
import io
import logging
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from evo.core import geometry as evo_geometry
from evo.core import metrics as evo_metrics
from evo.core import sync as evo_sync
from evo.core.trajectory import PoseTrajectory3D
from evo.tools import file_interface

from .. import geometry as geo
from ..errors import ConfigError, GeometryError
from ..fileio import atomic_write_text

logger = logging.getLogger(__name__)

ALIGNMENTS = ("none", "se2", "se3")


# --------------------------------------------------------------------------------------------
# Trajectories and TUM files
# --------------------------------------------------------------------------------------------
def trajectory(stamps: Sequence[float], poses) -> PoseTrajectory3D:
    """An evo trajectory from (N,) stamps and (N, 4, 4) poses or (N, 3) planar (x, y, yaw) poses.

    Raises GeometryError when the counts differ or there is no pose (evo has no empty trajectory).
    """
    s = np.asarray(stamps, dtype=np.float64).reshape(-1)
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim == 2 and p.shape[1] == 3:
        p = np.stack([geo.transform_from_se2(x, y, yaw) for x, y, yaw in p]) if len(p) else np.zeros((0, 4, 4))
    p = p.reshape(-1, 4, 4)
    if s.shape[0] != p.shape[0] or not len(s):
        raise GeometryError(f"trajectory: need as many stamps as poses, at least one; got {s.shape[0]} and {p.shape[0]}")
    return PoseTrajectory3D(poses_se3=[T.copy() for T in p], timestamps=s)


def planar(traj: PoseTrajectory3D) -> np.ndarray:
    """(N, 3) (x, y, yaw) of every pose (yaw: heading of the body's x axis in the x-y plane)."""
    return np.stack([geo.se2_from_transform(T) for T in traj.poses_se3])


def read_tum(path: str) -> PoseTrajectory3D:
    """Read a TUM trajectory (``t x y z qx qy qz qw`` per line, ``#`` comments) with evo's reader.

    Blank lines, runs of spaces and commas are accepted (evo's reader takes single spaces only).
    Stamps out of order are sorted (a warning; a repeated stamp keeps its first pose). Raises
    ConfigError naming the file and the line for a line without 8 numbers, a non-finite value
    or a quaternion whose norm is not close to 1.
    """
    try:
        with open(path, "r", encoding="utf-8") as handle:
            lines = handle.read().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read trajectory ({getattr(exc, 'strerror', None) or exc})", path=path) from None
    rows: List[str] = []
    numbers: List[int] = []
    for number, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = text.replace(",", " ").split()
        if len(fields) != 8:
            raise ConfigError(f"line {number}: expected 8 numbers 't x y z qx qy qz qw', found {len(fields)}",
                              path=path)
        rows.append(" ".join(fields))
        numbers.append(number)
    if not rows:
        raise ConfigError("no poses in the file", path=path)
    try:
        traj = file_interface.read_tum_trajectory_file(io.StringIO("\n".join(rows) + "\n"))
    except file_interface.FileInterfaceException:
        bad = next(k for k, row in enumerate(rows) if not _all_numbers(row))
        raise ConfigError(f"line {numbers[bad]}: not a number in {rows[bad]!r}", path=path) from None
    values = np.column_stack([traj.timestamps, traj.positions_xyz, traj.orientations_quat_wxyz])
    norm = np.linalg.norm(traj.orientations_quat_wxyz, axis=1)
    bad_rows = np.flatnonzero(~np.all(np.isfinite(values), axis=1) | ~((norm > 0.9) & (norm < 1.1)))
    if bad_rows.size:
        k = int(bad_rows[0])
        what = "non-finite value" if not np.all(np.isfinite(values[k])) else \
            f"quaternion norm {norm[k]:.4f} is not close to 1 (expected a unit quaternion qx qy qz qw)"
        raise ConfigError(f"line {numbers[k]}: {what} in {rows[k]!r}", path=path)
    if np.any(np.diff(traj.timestamps) <= 0):
        logger.warning("%s: stamps are not strictly increasing; sorting them", path)
        order = np.argsort(traj.timestamps, kind="stable")
        keep = np.ones(len(order), dtype=bool)
        keep[1:] = np.diff(traj.timestamps[order]) > 0
        traj.reduce_to_ids(order[keep])
    return traj


def _all_numbers(row: str) -> bool:
    try:
        [float(v) for v in row.split()]
    except ValueError:
        return False
    return True


def tum_text(traj: PoseTrajectory3D, header: Optional[str] = None) -> str:
    """The TUM text of a trajectory (evo's writer): ``#`` header lines, then one pose a line."""
    out = io.StringIO()
    file_interface.write_tum_trajectory_file(out, traj)
    head = "".join(f"# {line}\n" for line in header.splitlines()) if header else ""
    return head + out.getvalue()


def write_tum(path: str, traj: PoseTrajectory3D, header: Optional[str] = None) -> None:
    """Write a TUM trajectory file atomically (readable by evo and :func:`read_tum`)."""
    atomic_write_text(path, tum_text(traj, header), keep_backup=False)


# --------------------------------------------------------------------------------------------
# Association
# --------------------------------------------------------------------------------------------
def associate(ref: PoseTrajectory3D, est: PoseTrajectory3D, max_dt: float = 0.05,
              offset: float = 0.0) -> Tuple[PoseTrajectory3D, PoseTrajectory3D]:
    """Pair poses of equal stamps (evo's ``associate_trajectories``): copies, same length.

    Every pose of the shorter trajectory takes the pose of the other nearest in time, if within
    ``max_dt`` s; ``offset`` s is added to the estimate's stamps first (a clock offset).
    Raises ConfigError when no pair is found, with the two time ranges.
    """
    if max_dt <= 0:
        raise ConfigError(f"max_dt must be > 0 s, got {max_dt}")
    try:
        return evo_sync.associate_trajectories(ref, est, max_diff=max_dt, offset_2=offset,
                                               first_name="reference", snd_name="estimate")
    except evo_sync.SyncException:
        raise ConfigError(f"no estimate pose within {max_dt} s of a reference pose (reference "
                          f"{ref.timestamps[0]:.3f}..{ref.timestamps[-1]:.3f} s, estimate "
                          f"{est.timestamps[0] + offset:.3f}..{est.timestamps[-1] + offset:.3f} s)") from None


# --------------------------------------------------------------------------------------------
# Alignment
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Alignment:
    """``T_ref_est``: the estimate's frame in the reference's, as fitted by ``method``.

    Attributes:
        method: ``none`` (identity, the strict convention), ``se2`` or ``se3``.
        T_ref_est: (4, 4).
        n: pairs the fit used (0 for ``none``).
    """

    method: str
    T_ref_est: np.ndarray
    n: int = 0

    @property
    def fitted(self) -> bool:
        return self.method != "none"

    def apply(self, est: PoseTrajectory3D) -> PoseTrajectory3D:
        """A copy of ``est`` moved into the reference's frame (evo's ``transform``)."""
        out = copy.deepcopy(est)
        if self.fitted:
            out.transform(self.T_ref_est)
        return out

    def describe(self) -> str:
        """One line: the method, and for a fit its result and that it is a diagnostic."""
        if not self.fitted:
            return "alignment: none (the files are compared in their own frames: the strict convention)"
        T = self.T_ref_est
        rx, ry, rz = (np.degrees(a) for a in geo.rpy_from_matrix(T))
        return (f"alignment: {self.method} fitted over {self.n} pairs: translation ({T[0, 3]:+.4f}, "
                f"{T[1, 3]:+.4f}, {T[2, 3]:+.4f}) m, roll {rx:+.3f} pitch {ry:+.3f} yaw {rz:+.3f} deg "
                f"(DIAGNOSTIC: a fitted alignment absorbs any constant error of the estimate's frame; "
                f"the accuracy is --align none)")

    def as_dict(self) -> Dict[str, object]:
        T = self.T_ref_est
        rx, ry, rz = (float(np.degrees(a)) for a in geo.rpy_from_matrix(T))
        return {"method": self.method, "pairs": self.n, "x_m": float(T[0, 3]), "y_m": float(T[1, 3]),
                "z_m": float(T[2, 3]), "roll_deg": rx, "pitch_deg": ry, "yaw_deg": rz,
                "diagnostic": self.fitted}


def fit_alignment(ref: PoseTrajectory3D, est: PoseTrajectory3D, method: str = "none", n: int = -1,
                  min_spread: float = 0.05) -> Alignment:
    """Fit ``T_ref_est`` over associated trajectories (equal lengths), from the first ``n`` pairs.

    ``se3``: evo's Umeyama alignment of the positions (no scale). ``se2``: :func:`align_se2` of
    the planar poses (z, roll and pitch untouched). ``none``: identity. ``n`` = -1: all pairs.
    Raises GeometryError when the positions cannot determine the fit (e.g. SE(3) on collinear
    positions), ConfigError for an unknown method.
    """
    if method not in ALIGNMENTS:
        raise ConfigError(f"unknown alignment {method!r} (one of {', '.join(ALIGNMENTS)})")
    if ref.num_poses != est.num_poses:
        raise GeometryError(f"fit_alignment: associate the trajectories first ({ref.num_poses} vs {est.num_poses} poses)")
    count = ref.num_poses if n < 0 else max(1, min(n, ref.num_poses))
    if method == "none":
        return Alignment("none", np.eye(4), 0)
    if method == "se2":
        tx, ty, theta = align_se2(planar(est)[:count], planar(ref)[:count], min_spread=min_spread)
        return Alignment("se2", geo.transform_from_se2(tx, ty, theta), count)
    try:
        R, t, _ = evo_geometry.umeyama_alignment(est.positions_xyz[:count].T, ref.positions_xyz[:count].T)
    except evo_geometry.GeometryException as exc:
        raise GeometryError(f"SE(3) alignment over {count} pairs: {exc} (positions on a line or a point "
                            f"do not fix a 3D rotation; try --align se2)") from None
    return Alignment("se3", geo.make_transform(R, t), count)


def align_se2(source: np.ndarray, target: np.ndarray, min_spread: float = 0.05) -> np.ndarray:
    """Least-squares rigid 2D transform (x, y, theta) with ``target ~ R(theta) source + t``.

    evo's Umeyama alignment of the 2D positions (no scale). When the positions barely spread
    (within ``min_spread`` m RMS of their mean, e.g. a robot turning on the spot), the rotation
    is the circular mean of the yaw differences and the translation matches the means.

    Args:
        source: (N, 3) poses or (N, 2) positions to move (the estimate).
        target: (N, 3) or (N, 2) reference.

    Returns:
        (3,) ``(tx, ty, theta)``: the pose of the source frame in the target frame.
    """
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] not in (2, 3) or not len(src):
        raise GeometryError(f"align_se2: need two equal (N, 2|3) arrays, got {src.shape} and {dst.shape}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise GeometryError("align_se2: non-finite poses")
    ms, md = src[:, :2].mean(axis=0), dst[:, :2].mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((src[:, :2] - ms) ** 2, axis=1))))
    if spread >= min_spread:
        R, t, _ = evo_geometry.umeyama_alignment(src[:, :2].T, dst[:, :2].T)
        return np.array([t[0], t[1], float(np.arctan2(R[1, 0], R[0, 0]))])
    if src.shape[1] != 3:
        raise GeometryError(f"align_se2: positions spread only {spread:.3f} m and no yaw is given")
    theta = geo.circular_mean(geo.angle_diff(dst[:, 2], src[:, 2]))
    t = md - geo.rot_z(theta)[:2, :2] @ ms
    return np.array([t[0], t[1], theta])


def apply_se2(T: Sequence[float], poses: np.ndarray) -> np.ndarray:
    """Apply the 2D transform ``T = (tx, ty, theta)`` to (N, 3) poses (x, y, yaw)."""
    tx, ty, th = (float(v) for v in T)
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(th), np.sin(th)
    out = np.empty_like(p)
    out[:, 0] = c * p[:, 0] - s * p[:, 1] + tx
    out[:, 1] = s * p[:, 0] + c * p[:, 1] + ty
    out[:, 2] = geo.wrap_angle(p[:, 2] + th)
    return out


# --------------------------------------------------------------------------------------------
# Absolute pose error
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PoseErrors:
    """Per-pose errors of associated trajectories (evo's APE), estimate minus reference.

    Attributes:
        stamps: (N,) s (the reference's).
        position_m: (N,) Euclidean position error (m).
        rotation_deg: (N,) angle of the relative rotation (deg).
        xyz_m: (N, 3) signed position error in the reference frame's axes (m).
    """

    stamps: np.ndarray
    position_m: np.ndarray
    rotation_deg: np.ndarray
    xyz_m: np.ndarray

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def statistics(self) -> Dict[str, float]:
        """``n``, ``position_mm_{median,p95,max,rms,mean}``, ``rotation_deg_{median,p95,max,rms,mean}``."""
        out: Dict[str, float] = {"n": len(self)}
        for name, values in (("position_mm", 1000.0 * self.position_m), ("rotation_deg", self.rotation_deg)):
            out.update({f"{name}_median": float(np.median(values)), f"{name}_p95": float(np.percentile(values, 95)),
                        f"{name}_max": float(np.max(values)), f"{name}_rms": float(np.sqrt(np.mean(values ** 2))),
                        f"{name}_mean": float(np.mean(values))})
        return out


def ape(ref: PoseTrajectory3D, est: PoseTrajectory3D) -> PoseErrors:
    """evo's absolute pose error of associated trajectories: position (m) and rotation angle (deg)."""
    trans = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    trans.process_data((ref, est))
    rot = evo_metrics.APE(evo_metrics.PoseRelation.rotation_angle_deg)
    rot.process_data((ref, est))
    return PoseErrors(np.asarray(ref.timestamps, dtype=np.float64).copy(), np.asarray(trans.error, dtype=np.float64),
                      np.asarray(rot.error, dtype=np.float64), np.asarray(trans.E, dtype=np.float64).reshape(-1, 3))


def format_statistics(stats: Dict[str, float]) -> str:
    """Two lines for the console from :meth:`PoseErrors.statistics`."""
    return (f"position error: median {stats['position_mm_median']:.1f} mm ({stats['position_mm_median'] / 10:.2f} cm), "
            f"p95 {stats['position_mm_p95']:.1f} mm, max {stats['position_mm_max']:.1f} mm "
            f"(RMS {stats['position_mm_rms']:.1f} mm) over {stats['n']} poses\n"
            f"rotation error: median {stats['rotation_deg_median']:.3f} deg, p95 {stats['rotation_deg_p95']:.3f} deg, "
            f"max {stats['rotation_deg_max']:.3f} deg")


# --------------------------------------------------------------------------------------------
# Planar pose pairs (the paper's tables)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MatchedPairs:
    """Time-matched planar poses: ``ref[i]`` and ``est[i]`` at ``stamps[i]`` (s); (N, 3) each."""

    stamps: np.ndarray
    ref: np.ndarray
    est: np.ndarray

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    @classmethod
    def of(cls, ref: PoseTrajectory3D, est: PoseTrajectory3D) -> "MatchedPairs":
        """The planar poses of associated trajectories, on the reference's stamps."""
        return cls(np.asarray(ref.timestamps, dtype=np.float64).copy(), planar(ref), planar(est))

    def with_estimate(self, est: np.ndarray) -> "MatchedPairs":
        return MatchedPairs(self.stamps, self.ref, np.asarray(est, dtype=np.float64).reshape(-1, 3))


def pose_errors(ref: np.ndarray, est: np.ndarray) -> np.ndarray:
    """(N, 4) planar errors ``est - ref``: dx (m), dy (m), Euclidean (m), dyaw (rad, wrapped)."""
    r = np.asarray(ref, dtype=np.float64).reshape(-1, 3)
    e = np.asarray(est, dtype=np.float64).reshape(-1, 3)
    d = e[:, :2] - r[:, :2]
    return np.column_stack([d[:, 0], d[:, 1], np.hypot(d[:, 0], d[:, 1]), geo.wrap_angle(e[:, 2] - r[:, 2])])


def error_statistics(errors: np.ndarray) -> Dict[str, float]:
    """Position (cm) and |yaw| (deg) statistics of (N, 4) :func:`pose_errors`."""
    e = np.asarray(errors, dtype=np.float64).reshape(-1, 4)
    if not len(e):
        return {"n": 0}
    d = 100.0 * e[:, 2]
    y = np.degrees(np.abs(e[:, 3]))
    return {"n": int(len(e)),
            "position_cm_median": float(np.median(d)), "position_cm_mean": float(np.mean(d)),
            "position_cm_rms": float(np.sqrt(np.mean(d ** 2))), "position_cm_max": float(np.max(d)),
            "yaw_deg_mean_abs": float(np.mean(y)), "yaw_deg_rms": float(np.sqrt(np.mean(y ** 2))),
            "yaw_deg_max_abs": float(np.max(y))}
