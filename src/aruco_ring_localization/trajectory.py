"""Trajectories against a reference: TUM files, time matching, SE(2) alignment, stop errors, tables.

The trajectory half of the evaluation (``evaluation.py`` holds the map errors). Everything works
on the ground plane: poses are (x, y, yaw) in m and rad, as the paper compares them (§III-B:
"only the rotation on the Z-axis of the robot is considered").

Typical use (what ``aruco_ring evaluate``, the comparison node and the demo do)::

    ref, est = read_tum("ref.tum"), read_tum("est.tum")
    pairs = match(ref, est, max_dt=0.05)                 # time-matched (x, y, yaw) pairs
    T = align_se2(pairs.est, pairs.ref)                  # or None: no alignment
    pairs = pairs.with_estimate(apply_se2(T, pairs.est))
    stops = detect_stops(pairs.stamps, pairs.ref, min_duration=2.0)
    rows = stop_errors(pairs, stops)                     # one StopError per stop
    print(position_table_markdown(rows))                 # Table I
    print(orientation_table_markdown(rows))              # Table II

Errors are ``estimate - reference`` expressed in the reference frame: x, y (m), Euclidean (m)
and yaw (rad, wrapped to [-pi, pi)).
"""
from __future__ import annotations

import csv
import io
import logging
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

from . import geometry as geo
from .errors import ConfigError, GeometryError
from .fileio import atomic_write_text

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Trajectories and TUM files
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Trajectory:
    """A timed sequence of poses.

    Attributes:
        stamps: (N,) seconds, strictly increasing after :meth:`sorted`.
        poses: (N, 4, 4) poses ``T_frame_body`` (e.g. ``T_map_base``).
    """

    stamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        s = np.asarray(self.stamps, dtype=np.float64).reshape(-1)
        p = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if s.shape[0] != p.shape[0]:
            raise GeometryError(f"trajectory: {s.shape[0]} stamps but {p.shape[0]} poses")
        object.__setattr__(self, "stamps", s)
        object.__setattr__(self, "poses", p)

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    @classmethod
    def from_se2(cls, stamps: Sequence[float], se2: np.ndarray, z: float = 0.0) -> "Trajectory":
        """Build from (N,) stamps and (N, 3) (x, y, yaw) poses at height ``z``."""
        se2 = np.asarray(se2, dtype=np.float64).reshape(-1, 3)
        poses = np.stack([geo.transform_from_se2(x, y, yaw, z) for x, y, yaw in se2]) if len(se2) else np.zeros((0, 4, 4))
        return cls(np.asarray(stamps, dtype=np.float64), poses)

    @property
    def se2(self) -> np.ndarray:
        """(N, 3) (x, y, yaw) of every pose."""
        if not len(self):
            return np.zeros((0, 3))
        return np.stack([geo.se2_from_transform(T) for T in self.poses])

    def sorted(self) -> "Trajectory":
        """The same poses in increasing time; duplicated stamps keep the first pose."""
        order = np.argsort(self.stamps, kind="stable")
        s, p = self.stamps[order], self.poses[order]
        keep = np.ones(len(s), dtype=bool)
        keep[1:] = np.diff(s) > 0
        return Trajectory(s[keep], p[keep])


def read_tum(path: str) -> Trajectory:
    """Read a TUM trajectory file (``t x y z qx qy qz qw`` per line, ``#`` comments).

    Raises ConfigError naming the file and the line for a malformed line or a bad quaternion.
    """
    try:
        with open(path, "r", encoding="utf-8") as handle:
            lines = handle.readlines()
    except OSError as exc:
        raise ConfigError(f"cannot read trajectory ({exc.strerror})", path=path) from None
    stamps: List[float] = []
    poses: List[np.ndarray] = []
    for number, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = text.replace(",", " ").split()
        if len(fields) != 8:
            raise ConfigError(f"line {number}: expected 8 numbers 't x y z qx qy qz qw', found {len(fields)}",
                              path=path)
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise ConfigError(f"line {number}: not a number in {text!r}", path=path) from None
        if not np.all(np.isfinite(values)):
            raise ConfigError(f"line {number}: non-finite value in {text!r}", path=path)
        try:
            T = geo.transform_from_translation_quaternion(values[1:4], values[4:8], name=f"line {number}")
        except GeometryError as exc:
            raise ConfigError(f"line {number}: {exc}", path=path) from None
        stamps.append(values[0])
        poses.append(T)
    if not stamps:
        raise ConfigError("no poses in the file", path=path)
    traj = Trajectory(np.array(stamps), np.stack(poses))
    if np.any(np.diff(traj.stamps) <= 0):
        logger.warning("%s: stamps are not strictly increasing; sorting them", path)
        traj = traj.sorted()
    return traj


def tum_text(traj: Trajectory, header: Optional[str] = None) -> str:
    """The TUM text of a trajectory: ``#`` header lines, then :func:`evaluation.tum_lines`."""
    from .evaluation import tum_lines  # the package's one TUM line format (shared with `aruco_ring localize`)

    head = "".join(f"# {line}\n" for line in header.splitlines()) if header else ""
    return head + "".join(line + "\n" for line in tum_lines(traj.stamps, traj.poses))


def write_tum(path: str, traj: Trajectory, header: Optional[str] = None) -> None:
    """Write a TUM trajectory file atomically (readable by ``evo``)."""
    atomic_write_text(path, tum_text(traj, header), keep_backup=False)


# --------------------------------------------------------------------------------------------
# Time matching
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MatchedPairs:
    """Time-matched planar poses: ``ref[i]`` and ``est[i]`` at ``stamps[i]`` (s); (N, 3) each."""

    stamps: np.ndarray
    ref: np.ndarray
    est: np.ndarray

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def with_estimate(self, est: np.ndarray) -> "MatchedPairs":
        return MatchedPairs(self.stamps, self.ref, np.asarray(est, dtype=np.float64).reshape(-1, 3))


def _interp_se2(stamps: np.ndarray, se2: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear interpolation of (x, y, yaw) at times ``t`` (yaw unwrapped first)."""
    yaw = np.unwrap(se2[:, 2])
    return np.stack([np.interp(t, stamps, se2[:, 0]), np.interp(t, stamps, se2[:, 1]),
                     geo.wrap_angle(np.interp(t, stamps, yaw))], axis=1)


def match(ref: Trajectory, est: Trajectory, max_dt: float = 0.05, method: str = "nearest") -> MatchedPairs:
    """Pair every estimate pose with the reference at the same time.

    Args:
        ref: reference trajectory (ground truth, gmapping).
        est: estimated trajectory.
        max_dt: s; ``nearest``: largest stamp difference accepted; ``interpolate``: largest
            gap between the two reference poses around the estimate's stamp.
        method: ``nearest`` (the reference pose closest in time, as evo's ``--t_max_diff``) or
            ``interpolate`` (the reference linearly interpolated at the estimate's stamp).

    Returns:
        MatchedPairs on the estimate's stamps that found a partner (possibly empty).
    """
    if method not in ("nearest", "interpolate"):
        raise ConfigError(f"unknown time matching method {method!r} (nearest or interpolate)")
    if max_dt <= 0:
        raise ConfigError(f"max_dt must be > 0 s, got {max_dt}")
    ref, est = ref.sorted(), est.sorted()
    rs, es = ref.stamps, est.stamps
    ref_se2, est_se2 = ref.se2, est.se2
    if not len(rs) or not len(es):
        return MatchedPairs(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
    idx = np.searchsorted(rs, es)
    lo = np.clip(idx - 1, 0, len(rs) - 1)
    hi = np.clip(idx, 0, len(rs) - 1)
    if method == "nearest":
        pick = np.where(np.abs(rs[lo] - es) <= np.abs(rs[hi] - es), lo, hi)
        ok = np.abs(rs[pick] - es) <= max_dt
        r = ref_se2[pick[ok]]
    else:
        inside = (es >= rs[0]) & (es <= rs[-1])
        ok = inside & ((rs[hi] - rs[lo]) <= max_dt)
        r = _interp_se2(rs, ref_se2, es[ok]) if np.any(ok) else np.zeros((0, 3))
    logger.debug("matched %d of %d estimate poses (%s, max_dt %.3f s)", int(ok.sum()), len(es), method, max_dt)
    return MatchedPairs(es[ok], r, est_se2[ok])


# --------------------------------------------------------------------------------------------
# SE(2) alignment
# --------------------------------------------------------------------------------------------
def align_se2(source: np.ndarray, target: np.ndarray, min_spread: float = 0.05) -> np.ndarray:
    """Least-squares rigid 2D transform (x, y, theta) with ``target ~ R(theta) source + t``.

    Closed form (Umeyama / Kabsch in 2D, no scale) over the positions of matched poses. When the
    positions barely spread (all within ``min_spread`` m RMS of their mean, e.g. a robot turning
    on the spot), the rotation is undetermined by positions; it is then the circular mean of the
    yaw differences and the translation matches the means.

    Args:
        source: (N, 3) or (N, 2) poses/positions to move (the estimate).
        target: (N, 3) or (N, 2) reference.
        min_spread: m.

    Returns:
        (3,) ``(tx, ty, theta)``: the pose of the source frame in the target frame.
    """
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] not in (2, 3) or not len(src):
        raise GeometryError(f"align_se2: need two equal (N, 2|3) arrays, got {src.shape} and {dst.shape}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise GeometryError("align_se2: non-finite poses")
    ps, pd = src[:, :2], dst[:, :2]
    ms, md = ps.mean(axis=0), pd.mean(axis=0)
    a, b = ps - ms, pd - md
    spread = float(np.sqrt(np.mean(np.sum(a * a, axis=1))))
    if spread >= min_spread:
        # maximise sum b_i . R a_i: theta = atan2(sum a x b, sum a . b)
        cross = float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
        dot = float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
        theta = float(np.arctan2(cross, dot))
    elif src.shape[1] == 3:
        theta = geo.circular_mean(geo.angle_diff(dst[:, 2], src[:, 2]))
    else:
        raise GeometryError(f"align_se2: positions spread only {spread:.3f} m and no yaw is given")
    c, s = np.cos(theta), np.sin(theta)
    t = md - np.array([[c, -s], [s, c]]) @ ms
    return np.array([t[0], t[1], geo.wrap_angle(theta)])


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


def compose_se2(a: Sequence[float], b: Sequence[float]) -> np.ndarray:
    """``a * b`` for 2D poses (x, y, theta)."""
    return apply_se2(a, np.asarray(b, dtype=np.float64).reshape(1, 3))[0]


def invert_se2(a: Sequence[float]) -> np.ndarray:
    """Inverse of a 2D pose (x, y, theta)."""
    x, y, th = (float(v) for v in a)
    c, s = np.cos(th), np.sin(th)
    return np.array([-(c * x + s * y), s * x - c * y, geo.wrap_angle(-th)])


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------
def pose_errors(ref: np.ndarray, est: np.ndarray) -> np.ndarray:
    """(N, 4) errors ``est - ref``: dx (m), dy (m), Euclidean (m), dyaw (rad, wrapped)."""
    r = np.asarray(ref, dtype=np.float64).reshape(-1, 3)
    e = np.asarray(est, dtype=np.float64).reshape(-1, 3)
    d = e[:, :2] - r[:, :2]
    return np.column_stack([d[:, 0], d[:, 1], np.hypot(d[:, 0], d[:, 1]), geo.wrap_angle(e[:, 2] - r[:, 2])])


def error_statistics(errors: np.ndarray) -> Dict[str, float]:
    """Position (cm) and yaw (deg) statistics of (N, 4) :func:`pose_errors`."""
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


# --------------------------------------------------------------------------------------------
# Stops
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Stop:
    """An interval [start, end] (s) during which the reference stood still."""

    start: float
    end: float

    @property
    def duration(self) -> float:
        return self.end - self.start


def detect_stops(stamps: np.ndarray, ref: np.ndarray, min_duration: float = 2.0, pos_tol: float = 0.01,
                 yaw_tol: float = np.radians(0.5), settle: float = 0.0) -> List[Stop]:
    """Intervals where the reference pose stays within a tolerance for at least ``min_duration``.

    A stop grows while every pose stays within ``pos_tol`` m and ``yaw_tol`` rad of the pose that
    opened it. ``settle`` s are cut from the start of each stop (a filter catching up after the
    motion) and the stop is kept only if ``min_duration`` remains.

    Args:
        stamps: (N,) increasing seconds.
        ref: (N, 3) reference poses.
    """
    s = np.asarray(stamps, dtype=np.float64).reshape(-1)
    r = np.asarray(ref, dtype=np.float64).reshape(-1, 3)
    stops: List[Stop] = []
    i, n = 0, len(s)
    while i < n:
        j = i + 1
        while j < n and np.hypot(*(r[j, :2] - r[i, :2])) <= pos_tol and abs(geo.angle_diff(r[j, 2], r[i, 2])) <= yaw_tol:
            j += 1
        start, end = s[i] + settle, s[j - 1]
        if end - start >= min_duration:
            stops.append(Stop(float(start), float(end)))
        i = j
    return stops


@dataclass(frozen=True)
class StopError:
    """The errors at one stop (the rows of Tables I and II).

    Attributes:
        label: row name ("1", "P3", ...).
        ref: (3,) reference pose (x m, y m, yaw rad): the median over the stop.
        est: (3,) estimated pose over the stop (median, yaw by circular mean).
        n: matched poses averaged.
        start, end: s.
    """

    label: str
    ref: np.ndarray
    est: np.ndarray
    n: int = 1
    start: float = float("nan")
    end: float = float("nan")
    extra: Dict[str, float] = field(default_factory=dict)

    @property
    def errors(self) -> np.ndarray:
        """(4,) dx m, dy m, Euclidean m, dyaw rad."""
        return pose_errors(self.ref, self.est)[0]


def _robust_pose(p: np.ndarray) -> np.ndarray:
    return np.array([float(np.median(p[:, 0])), float(np.median(p[:, 1])), geo.circular_mean(p[:, 2])])


def stop_errors(pairs: MatchedPairs, stops: Iterable[Stop], labels: Optional[Sequence[str]] = None) -> List[StopError]:
    """One :class:`StopError` per stop that has matched poses (median of the poses inside it)."""
    rows: List[StopError] = []
    for k, stop in enumerate(stops):
        inside = (pairs.stamps >= stop.start) & (pairs.stamps <= stop.end)
        if not np.any(inside):
            logger.warning("stop %d [%.2f, %.2f] s has no matched estimate; skipped", k + 1, stop.start, stop.end)
            continue
        label = labels[k] if labels is not None and k < len(labels) else str(k + 1)
        rows.append(StopError(label, _robust_pose(pairs.ref[inside]), _robust_pose(pairs.est[inside]),
                              int(inside.sum()), stop.start, stop.end))
    return rows


def summarize(rows: Sequence[StopError]) -> Dict[str, float]:
    """Statistics over stops: position error (cm) median/mean/max, |yaw| error (deg) mean/max."""
    if not rows:
        return {"n": 0}
    stats = error_statistics(np.stack([r.errors for r in rows]))
    return stats


# --------------------------------------------------------------------------------------------
# Tables (markdown and CSV)
# --------------------------------------------------------------------------------------------
def position_table_markdown(rows: Sequence[StopError], title: str = "Table I. Errors in position",
                            reference_name: str = "reference") -> str:
    """The paper's Table I: absolute x, y and Euclidean error per position (cm), plus statistics."""
    lines = [f"**{title}** (estimate against {reference_name}, cm)", "",
             "| Position | X error (cm) | Y error (cm) | Euclidean error (cm) | Reference x, y (m) |",
             "|---:|---:|---:|---:|---:|"]
    for r in rows:
        dx, dy, d, _ = r.errors
        lines.append(f"| {r.label} | {100 * abs(dx):.3f} | {100 * abs(dy):.3f} | {100 * d:.3f} | "
                     f"{r.ref[0]:.3f}, {r.ref[1]:.3f} |")
    s = summarize(rows)
    if s.get("n"):
        lines += ["", f"Median Euclidean error {s['position_cm_median']:.3f} cm, mean {s['position_cm_mean']:.3f} cm, "
                      f"max {s['position_cm_max']:.3f} cm over {s['n']} positions."]
    return "\n".join(lines) + "\n"


def orientation_table_markdown(rows: Sequence[StopError], title: str = "Table II. Errors in orientation",
                               reference_name: str = "reference") -> str:
    """The paper's Table II: signed yaw error per orientation (deg), plus statistics."""
    lines = [f"**{title}** (estimate against {reference_name}, degrees)", "",
             "| Orientation | Reference yaw (deg) | Estimated yaw (deg) | Error (deg) |",
             "|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r.label} | {np.degrees(r.ref[2]):.2f} | {np.degrees(r.est[2]):.2f} | "
                     f"{np.degrees(r.errors[3]):+.3f} |")
    s = summarize(rows)
    if s.get("n"):
        lines += ["", f"Mean |error| {s['yaw_deg_mean_abs']:.3f} deg, max |error| {s['yaw_deg_max_abs']:.3f} deg "
                      f"over {s['n']} orientations."]
    return "\n".join(lines) + "\n"


CSV_COLUMNS = ("label", "start_s", "end_s", "n", "ref_x_m", "ref_y_m", "ref_yaw_deg", "est_x_m", "est_y_m",
               "est_yaw_deg", "err_x_cm", "err_y_cm", "err_euclidean_cm", "err_yaw_deg")


def stops_csv(rows: Sequence[StopError]) -> str:
    """CSV of the stop errors (signed errors, estimate - reference), one row per stop."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for r in rows:
        dx, dy, d, dyaw = r.errors
        writer.writerow([r.label, f"{r.start:.3f}", f"{r.end:.3f}", r.n,
                         f"{r.ref[0]:.5f}", f"{r.ref[1]:.5f}", f"{np.degrees(r.ref[2]):.4f}",
                         f"{r.est[0]:.5f}", f"{r.est[1]:.5f}", f"{np.degrees(r.est[2]):.4f}",
                         f"{100 * dx:.4f}", f"{100 * dy:.4f}", f"{100 * d:.4f}", f"{np.degrees(dyaw):.4f}"])
    return out.getvalue()


def pairs_csv(pairs: MatchedPairs) -> str:
    """CSV of every matched pair and its errors."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(("t", "ref_x_m", "ref_y_m", "ref_yaw_deg", "est_x_m", "est_y_m", "est_yaw_deg",
                     "err_x_cm", "err_y_cm", "err_euclidean_cm", "err_yaw_deg"))
    errs = pose_errors(pairs.ref, pairs.est)
    for t, r, e, er in zip(pairs.stamps, pairs.ref, pairs.est, errs):
        writer.writerow([f"{t:.6f}", f"{r[0]:.5f}", f"{r[1]:.5f}", f"{np.degrees(r[2]):.4f}",
                         f"{e[0]:.5f}", f"{e[1]:.5f}", f"{np.degrees(e[2]):.4f}",
                         f"{100 * er[0]:.4f}", f"{100 * er[1]:.4f}", f"{100 * er[2]:.4f}", f"{np.degrees(er[3]):.4f}"])
    return out.getvalue()


def write_tables(out_dir: str, position_rows: Sequence[StopError], orientation_rows: Sequence[StopError],
                 reference_name: str = "reference", prefix: str = "") -> Dict[str, str]:
    """Write ``table1.md``/``table1.csv`` and ``table2.md``/``table2.csv`` into ``out_dir``.

    Returns {name: path}. An empty row list skips its table.
    """
    import os

    paths: Dict[str, str] = {}
    if position_rows:
        paths["table1_md"] = os.path.join(out_dir, prefix + "table1.md")
        atomic_write_text(paths["table1_md"], position_table_markdown(position_rows, reference_name=reference_name),
                          keep_backup=False)
        paths["table1_csv"] = os.path.join(out_dir, prefix + "table1.csv")
        atomic_write_text(paths["table1_csv"], stops_csv(position_rows), keep_backup=False)
    if orientation_rows:
        paths["table2_md"] = os.path.join(out_dir, prefix + "table2.md")
        atomic_write_text(paths["table2_md"], orientation_table_markdown(orientation_rows, reference_name=reference_name),
                          keep_backup=False)
        paths["table2_csv"] = os.path.join(out_dir, prefix + "table2.csv")
        atomic_write_text(paths["table2_csv"], stops_csv(orientation_rows), keep_backup=False)
    return paths


# Paper §III, Tables I and II (gmapping against the proposed system), for side-by-side reports.
PAPER_TABLE1_CM: Tuple[Tuple[float, float, float], ...] = (
    (2.015, 4.969, 5.363), (1.255, 1.480, 1.941), (0.499, 3.132, 3.172), (2.521, 1.812, 3.104),
    (0.302, 0.221, 0.374), (2.870, 0.609, 2.932), (7.425, 1.556, 7.587), (0.257, 0.652, 0.701),
    (2.01, 2.061, 2.881), (6.611, 2.452, 7.051), (16.135, 6.152, 17.268), (3.899, 2.478, 4.619),
    (0.144, 1.468, 1.475), (1.346, 0.461, 1.423), (11.463, 5.827, 12.859))
PAPER_TABLE2_DEG: Tuple[float, ...] = (0.076, -4.501, 0.490, 1.359, -3.435, -3.169, 1.157, 1.028)
