"""The robot's odometry in mapping: links between consecutive stations (issue 11).

A long walk (a handheld rig, a robot driving through a building) sees its markers in small groups;
chained only through the markers, the stations drift (an open chain: test_11's 240 mm). Odometry
(wheel odometry, visual-inertial odometry: any ``nav_msgs/Odometry`` whose pose is the odometry
body in a drifting odom frame) measures the motion between two stations directly, also across
stretches where no marker is in view. :class:`OdometryTrack` keeps the poses, interpolates them at
the stations' stamps and turns each pair of consecutive stations into a relative-pose factor of the
bundle adjustment (:class:`bundle_adjustment.RelativePoseFactors`).

**Frames.** The odometry's pose is ``T_odom_body`` of its own body frame (the message's
``child_frame_id``: the IMU of a VIO, the wheel base of a robot), which need not be the ring's base
frame: ``base_to_odom`` is that body's pose in the ring's base frame, ``X = T_base_body`` (TagSLAM's
``T_body_odom`` of the rig body: its "body" is our base frame, its "odom" the odometry's body). The
motion of the base frame from station ``i`` to ``j`` is then ``X · P_i^-1 P_j · X^-1`` with ``P`` the
odometry poses at the stations' stamps (translation interpolated linearly, rotation by slerp,
between the two messages around each stamp; a stamp farther than ``max_gap`` from a message gets no
link). Nothing about the odom frame itself is used: its drift does not enter.

**Noise model**, ``noise_model``. ``per_message`` (the default; TagSLAM's, from its
odometry_processor): each odometry message's motion has a sigma, how far it departs from the
previous message's velocity clamped to ``[message_acceleration, message_acceleration_max] x dt^2``
(the rotation alike; or fixed ``message_translation_noise`` / ``message_rotation_noise`` when both
are set), and a link's variance is the sum over the messages it spans (a message partly inside
the link by that part) plus the interpolation terms below (:meth:`OdometryTrack.message_variances`).
``random_walk`` (per link, 1-sigma on each axis; ``d`` the distance and ``a`` the angle of the
link's motion, both from the odometry)::

    sigma_trans^2 = min_translation^2 + translation_noise^2 * d + translation_per_second^2 * dt + jumps_trans^2
                    + interp_trans(t_i)^2 + interp_trans(t_j)^2
    sigma_rot^2   = min_rotation^2 + rotation_noise^2 * a + rotation_per_metre^2 * d
                    + rotation_per_second^2 * dt + jumps_rot^2 + interp_rot(t_i)^2 + interp_rot(t_j)^2

(a random walk: the variance grows with the distance and the angle travelled, as wheel odometry
and VIO drift, and with the time ``dt`` between the stations). **Jumps** (``random_walk``): an odometry message whose motion departs from the constant-velocity
prediction of the previous one by more than ``max_acceleration * dt^2`` (``max_angular_acceleration``
for the rotation) adds that excess to the sigma of the link that spans it (``jumps_*``: root sum of
squares): a VIO reset or a wheel slip widens its own link instead of bending the map.
**Interpolation**: a station between two messages ``t0 < t < t1`` gets the interpolated pose, off by
up to ``max_acceleration * (t - t0) * (t1 - t) / 2`` (``interp_trans``; ``max_angular_acceleration``
for ``interp_rot``) when the motion changes speed in between: nothing for an odometry stamped with
the frames or much faster than they come (tests 11, 12, 21: 20-30 Hz at the frames' stamps), tens of
mm for one at 4 Hz beside the frames (test_22's tracking camera: 22 mm median, the links were 4x
too tight and bent its map by 11 mm). On top, the
bundle adjustment's Huber loss on each link's whitened norm (``robust_scale``) bounds what any link
still off can pull.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from . import geometry as geo
from .bundle_adjustment import RelativePoseFactors
from .config import param
from .errors import ConfigError

logger = logging.getLogger(__name__)


#: ``MappingOdometryOptions.noise_model`` values.
NOISE_MODELS = ("random_walk", "per_message")
#: ``MappingOdometryOptions.message_sampling`` values.
MESSAGE_SAMPLINGS = ("messages", "frames")


@dataclass(frozen=True)
class MappingOdometryOptions:
    """Odometry links between stations (the mapper's ``mapping.odometry`` section)."""

    topic: str = param("", "nav_msgs/Odometry topic whose poses link consecutive stations in the bundle adjustment "
                           "(build-map --odom-topic; the mapper node subscribes to it); empty: no odometry")
    base_to_odom: Tuple[float, ...] = param([0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                                            "pose of the odometry's body frame (the messages' child_frame_id, e.g. "
                                            "a VIO's IMU) in the ring's base frame: x, y, z (m), rotation vector "
                                            "(rad); TagSLAM's T_body_odom")
    translation_noise: float = param(0.02, "odometry's position error after 1 m travelled (grows with the square "
                                           "root of the distance)", unit="m/sqrt(m)")
    rotation_noise: float = param(0.01, "odometry's rotation error after turning 1 rad (square root growth)",
                                  unit="rad/sqrt(rad)")
    rotation_per_metre: float = param(0.002, "odometry's rotation error after 1 m travelled (square root growth)",
                                      unit="rad/sqrt(m)")
    translation_per_second: float = param(0.0, "odometry's position error after 1 s (square root growth; 0: "
                                               "none)", unit="m/sqrt(s)")
    rotation_per_second: float = param(0.0, "odometry's rotation error after 1 s (square root growth; 0: none)",
                                       unit="rad/sqrt(s)")
    min_translation: float = param(0.002, "floor of a link's position error", unit="m")
    min_rotation: float = param(0.001, "floor of a link's rotation error", unit="rad")
    max_acceleration: float = param(5.0, "jumps: an odometry message departing from the previous one's constant "
                                         "velocity by more than this x dt^2 widens its link by the excess; a "
                                         "station between two messages widens its links by what the "
                                         "interpolation may miss at this acceleration",
                                    unit="m/s^2")
    max_angular_acceleration: float = param(5.0, "... the same for the rotation", unit="rad/s^2")
    max_gap: float = param(0.5, "a station whose stamp is farther than this from an odometry message (before and "
                                "after) gets no link", unit="s")
    robust_scale: float = param(3.0, "Huber loss of each link beyond this many sigmas (whitened norm); 0: none")
    noise_model: str = param("per_message", "noise of a link: random_walk = the terms above (distance, angle, "
                                            "time); per_message = TagSLAM's: each odometry message's motion has "
                                            "its own sigma (message_*), a link sums those of the messages it "
                                            "spans (the interpolation term still applies; min_*, *_noise, "
                                            "*_per_metre, *_per_second and the jumps term do not)")
    message_acceleration: float = param(5.0, "per_message: a message's position sigma is how far its motion "
                                             "departs from the previous message's constant velocity, at least "
                                             "this x dt^2 (TagSLAM's odom_acceleration, "
                                             "odom_acceleration_noise_min)", unit="m/s^2")
    message_acceleration_max: float = param(0.0, "per_message: ... at most this x dt^2 (TagSLAM's "
                                                 "odom_acceleration_noise_max; 0: 10 x message_acceleration)",
                                            unit="m/s^2")
    message_angular_acceleration: float = param(5.0, "per_message: the same for the rotation, at least this x "
                                                     "dt^2 (odom_angular_acceleration)", unit="rad/s^2")
    message_angular_acceleration_max: float = param(0.0, "per_message: ... at most this x dt^2 (0: 10 x "
                                                         "message_angular_acceleration)", unit="rad/s^2")
    message_translation_noise: float = param(0.0, "per_message: with message_rotation_noise, a fixed position "
                                                  "sigma per message instead of the acceleration's (TagSLAM's "
                                                  "odom_translation_noise; 0: not used)", unit="m")
    message_rotation_noise: float = param(0.0, "per_message: a fixed rotation sigma per message (TagSLAM's "
                                               "odom_rotation_noise; used only when both are > 0)", unit="rad")
    message_sampling: str = param("messages", "per_message: which poses are the messages: messages = every "
                                              "odometry message as it came; frames = the odometry at each ring "
                                              "frame's stamp (interpolated), one message per frame, as TagSLAM's "
                                              "synchronizer pairs one odometry message with each frame (an "
                                              "odometry faster than the frames is not taken as more precise: "
                                              "the acceleration floor x dt^2 summed over n messages shrinks as "
                                              "1/n^3)")

    def __post_init__(self) -> None:
        if len(self.base_to_odom) != 6 or not all(np.isfinite(float(v)) for v in self.base_to_odom):
            raise ConfigError(f"expected 6 finite numbers x y z rx ry rz, got {list(self.base_to_odom)!r}",
                              key="base_to_odom")
        if self.noise_model not in NOISE_MODELS:
            raise ConfigError(f"expected one of {', '.join(NOISE_MODELS)}, got {self.noise_model!r}",
                              key="noise_model")
        if self.message_sampling not in MESSAGE_SAMPLINGS:
            raise ConfigError(f"expected one of {', '.join(MESSAGE_SAMPLINGS)}, got {self.message_sampling!r}",
                              key="message_sampling")
        for key in ("translation_noise", "rotation_noise", "rotation_per_metre", "translation_per_second",
                    "rotation_per_second", "max_acceleration",
                    "max_angular_acceleration", "max_gap", "robust_scale", "message_acceleration_max",
                    "message_angular_acceleration_max", "message_translation_noise", "message_rotation_noise"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"expected a number >= 0, got {v!r}", key=key)
        for key in ("min_translation", "min_rotation", "message_acceleration", "message_angular_acceleration"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"expected a number > 0, got {v!r}", key=key)

    @property
    def T_base_odom(self) -> np.ndarray:
        v = np.asarray(self.base_to_odom, dtype=float)
        return geo.make_transform(geo.rotation_from_rvec(v[3:]), v[:3])


class OdometryTrack:
    """The odometry poses ``T_odom_body`` by stamp (appended in any order; duplicates keep the last)."""

    def __init__(self, stamps: Sequence[float] = (), poses: Optional[np.ndarray] = None):
        self._stamps: List[float] = []
        self._poses: List[np.ndarray] = []
        self._cache: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = None
        if poses is not None:
            for t, T in zip(stamps, np.asarray(poses, dtype=float).reshape(-1, 4, 4)):
                self.add(float(t), T)

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, stamp: float, T_odom_body: np.ndarray) -> bool:
        """Keep one pose; False (ignored) when it is not a finite rigid transform."""
        T = np.asarray(T_odom_body, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.isfinite(stamp) \
                or abs(np.linalg.det(T[:3, :3]) - 1.0) > 1e-3:
            return False
        self._stamps.append(float(stamp))
        self._poses.append(T)
        self._cache = None
        return True

    def _sorted(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(stamps, poses, per-message jump excess (N, 2): translation m, rotation rad)."""
        if self._cache is None:
            t = np.asarray(self._stamps)
            order = np.argsort(t, kind="stable")
            keep = np.ones(len(order), dtype=bool)
            keep[:-1] = np.diff(t[order]) > 0     # equal stamps: the last one appended
            idx = order[keep]
            P = np.stack(self._poses)[idx] if len(idx) else np.zeros((0, 4, 4))
            self._cache = (t[idx], P, np.zeros((len(idx), 2)))
        return self._cache

    def jumps(self, max_acceleration: float, max_angular_acceleration: float) -> np.ndarray:
        """(N, 2) per message: how far its motion departs from the previous message's constant
        velocity beyond ``max_acceleration * dt^2`` (m; rad for the rotation), else 0."""
        t, P, _ = self._sorted()
        out = np.zeros((len(t), 2))
        if len(t) < 3:
            return out
        # P_k-1^-1 P_k (body frame): rotation R_k-1^T R_k, translation R_k-1^T (t_k - t_k-1). (Not
        # the 4x4 transpose product, whose translation would be R_k-1^T t_k: the position, not the step.)
        dt = np.maximum(np.diff(t), 1e-3)
        dx = np.einsum("nji,nj->ni", P[:-1, :3, :3], P[1:, :3, 3] - P[:-1, :3, 3])
        da = Rotation.from_matrix(np.einsum("nji,njk->nik", P[:-1, :3, :3], P[1:, :3, :3])).as_rotvec()
        # Departure of increment k from increment k-1 scaled to its dt (constant velocity).
        ex = np.linalg.norm(dx[1:] - dx[:-1] * (dt[1:] / dt[:-1])[:, None], axis=1) - max_acceleration * dt[1:] ** 2
        ea = np.linalg.norm(da[1:] - da[:-1] * (dt[1:] / dt[:-1])[:, None], axis=1) \
            - max_angular_acceleration * dt[1:] ** 2
        out[2:, 0] = np.maximum(ex, 0.0)
        out[2:, 1] = np.maximum(ea, 0.0)
        return out

    def message_variances(self, X: np.ndarray, opts: MappingOdometryOptions) -> np.ndarray:
        """(N, 2) per message ``k``: the variance (m^2, rad^2) of its motion since message ``k - 1``
        under the ``per_message`` model (row 0: no motion, 0). With both ``message_translation_noise``
        and ``message_rotation_noise`` set, those sigmas; else each motion's departure from the
        previous message's velocity (zero before the first motion), clamped to
        ``[message_acceleration, message_acceleration_max] x dt^2`` (rotation alike). The motions are
        the base frame's, ``X · P_k-1^-1 P_k · X^-1``."""
        t, P, _ = self._sorted()
        out = np.zeros((len(t), 2))
        if len(t) < 2:
            return out
        if opts.message_translation_noise > 0 and opts.message_rotation_noise > 0:
            out[1:, 0] = opts.message_translation_noise ** 2
            out[1:, 1] = opts.message_rotation_noise ** 2
            return out
        raw = np.zeros((len(t) - 1, 4, 4))                               # P_k-1^-1 P_k
        raw[:, :3, :3] = np.einsum("nji,njk->nik", P[:-1, :3, :3], P[1:, :3, :3])
        raw[:, :3, 3] = np.einsum("nji,nj->ni", P[:-1, :3, :3], P[1:, :3, 3] - P[:-1, :3, 3])
        raw[:, 3, 3] = 1.0
        D = X[None] @ raw @ geo.inverse(X)[None]
        dt = np.maximum(np.diff(t), 1e-3)
        dx = D[:, :3, 3]
        da = Rotation.from_matrix(D[:, :3, :3]).as_rotvec()
        v_prev = np.vstack([np.zeros(3), dx[:-1] / dt[:-1, None]])
        w_prev = np.vstack([np.zeros(3), da[:-1] / dt[:-1, None]])
        dpos = np.linalg.norm(dx - v_prev * dt[:, None], axis=1)
        dang = np.linalg.norm(da - w_prev * dt[:, None], axis=1)
        amax = opts.message_acceleration_max or 10.0 * opts.message_acceleration
        wmax = opts.message_angular_acceleration_max or 10.0 * opts.message_angular_acceleration
        out[1:, 0] = np.clip(dpos, opts.message_acceleration * dt ** 2, amax * dt ** 2) ** 2
        out[1:, 1] = np.clip(dang, opts.message_angular_acceleration * dt ** 2, wmax * dt ** 2) ** 2
        return out

    def interpolation_error(self, stamp: float, max_acceleration: float,
                            max_angular_acceleration: float) -> Tuple[float, float]:
        """(m, rad): how far the interpolated pose at ``stamp`` may be off when the motion changes speed
        between the two messages around it, at most ``max_acceleration`` (constant acceleration
        ``a``: ``a (t - t0)(t1 - t) / 2``); 0 at a message's stamp and outside the track."""
        t, _, _ = self._sorted()
        k = int(np.searchsorted(t, stamp))
        if k == 0 or k >= len(t) or abs(t[k] - stamp) <= 1e-9:
            return 0.0, 0.0
        w = max(stamp - t[k - 1], 0.0) * max(t[k] - stamp, 0.0) / 2.0
        return max_acceleration * w, max_angular_acceleration * w

    def pose_at(self, stamp: float, max_gap: float) -> Optional[np.ndarray]:
        """``T_odom_body`` at ``stamp`` (interpolated), or None outside the track or in a gap."""
        t, P, _ = self._sorted()
        if len(t) == 0 or stamp < t[0] - 1e-9 or stamp > t[-1] + 1e-9:
            return None
        k = int(np.searchsorted(t, stamp))
        if k < len(t) and abs(t[k] - stamp) <= 1e-9:
            return P[k].copy()
        if k == 0:
            return P[0].copy() if abs(t[0] - stamp) <= 1e-9 else None
        if k >= len(t):
            return P[-1].copy()
        t0, t1 = t[k - 1], t[k]
        if stamp - t0 > max_gap or t1 - stamp > max_gap:
            return None
        s = (stamp - t0) / (t1 - t0)
        R = Slerp([0.0, 1.0], Rotation.from_matrix(P[k - 1:k + 1, :3, :3]))([s]).as_matrix()[0]
        return geo.make_transform(R, (1 - s) * P[k - 1][:3, 3] + s * P[k][:3, 3])

    def sampled(self, stamps: Sequence[float], max_gap: float) -> "OdometryTrack":
        """The track at ``stamps`` (interpolated, :meth:`pose_at`; those outside the track or in a gap
        left out): the messages ``message_sampling: frames`` judges."""
        t_all, P, _ = self._sorted()
        t = np.unique(np.asarray(stamps, dtype=float))
        if len(t_all) < 2 or not len(t):
            return OdometryTrack()
        t = t[(t >= t_all[0] - 1e-9) & (t <= t_all[-1] + 1e-9)]
        k = np.clip(np.searchsorted(t_all, t), 1, len(t_all) - 1)      # t in (t_all[k-1], t_all[k]]
        t0, t1 = t_all[k - 1], t_all[k]
        on = (np.abs(t - t0) <= 1e-9) | (np.abs(t - t1) <= 1e-9)         # on a message: exact
        keep = on | ((t - t0 <= max_gap) & (t1 - t <= max_gap))
        t, k, t0, t1 = t[keep], k[keep], t0[keep], t1[keep]
        s = np.clip((t - t0) / np.maximum(t1 - t0, 1e-12), 0.0, 1.0)
        R0 = Rotation.from_matrix(P[k - 1, :3, :3])
        rel = (R0.inv() * Rotation.from_matrix(P[k, :3, :3])).as_rotvec()
        out = np.tile(np.eye(4), (len(t), 1, 1))
        out[:, :3, :3] = (R0 * Rotation.from_rotvec(rel * s[:, None])).as_matrix()
        out[:, :3, 3] = (1 - s)[:, None] * P[k - 1, :3, 3] + s[:, None] * P[k, :3, 3]
        return OdometryTrack(t, out)

    def links(self, station_stamps: Dict[int, float], opts: MappingOdometryOptions,
              frame_stamps: Optional[Sequence[float]] = None) -> Optional[RelativePoseFactors]:
        """Factors between consecutive stations (by stamp) of ``station_stamps`` (station -> stamp),
        in the ring's base frame, with the noise model of the module docstring; None when no pair
        of stations is covered by the odometry. ``frame_stamps``: the stamps of every ring frame,
        the messages of ``message_sampling: frames`` (the stations' own stamps without them)."""
        if len(self) < 2 or len(station_stamps) < 2:
            return None
        if opts.noise_model == "per_message" and opts.message_sampling == "frames":
            stamps = list(station_stamps.values()) + ([] if frame_stamps is None else list(frame_stamps))
            messages = self.sampled(stamps, opts.max_gap)
            if len(messages) < 2:
                return None
            return messages._links(station_stamps, opts, interp_from=self)
        return self._links(station_stamps, opts, interp_from=self)

    def _links(self, station_stamps: Dict[int, float], opts: MappingOdometryOptions,
               interp_from: "OdometryTrack") -> Optional[RelativePoseFactors]:
        """:meth:`links` on this track's messages; the interpolation terms from ``interp_from`` (the
        odometry as it came: resampled at the frames, the stations sit on messages, but their
        poses were interpolated between the original ones)."""
        X = opts.T_base_odom
        Xi = geo.inverse(X)
        t_all, _, _ = self._sorted()
        jumps = self.jumps(opts.max_acceleration, opts.max_angular_acceleration)
        order = sorted(station_stamps, key=lambda s: (station_stamps[s], s))
        poses = {s: self.pose_at(station_stamps[s], opts.max_gap) for s in order}
        interp = {s: interp_from.interpolation_error(station_stamps[s], opts.max_acceleration,
                                                     opts.max_angular_acceleration) for s in order}
        per_message = opts.noise_model == "per_message"
        if per_message:
            var = self.message_variances(X, opts)
            t_prev = np.r_[t_all[:1], t_all[:-1]]                 # message k covers (t_prev[k], t_all[k]]
        I, J, Z, sig = [], [], [], []
        prev = None
        for s in order:
            if poses[s] is None:
                prev = None          # no link across a station the odometry does not cover
                continue
            if prev is not None:
                ta, tb = station_stamps[prev], station_stamps[s]
                D = X @ geo.inverse(poses[prev]) @ poses[s] @ Xi
                d = float(np.linalg.norm(D[:3, 3]))
                a = float(np.linalg.norm(Rotation.from_matrix(D[:3, :3]).as_rotvec()))
                inside = (t_all > ta) & (t_all <= tb)
                jt, jr = (np.sqrt(np.sum(jumps[inside] ** 2, axis=0)) if np.any(inside) else (0.0, 0.0))
                dt = tb - ta
                (it_a, ir_a), (it_b, ir_b) = interp[prev], interp[s]
                if per_message:
                    # The messages' motions the link spans, each by the part of its interval inside
                    # (ta, tb] (a random walk within a message).
                    span = np.maximum(t_all - t_prev, 1e-9)
                    part = np.clip((np.minimum(t_all, tb) - np.maximum(t_prev, ta)) / span, 0.0, 1.0)
                    vt, vr = part @ var
                    st = np.sqrt(max(vt + it_a ** 2 + it_b ** 2, 1e-12))
                    sr = np.sqrt(max(vr + ir_a ** 2 + ir_b ** 2, 1e-12))
                else:
                    st = np.sqrt(opts.min_translation ** 2 + opts.translation_noise ** 2 * d
                                 + opts.translation_per_second ** 2 * dt + jt ** 2 + it_a ** 2 + it_b ** 2)
                    sr = np.sqrt(opts.min_rotation ** 2 + opts.rotation_noise ** 2 * a
                                 + opts.rotation_per_metre ** 2 * d + opts.rotation_per_second ** 2 * dt + jr ** 2
                                 + ir_a ** 2 + ir_b ** 2)
                I.append(prev)
                J.append(s)
                Z.append(D)
                sig.append(np.r_[np.full(3, sr), np.full(3, st)])
            prev = s
        if not I:
            return None
        return RelativePoseFactors(I, J, Z, sig, robust_scale=opts.robust_scale)
