"""Figures of the paper's experiment (matplotlib, Agg backend: no display needed).

All functions draw in one planar frame (the demo's lab frame, in which its Table I is given too),
in metres, and write a PNG. Inputs are plain arrays so the demo, ``aruco_ring evaluate`` and the
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
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
from matplotlib.transforms import ScaledTranslation  # noqa: E402

logger = logging.getLogger(__name__)

TRUE_COLOUR = "tab:blue"
EST_COLOUR = "tab:red"
# per-camera colours, none of them the true (blue) or estimated (red) one
CAMERA_COLOURS = ("tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:gray", "tab:olive",
                  "tab:cyan")


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


def _top_view(ax, title: str) -> None:
    """Equal axes in metres, a grid, the title, and the legend below the axes (never over labels)."""
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    # 0.5 inch below the axes, whatever their height: under the tick labels and the x label
    below = ax.transAxes + ScaledTranslation(0.0, -0.5, ax.figure.dpi_scale_trans)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, 0.0), bbox_transform=below, ncol=4, fontsize=8)


def _robot_outline(ax, pose: Sequence[float], footprint: Tuple[float, float], **kwargs) -> None:
    x, y, yaw = pose
    L, W = footprint
    c = np.array([[L / 2, W / 2], [-L / 2, W / 2], [-L / 2, -W / 2], [L / 2, -W / 2]])
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    _polygon(ax, c @ R.T + (x, y), **kwargs)


def label_apart(fig, ax, points: np.ndarray, names: Sequence[str], min_px: float = 22.0) -> int:
    """Label points, skipping any whose label would sit within ``min_px`` pixels of one placed.

    Call after the axes' limits and aspect are final. Returns the number of labels placed.
    """
    fig.canvas.draw()
    xy = ax.transData.transform(np.asarray(points, dtype=float).reshape(-1, 2))
    placed: List[np.ndarray] = []
    for k, (p, name) in enumerate(zip(xy, names)):
        if any(np.hypot(*(p - q)) < min_px for q in placed):
            continue
        placed.append(p)
        ax.annotate(str(name), points[k], textcoords="offset points", xytext=(4, 4), fontsize=8)
    return len(placed)


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
    _top_view(ax, title)
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
    names = [labels[k] if labels is not None else str(k + 1) for k in range(len(t))]
    _top_view(ax, title)
    label_apart(fig, ax, t, [name + (f" ({errors_cm[k]:.2f} cm)" if errors_cm is not None else "")
                             for k, name in enumerate(names)], min_px=22.0)
    # the errors are mm-sized: show the error vectors magnified on the right
    d = 100.0 * (e - t)
    axz.axhline(0, color="0.7", lw=0.8)
    axz.axvline(0, color="0.7", lw=0.8)
    axz.scatter(d[:, 0], d[:, 1], color=EST_COLOUR, marker="x")
    lim = max(1.0, float(np.max(np.abs(d))) * 1.2) if len(d) else 1.0
    axz.set_xlim(-lim, lim)
    axz.set_ylim(-lim, lim)
    axz.set_aspect("equal")
    if label_apart(fig, axz, d, names, min_px=22.0) < len(d):
        axz.set_title("estimate - true (labels of clustered points left out)")
    axz.set_xlabel("x error (cm)")
    axz.set_ylabel("y error (cm)")
    if not axz.get_title():
        axz.set_title("estimate - true")
    axz.grid(True, alpha=0.3)
    return _save(fig, path)


def plot_camera_estimates(path: str, cases: Sequence[Dict[str, object]],
                          title: str = "Per-camera estimates and the fused pose (Fig. 9)") -> str:
    """The paper's Fig. 9: at a few positions, each camera's robot-pose estimate vs the fused one.

    Every panel has the same scale (centimetres around the true position), so the spread of
    the per-camera estimates compares across positions; cameras are told apart by colour, in one
    legend for all panels (no label beside each point: clustered estimates would overprint).

    Args:
        cases: dicts with ``label`` (str), ``true`` (x, y, yaw), ``fused`` (x, y, yaw) and
            ``cameras`` ({camera name: (x, y, yaw)}), all in m/rad of the same frame.
    """
    n = max(1, len(cases))
    offsets = []
    names: List[str] = []
    for case in cases:
        ref = np.asarray(case["true"], dtype=float)[:2]
        cams = {str(k): 100.0 * (np.asarray(p, dtype=float)[:2] - ref) for k, p in (case.get("cameras") or {}).items()}
        fused = 100.0 * (np.asarray(case["fused"], dtype=float)[:2] - ref)
        offsets.append((cams, fused))
        names += [k for k in cams if k not in names]
    every = [np.zeros(2)] + [f for _, f in offsets] + [p for c, _ in offsets for p in c.values()]
    lim = max(1.0, 1.2 * float(np.max(np.abs(np.vstack(every)))))
    colour = {name: CAMERA_COLOURS[k % len(CAMERA_COLOURS)] for k, name in enumerate(names)}
    fig, axes = plt.subplots(1, n, figsize=(4.4 * n + 1.0, 5.2), squeeze=False, sharex=True, sharey=True,
                             layout="constrained")
    for ax, case, (cams, fused) in zip(axes[0], cases, offsets):
        for name, q in cams.items():
            ax.scatter(q[0], q[1], marker="^", s=45, color=colour[name], label=f"camera {name}")
        ax.scatter(0, 0, marker="o", s=110, facecolors="none", edgecolors=TRUE_COLOUR, lw=1.5, label="true")
        ax.scatter(fused[0], fused[1], marker="x", s=80, color=EST_COLOUR, lw=2, label="fused")
        true = np.asarray(case["true"], dtype=float)
        err = float(np.hypot(*fused))
        ax.set_title(f"{case.get('label', '')}: true ({true[0]:.2f}, {true[1]:.2f}) m\nfused error {err:.2f} cm",
                     fontsize=10)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.grid(True, alpha=0.3)
        ax.set_xlabel("x - true x (cm)")
    axes[0][0].set_ylabel("y - true y (cm)")
    handles, labels = {}, []
    for ax in axes[0]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in handles:
                handles[lab] = h
                labels.append(lab)
    fig.legend([handles[lab] for lab in labels], labels, loc="outside lower center", ncol=min(len(labels), 6),
               fontsize=8)
    fig.suptitle(title)
    return _save(fig, path)


def heading_magnification(max_error_deg: float, shown_deg: float = 20.0) -> int:
    """The largest of 1, 2, 5, 10, 20, 50, ... that shows ``max_error_deg`` as at most ``shown_deg``."""
    gain = 1
    for g in (2, 5, 10, 20, 50, 100, 200, 500, 1000):
        if g * max_error_deg <= shown_deg:
            gain = g
    return gain


def plot_orientations(path: str, true_yaw: Sequence[float], est_yaw: Sequence[float],
                      labels: Optional[Sequence[str]] = None,
                      title: str = "Orientations: true (blue) and estimated (red) (Fig. 10)") -> str:
    """The paper's Fig. 10: the robot's heading at each orientation, true and estimated.

    Errors of a fraction of a degree are invisible at the scale of a full turn, so the left
    panel draws the estimated heading with its error magnified (x1, 2, 5, 10, ..., stated in the
    panel) until the largest shows as about 20 deg; the right panel gives the errors themselves.

    Args:
        true_yaw, est_yaw: rad.
    """
    t = np.asarray(true_yaw, dtype=float)
    e = np.asarray(est_yaw, dtype=float)
    err = np.angle(np.exp(1j * (e - t)))
    gain = heading_magnification(float(np.degrees(np.max(np.abs(err)))) if len(err) else 0.0)
    shown = t + gain * err
    names = list(labels) if labels is not None else [str(k + 1) for k in range(len(t))]
    fig, (ax, axe) = plt.subplots(1, 2, figsize=(12, 5.5))
    for k in range(len(t)):
        ax.annotate("", xy=(np.cos(t[k]), np.sin(t[k])), xytext=(0, 0),
                    arrowprops=dict(arrowstyle="-|>", color=TRUE_COLOUR, lw=2.5, alpha=0.6))
        ax.annotate("", xy=(0.9 * np.cos(shown[k]), 0.9 * np.sin(shown[k])), xytext=(0, 0),
                    arrowprops=dict(arrowstyle="-|>", color=EST_COLOUR, lw=1.2))
        ax.text(1.14 * np.cos(t[k]), 1.14 * np.sin(t[k]), names[k], ha="center", va="center", fontsize=9)
    ax.set_xlim(-1.3, 1.3)
    ax.set_ylim(-1.3, 1.3)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(title + (f"\nestimated heading drawn with its error magnified x{gain}" if gain > 1 else ""),
                 fontsize=10)
    err_deg = np.degrees(err)
    x = np.arange(len(names))
    axe.bar(x, err_deg, color=EST_COLOUR)
    span = max(float(np.max(np.abs(err_deg))) if len(err_deg) else 0.0, 1e-3)
    for k, v in enumerate(err_deg):
        axe.text(k, v + (0.03 * span if v >= 0 else -0.03 * span), f"{v:+.3f}", ha="center",
                 va="bottom" if v >= 0 else "top", fontsize=8)
    axe.set_ylim(-1.25 * span if np.any(err_deg < 0) else 0.0, 1.25 * span if np.any(err_deg > 0) else 0.0)
    axe.set_xticks(x)
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
    _top_view(ax, title)
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
