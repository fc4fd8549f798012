"""Figures of the paper's experiment (matplotlib, Agg backend: no display needed).

All functions draw in one planar frame (the marker map frame ``map`` in the demo), in metres,
and write a PNG. Inputs are plain arrays so the demo, ``aruco_ring evaluate`` and the
comparison node can share them:

- :func:`plot_map`: the marker map (true and estimated markers, ids), the plate and the room;
- :func:`plot_positions`: the paper's Fig. 8, true and estimated positions on the plate;
- :func:`plot_camera_estimates`: Fig. 9, per-camera estimates against the fused pose;
- :func:`plot_orientations`: Fig. 10, the orientations true and estimated;
- :func:`plot_trajectory`: a trajectory against its reference, with the error over time.
"""
from __future__ import annotations

import logging
import os
from typing import Dict, Mapping, Optional, Sequence, Tuple

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)

logger = logging.getLogger(__name__)

TRUE_COLOUR = "tab:blue"
EST_COLOUR = "tab:red"


def _save(fig, path: str) -> str:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    logger.debug("wrote %s", path)
    return path


def _polygon(ax, poly: Optional[np.ndarray], **kwargs) -> None:
    if poly is None:
        return
    p = np.asarray(poly, dtype=float).reshape(-1, 2)
    closed = np.vstack([p, p[:1]])
    ax.plot(closed[:, 0], closed[:, 1], **kwargs)


def _robot_outline(ax, pose: Sequence[float], footprint: Tuple[float, float], **kwargs) -> None:
    x, y, yaw = pose
    L, W = footprint
    c = np.array([[L / 2, W / 2], [-L / 2, W / 2], [-L / 2, -W / 2], [L / 2, -W / 2]])
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    _polygon(ax, c @ R.T + (x, y), **kwargs)


def plot_map(path: str, markers_est: Mapping[int, np.ndarray], markers_true: Optional[Mapping[int, np.ndarray]] = None,
             plate: Optional[np.ndarray] = None, room: Optional[np.ndarray] = None,
             robot_pose: Optional[Sequence[float]] = None, footprint: Tuple[float, float] = (0.98, 0.61),
             title: str = "Marker map") -> str:
    """Top view of a marker map.

    Args:
        markers_est: {id: (4, 3) marker corners} of the estimated map (m, plotting frame).
        markers_true: the same for the truth, drawn underneath.
        plate: (4, 2) plate corners; room: (K, 2) room outline.
        robot_pose: (x, y, yaw) of the robot during mapping (drawn with its footprint).
    """
    fig, ax = plt.subplots(figsize=(8, 6.5))
    _polygon(ax, room, color="0.4", lw=1.5, label="room")
    _polygon(ax, plate, color="k", lw=2.0, label="plate")
    if robot_pose is not None:
        _robot_outline(ax, robot_pose, footprint, color="tab:green", lw=1.5, label="robot (mapping)")
    for label, markers, colour, lw in (("true markers", markers_true, TRUE_COLOUR, 5.0),
                                       ("mapped markers", markers_est, EST_COLOUR, 2.0)):
        if not markers:
            continue
        first = True
        for mid, corners in markers.items():
            c = np.asarray(corners, dtype=float)
            # the marker seen from above: a segment through its top corners, a tick for its normal
            a, b = c[0, :2], c[1, :2]
            ax.plot([a[0], b[0]], [a[1], b[1]], color=colour, lw=lw, solid_capstyle="butt",
                    label=label if first else None)
            first = False
            if colour == EST_COLOUR:
                centre = c.mean(axis=0)
                n = np.cross(c[1] - c[0], c[3] - c[0])
                n2 = n[:2] / (np.linalg.norm(n[:2]) + 1e-12)
                ax.annotate("", xy=centre[:2] + 0.35 * n2, xytext=centre[:2],
                            arrowprops=dict(arrowstyle="->", color=colour, lw=1))
                ax.text(centre[0] - 0.25 * n2[0], centre[1] - 0.25 * n2[1], str(mid), fontsize=9,
                        ha="center", va="center")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return _save(fig, path)


def plot_positions(path: str, true_xy: np.ndarray, est_xy: np.ndarray, plate: Optional[np.ndarray] = None,
                   labels: Optional[Sequence[str]] = None, errors_cm: Optional[Sequence[float]] = None,
                   title: str = "Positions: true and estimated (Fig. 8)") -> str:
    """The paper's Fig. 8: true (ground truth) and estimated positions on the plate.

    Args:
        true_xy, est_xy: (N, 2) m. labels: N names. errors_cm: N errors printed beside each.
    """
    t = np.asarray(true_xy, dtype=float).reshape(-1, 2)
    e = np.asarray(est_xy, dtype=float).reshape(-1, 2)
    fig, (ax, axz) = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [3, 2]})
    _polygon(ax, plate, color="k", lw=2.0, label="plate")
    ax.scatter(t[:, 0], t[:, 1], marker="o", s=60, facecolors="none", edgecolors=TRUE_COLOUR, label="true")
    ax.scatter(e[:, 0], e[:, 1], marker="x", s=40, color=EST_COLOUR, label="estimated")
    for k in range(len(t)):
        name = labels[k] if labels is not None else str(k + 1)
        extra = f" ({errors_cm[k]:.2f} cm)" if errors_cm is not None else ""
        ax.annotate(name + extra, t[k], textcoords="offset points", xytext=(6, 6), fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    # the errors are mm-sized: show the error vectors magnified on the right
    d = 100.0 * (e - t)
    axz.axhline(0, color="0.7", lw=0.8)
    axz.axvline(0, color="0.7", lw=0.8)
    axz.scatter(d[:, 0], d[:, 1], color=EST_COLOUR, marker="x")
    for k in range(len(d)):
        axz.annotate(labels[k] if labels is not None else str(k + 1), d[k], textcoords="offset points",
                     xytext=(4, 4), fontsize=8)
    lim = max(1.0, float(np.max(np.abs(d))) * 1.2) if len(d) else 1.0
    axz.set_xlim(-lim, lim)
    axz.set_ylim(-lim, lim)
    axz.set_aspect("equal")
    axz.set_xlabel("x error (cm)")
    axz.set_ylabel("y error (cm)")
    axz.set_title("estimate - true")
    axz.grid(True, alpha=0.3)
    return _save(fig, path)


def plot_camera_estimates(path: str, cases: Sequence[Dict[str, object]],
                          title: str = "Per-camera estimates and the fused pose (Fig. 9)") -> str:
    """The paper's Fig. 9: at a few positions, each camera's robot-pose estimate vs the fused one.

    Args:
        cases: dicts with ``label`` (str), ``true`` (x, y, yaw), ``fused`` (x, y, yaw) and
            ``cameras`` ({camera name: (x, y, yaw)}), all in m/rad of the same frame.
    """
    n = max(1, len(cases))
    fig, axes = plt.subplots(1, n, figsize=(5.0 * n, 5.0), squeeze=False)
    for ax, case in zip(axes[0], cases):
        true = np.asarray(case["true"], dtype=float)
        fused = np.asarray(case["fused"], dtype=float)
        cams = case.get("cameras") or {}
        ref = true[:2]
        # centimetres around the true position
        pts = [100.0 * (np.asarray(p, dtype=float)[:2] - ref) for p in cams.values()]
        for (name, p), q in zip(cams.items(), pts):
            ax.scatter(q[0], q[1], marker="^", s=35, color="tab:orange")
            ax.annotate(str(name), q, textcoords="offset points", xytext=(4, 3), fontsize=8)
        f = 100.0 * (fused[:2] - ref)
        ax.scatter(0, 0, marker="o", s=90, facecolors="none", edgecolors=TRUE_COLOUR, label="true")
        ax.scatter(f[0], f[1], marker="x", s=70, color=EST_COLOUR, label="fused")
        if pts:
            ax.scatter([], [], marker="^", color="tab:orange", label="per camera")
        allp = np.vstack(pts + [f, np.zeros(2)])
        lim = max(1.0, float(np.max(np.abs(allp))) * 1.25)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.grid(True, alpha=0.3)
        ax.set_xlabel("x - true x (cm)")
        ax.set_ylabel("y - true y (cm)")
        ax.set_title(f"{case.get('label', '')}: true ({true[0]:.2f}, {true[1]:.2f}) m", fontsize=10)
        ax.legend(loc="best", fontsize=8)
    fig.suptitle(title)
    return _save(fig, path)


def plot_orientations(path: str, true_yaw: Sequence[float], est_yaw: Sequence[float],
                      labels: Optional[Sequence[str]] = None,
                      title: str = "Orientations: true (blue) and estimated (red) (Fig. 10)") -> str:
    """The paper's Fig. 10: the robot's heading at each orientation, true and estimated.

    Args:
        true_yaw, est_yaw: rad.
    """
    t = np.asarray(true_yaw, dtype=float)
    e = np.asarray(est_yaw, dtype=float)
    fig, (ax, axe) = plt.subplots(1, 2, figsize=(12, 5.5))
    for k in range(len(t)):
        ax.annotate("", xy=(np.cos(t[k]), np.sin(t[k])), xytext=(0, 0),
                    arrowprops=dict(arrowstyle="-|>", color=TRUE_COLOUR, lw=2.5, alpha=0.6))
        ax.annotate("", xy=(0.9 * np.cos(e[k]), 0.9 * np.sin(e[k])), xytext=(0, 0),
                    arrowprops=dict(arrowstyle="-|>", color=EST_COLOUR, lw=1.2))
        ax.text(1.12 * np.cos(t[k]), 1.12 * np.sin(t[k]), labels[k] if labels is not None else str(k + 1),
                ha="center", va="center", fontsize=9)
    ax.set_xlim(-1.3, 1.3)
    ax.set_ylim(-1.3, 1.3)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(title, fontsize=10)
    err = np.degrees(np.angle(np.exp(1j * (e - t))))
    names = list(labels) if labels is not None else [str(k + 1) for k in range(len(t))]
    axe.bar(np.arange(len(names)), err, color=EST_COLOUR)
    axe.set_xticks(np.arange(len(names)))
    axe.set_xticklabels(names)
    axe.axhline(0, color="k", lw=0.8)
    axe.set_xlabel("orientation")
    axe.set_ylabel("yaw error (deg)")
    axe.set_title("estimated - true")
    axe.grid(True, axis="y", alpha=0.3)
    return _save(fig, path)


def plot_trajectory(path: str, stamps: np.ndarray, ref: np.ndarray, est: np.ndarray,
                    plate: Optional[np.ndarray] = None, title: str = "Trajectory") -> str:
    """A trajectory against its reference (top view) and the errors over time.

    Args:
        stamps: (N,) s; ref, est: (N, 3) matched (x, y, yaw) in m, rad.
    """
    s = np.asarray(stamps, dtype=float)
    r = np.asarray(ref, dtype=float).reshape(-1, 3)
    e = np.asarray(est, dtype=float).reshape(-1, 3)
    fig, (ax, axe) = plt.subplots(1, 2, figsize=(13, 5.5))
    _polygon(ax, plate, color="k", lw=2.0, label="plate")
    ax.plot(r[:, 0], r[:, 1], color=TRUE_COLOUR, lw=2, label="reference")
    ax.plot(e[:, 0], e[:, 1], color=EST_COLOUR, lw=1, label="estimate")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title)
    if len(s):
        t0 = s[0]
        d = 100.0 * np.hypot(e[:, 0] - r[:, 0], e[:, 1] - r[:, 1])
        yaw = np.degrees(np.angle(np.exp(1j * (e[:, 2] - r[:, 2]))))
        axe.plot(s - t0, d, color="tab:purple", label="position error (cm)")
        ax2 = axe.twinx()
        ax2.plot(s - t0, yaw, color="tab:gray", lw=0.8, label="yaw error (deg)")
        ax2.set_ylabel("yaw error (deg)")
        axe.set_xlabel("time (s)")
        axe.set_ylabel("position error (cm)")
        axe.grid(True, alpha=0.3)
        axe.legend(loc="upper left", fontsize=8)
        ax2.legend(loc="upper right", fontsize=8)
    return _save(fig, path)


def plate_polygon(centre: Sequence[float], size: Sequence[float], T_frame_world: Optional[np.ndarray] = None) -> np.ndarray:
    """(4, 2) plate corners, optionally moved from the world frame into another frame (4x4)."""
    cx, cy = centre
    hx, hy = size[0] / 2, size[1] / 2
    c = np.array([[cx - hx, cy - hy], [cx + hx, cy - hy], [cx + hx, cy + hy], [cx - hx, cy + hy]])
    return _to_frame(c, T_frame_world)


def room_polygon(origin: Sequence[float], size: Sequence[float], T_frame_world: Optional[np.ndarray] = None) -> np.ndarray:
    """(4, 2) room outline, optionally moved into another frame (4x4)."""
    x0, y0 = origin
    c = np.array([[x0, y0], [x0 + size[0], y0], [x0 + size[0], y0 + size[1]], [x0, y0 + size[1]]])
    return _to_frame(c, T_frame_world)


def _to_frame(c: np.ndarray, T: Optional[np.ndarray]) -> np.ndarray:
    if T is None:
        return c
    T = np.asarray(T, dtype=float)
    p = np.column_stack([c, np.zeros(len(c)), np.ones(len(c))]) @ T.T
    return p[:, :2]
