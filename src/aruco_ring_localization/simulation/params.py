"""The simulator's parameter schema (:class:`SimulatorConfig`): nested sections, each default once.

``config/simulator.yaml`` mirrors it key for key (``test/unit/test_simulator_core.py`` checks
names and defaults); the ``simulator`` node reads it with ``ros/params.read_config`` and
``launch/simulation.launch`` overrides a key only when its argument is given. The simulation
classes take their own defaults from these sections (``RingSimulator(pixel_noise=...)``,
``perturb_ring``, ``RingRenderer``, ``LaserScanner``, ``SimRobot``), so a default is written here
and nowhere else.

Sections, and what will join them (the structure is ready for it): ``cameras`` (which cameras,
what they see, their trigger: synchronized or free-running with phases and jitter),
``ring`` (the calibration, the true rig's error from it, per-frame vibration), ``plate`` (a floor
that is not flat), ``render`` (images mode: blur, noise, exposure and motion blur, illumination),
``robot`` (start, waypoints, limits),
``ground_truth``, ``odometry``, ``gmapping`` (a perfect gmapping's tf and grid), ``laser``,
``clock`` (owning ``/clock``, its speed), ``lockstep``
(waiting for the consumers of each frame). Every default is the kind lab; config/lab_harsh.yaml
sets the harsher one's (docs/simulation.md, "The harsh lab").
Units: SI; angles in radians unless the key ends in ``_deg``.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any, Iterator, Mapping, Optional, Sequence, Tuple

import numpy as np

from ..config import param, section, with_overrides
from ..errors import ConfigError

MODES = ("corners", "images")
TRIGGERS = ("synchronized", "free")
WAYPOINT_SETS = ("test_positions", "test_orientations", "paper", "mapping_stations", "mapping_pose", "none")
DRIVES = ("cmd_vel", "direct", "teleport")


def _positive(name: str, value: float) -> None:
    if not (np.isfinite(value) and value > 0):
        raise ConfigError(f"must be a positive number, got {value!r}", key=name)


def _non_negative(name: str, value: float) -> None:
    if not (np.isfinite(value) and value >= 0):
        raise ConfigError(f"must be zero or positive, got {value!r}", key=name)


def _pose_deg(name: str, value: Sequence[Any]) -> None:
    try:
        ok = len(value) == 3 and all(np.isfinite(float(v)) for v in value)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ConfigError(f"expected [x, y, yaw_deg] (three numbers), got {value!r}", key=name)


@dataclass(frozen=True)
class SceneParams:
    """The hall: walls, plate, markers, test poses (docs/simulation.md, "Scene file format")."""

    file: str = param("", "scene YAML; empty = the package's config/lab_scene.yaml; a name that is not an "
                          "existing path is looked for in the package's config/ (e.g. lab_scene_harsh.yaml)")


@dataclass(frozen=True)
class RingParams:
    """The ring file the estimators use, and how far the simulator's true rig is from it."""

    file: str = param("", "ring YAML (the calibration); empty = the package's config/ring.yaml")
    calibration_trans_std: float = param(0.002, "true rig vs ring file: Gaussian translation per axis, "
                                                "in each camera's frame", unit="m")
    calibration_rot_std_deg: float = param(0.2, "true rig vs ring file: Gaussian rotation per axis", unit="deg")
    vibration_rot_std_deg: float = param(0.0, "ring vibration: every frame each camera's true extrinsics turn "
                                              "by a fresh Gaussian rotation per axis (its own frame); 0 = rigid",
                                         unit="deg")
    vibration_trans_std: float = param(0.0, "ring vibration: every frame each camera moves by a fresh Gaussian "
                                            "translation per axis", unit="m")

    def __post_init__(self) -> None:
        for name in ("calibration_trans_std", "calibration_rot_std_deg", "vibration_rot_std_deg",
                     "vibration_trans_std"):
            _non_negative(name, getattr(self, name))


@dataclass(frozen=True)
class PlateParams:
    """The floor under the robot: flat (the kind lab) or tilted with bumps, so the robot rolls and pitches.

    The floor's height is ``tilt`` (a plane rising along ``tilt_direction_deg``) plus ``bump``
    (a sum of two seeded sinusoidal waves of ``bump_wavelength``, scaled so that their slope is at
    most ``bump_deg``). base_link stands on it: its height is the floor's and its z axis the
    floor's normal, averaged over the robot's footprint (the wheels span it); the wheel odometry
    stays planar.
    """

    tilt_deg: float = param(0.0, "slope of the plate as a whole", unit="deg")
    tilt_direction_deg: float = param(0.0, "direction the plate rises toward (about z, 0 = +x)", unit="deg")
    bump_deg: float = param(0.0, "largest slope of the bumps", unit="deg")
    bump_wavelength: float = param(1.5, "wavelength of the bumps", unit="m")

    def __post_init__(self) -> None:
        for name in ("tilt_deg", "bump_deg"):
            value = getattr(self, name)
            if not (np.isfinite(value) and 0.0 <= value <= 5.0):
                raise ConfigError(f"must be within [0, 5] deg, got {value!r}", key=name)
        if not np.isfinite(self.tilt_direction_deg):
            raise ConfigError(f"must be a number, got {self.tilt_direction_deg!r}", key="tilt_direction_deg")
        _positive("bump_wavelength", self.bump_wavelength)


@dataclass(frozen=True)
class CameraParams:
    """The simulated cameras: which ones, and what they see."""

    names: tuple = param([], "camera names to simulate (e.g. [cam1, cam5]); empty = every ring camera")
    max_range: float = param(8.0, "markers farther than this from a camera are not seen", unit="m")
    pixel_noise: float = param(0.3, "corners mode: Gaussian corner noise per coordinate", unit="px")
    trigger: str = param("synchronized", "synchronized: every camera exposes at the frame's time | free: "
                                         "free-running, each camera at its own phase and jitter, stamped with "
                                         "its own exposure time (docs/simulation.md, \"Free-running cameras\")")
    phase_spread: float = param(1.0, "free: each camera's phase (how long before the frame's time it exposes) "
                                     "is drawn once, uniform in [0, phase_spread) frame periods; at most 1")
    jitter_std: float = param(0.002, "free: per-frame Gaussian jitter of each camera's exposure time (the rate "
                                     "wobbles); the exposure stays within one frame period before the frame's "
                                     "time", unit="s")

    def __post_init__(self) -> None:
        _positive("max_range", self.max_range)
        _non_negative("pixel_noise", self.pixel_noise)
        if self.trigger not in TRIGGERS:
            raise ConfigError(f"expected one of {' | '.join(TRIGGERS)}, got {self.trigger!r}", key="trigger")
        if not (np.isfinite(self.phase_spread) and 0.0 <= self.phase_spread <= 1.0):
            raise ConfigError(f"must be within [0, 1] frame periods, got {self.phase_spread!r}", key="phase_spread")
        _non_negative("jitter_std", self.jitter_std)


@dataclass(frozen=True)
class RenderParams:
    """Images mode: how each camera's mono8 image is rendered (docs/simulation.md, "What is simulated")."""

    blur_sigma: float = param(0.6, "optical blur, Gaussian sigma", unit="px")
    noise_std: float = param(2.0, "sensor noise, Gaussian sigma", unit="grey levels")
    supersample: int = param(2, "samples per pixel along each axis on the markers (1 = point sampling: "
                                "edges snap to pixel boundaries)")
    exposure_time: float = param(0.0, "motion blur: each image averages the views along this exposure, "
                                      "centred on its stamp, while the robot moves; 0 = instantaneous", unit="s")
    blur_samples: int = param(4, "motion blur: views averaged over the exposure while moving")
    gain_std: float = param(0.0, "exposure changes: each camera's image gain wanders (log-normal, this "
                                 "stationary sigma of log gain, about 2 s correlation); 0 = fixed gain")
    illumination_gradient: float = param(0.0, "uneven light: brightness varies linearly across each image by "
                                              "up to this fraction either side, its direction drifting per "
                                              "camera; 0 = even")

    def __post_init__(self) -> None:
        _non_negative("blur_sigma", self.blur_sigma)
        _non_negative("noise_std", self.noise_std)
        if self.supersample < 1:
            raise ConfigError(f"must be 1 or more, got {self.supersample!r}", key="supersample")
        _non_negative("exposure_time", self.exposure_time)
        if self.blur_samples < 1:
            raise ConfigError(f"must be 1 or more, got {self.blur_samples!r}", key="blur_samples")
        _non_negative("gain_std", self.gain_std)
        if not (np.isfinite(self.illumination_gradient) and 0.0 <= self.illumination_gradient < 1.0):
            raise ConfigError(f"must be within [0, 1), got {self.illumination_gradient!r}",
                              key="illumination_gradient")


@dataclass(frozen=True)
class MotionLimits:
    """Limits of the holonomic base; both the waypoint driver and external cmd_vel obey them."""

    max_speed: float = param(0.3, "translation speed", unit="m/s")
    max_yaw_rate: float = param(0.6, "yaw rate", unit="rad/s")
    max_accel: float = param(0.5, "translational acceleration", unit="m/s^2")
    max_yaw_accel: float = param(1.0, "yaw acceleration", unit="rad/s^2")

    def __post_init__(self) -> None:
        for name in ("max_speed", "max_yaw_rate", "max_accel", "max_yaw_accel"):
            _positive(name, getattr(self, name))


@dataclass(frozen=True)
class RobotParams:
    """Where the robot starts and what it does: waypoints (driven or jumped to) or cmd_vel."""

    start_pose: tuple = param([], "[x, y, yaw_deg] in the world; empty = the scene's mapping_pose", unit="m, m, deg")
    waypoints: str = param("test_positions", "the scene's poses to visit: " + " | ".join(WAYPOINT_SETS)
                           + " (none: follow cmd_vel only)")
    plan: tuple = param([], "explicit waypoints [[x, y, yaw_deg], ...] in the world, visited in this order "
                            "instead of `waypoints` (e.g. the demo's route)", unit="m, m, deg")
    hold_time: float = param(3.0, "time held at each waypoint", unit="s")
    drive: str = param("cmd_vel", "cmd_vel: drive to each waypoint within the limits (published on cmd_vel); "
                                  "direct or teleport: jump onto it")
    loop: bool = param(False, "visit the waypoints again and again (false: stop at the last one, then follow cmd_vel)")
    limits: MotionLimits = section(MotionLimits)

    def __post_init__(self) -> None:
        if self.waypoints not in WAYPOINT_SETS:
            raise ConfigError(f"expected one of {' | '.join(WAYPOINT_SETS)}, got {self.waypoints!r}", key="waypoints")
        if self.drive not in DRIVES:
            raise ConfigError(f"expected one of {' | '.join(DRIVES)}, got {self.drive!r}", key="drive")
        if self.start_pose:
            _pose_deg("start_pose", self.start_pose)
        for k, p in enumerate(self.plan):
            _pose_deg(f"plan[{k}]", p)
        _non_negative("hold_time", self.hold_time)


@dataclass(frozen=True)
class GroundTruthParams:
    """The true pose of base_link: topic ``sim/ground_truth`` and tf ``parent -> frame``."""

    parent: str = param("world", "parent frame of the ground-truth tf (the scene's world frame)")
    frame: str = param("sim_ground_truth", "child frame of the ground-truth tf")


@dataclass(frozen=True)
class OdometryParams:
    """Drifting wheel odometry (REP-105): topic ``odom`` and, optionally, tf ``frame -> base_frame``."""

    frame: str = param("odom", "odometry frame")
    base_frame: str = param("base_link", "robot frame")
    publish_tf: bool = param(True, "publish tf odom -> base_link")


@dataclass(frozen=True)
class GmappingParams:
    """A perfect gmapping, so that what runs beside gmapping on a robot has a reference in the simulation.

    gmapping publishes ``map -> odom`` (so that ``map -> base_link`` is its robot pose) and a latched
    occupancy grid on ``map``. This stand-in publishes the same, from the ground truth: ``map`` is the
    scene's world frame, ``map -> odom`` puts base_link at its true pose, the grid is the room's walls
    and posts. Off by default: without gmapping our own localizer or mapper owns ``map -> odom``.
    """

    publish: bool = param(False, "publish map_frame -> odom (base_link's true pose through the odometry; "
                                 "map_frame -> base_link when odometry.publish_tf is off) and the grid on `map`")
    map_frame: str = param("map", "gmapping's map frame (the scene's world frame)")
    resolution: float = param(0.05, "cell side of the occupancy grid", unit="m")

    def __post_init__(self) -> None:
        _positive("resolution", self.resolution)


@dataclass(frozen=True)
class LaserParams:
    """A planar scan of the walls and posts (``scan``), for users who run gmapping on the simulated lab."""

    publish: bool = param(True, "publish ``scan``")
    frame: str = param("base_link", "frame_id of the scan (its origin is base_link's)")
    beams: int = param(360, "beams over 360 deg")
    range_max: float = param(20.0, "maximum range; beyond it a beam reads inf", unit="m")

    def __post_init__(self) -> None:
        if self.beams < 1:
            raise ConfigError(f"must be 1 or more, got {self.beams!r}", key="beams")
        _positive("range_max", self.range_max)


@dataclass(frozen=True)
class ClockParams:
    """Simulated time: with ``publish`` the simulator owns ``/clock`` (run every node with use_sim_time)."""

    publish: bool = param(False, "publish /clock; every frame is then exactly 1/rate after the previous one")
    speed: float = param(1.0, "simulated seconds per wall second (at most: lockstep may slow it down)")
    start_time: float = param(1.0, "first simulated time (rospy treats 0 as 'not set')", unit="s")

    def __post_init__(self) -> None:
        _positive("speed", self.speed)
        _positive("start_time", self.start_time)


@dataclass(frozen=True)
class LockstepParams:
    """With clock.publish: wait, before the next frame, until the frame's consumers have answered it.

    The consumers are, in images mode, every simulated camera's detector (``<ns>/fiducial_vertices``)
    and, in both modes, each topic of ``topics`` (any message type whose first field is a
    std_msgs/Header, e.g. ``localizer/pose``). Only consumers that are connected are waited for,
    so lockstep is harmless when nobody listens. No frame is then lost on a slow CPU; the
    simulated clock runs slower instead. Before the first frame the simulator also waits for its
    subscribers to connect (``startup_timeout``), so a node started beside it sees every frame.
    """

    enabled: bool = param(True, "wait for the consumers of each frame (only when clock.publish)")
    topics: tuple = param([], "downstream topics whose messages carry the frame's stamp when it has been "
                              "processed, e.g. [localizer/pose]")
    timeout: float = param(2.0, "longest wait for one frame; then the frame goes on without the late ones "
                                "(warned)", unit="s (wall)")
    startup_timeout: float = param(20.0, "before the first frame, wait at most this long until every simulated "
                                         "camera's outputs have a subscriber and every topic of `topics` a "
                                         "publisher (then 1 s more, for the subscribers' tf); 0 = start at once",
                                   unit="s (wall)")

    def __post_init__(self) -> None:
        _positive("timeout", self.timeout)
        _non_negative("startup_timeout", self.startup_timeout)


def scene_event(e, key: str = "events") -> Tuple[float, int, Tuple[float, ...], Tuple[float, ...]]:
    """``(t, marker, move, rotate_deg)`` of one ``events`` entry; ConfigError naming the key."""
    if not isinstance(e, Mapping) or not {"t", "marker"} <= set(e) or not set(e) <= {"t", "marker", "move",
                                                                                     "rotate_deg"}:
        raise ConfigError(f"expected {{t: s, marker: id, move: [dx, dy, dz], rotate_deg: [rx, ry, rz]}}, got {e!r}",
                          key=key)
    try:
        t, marker = float(e["t"]), int(e["marker"])
        move = tuple(float(v) for v in e.get("move", (0.0, 0.0, 0.0)))
        rot = tuple(float(v) for v in e.get("rotate_deg", (0.0, 0.0, 0.0)))
    except (TypeError, ValueError):
        raise ConfigError(f"t, marker and the vectors must be numbers, got {e!r}", key=key) from None
    if len(move) != 3 or len(rot) != 3 or not all(math.isfinite(v) for v in (t,) + move + rot):
        raise ConfigError(f"move and rotate_deg are 3 finite numbers, t finite, got {e!r}", key=key)
    return t, marker, move, rot


@dataclass(frozen=True)
class SimulatorConfig:
    """Private parameters of the ``simulator`` node (config/simulator.yaml, docs/simulation.md)."""

    mode: str = param("corners", "corners: projected corners with pixel noise (fast) | images: rendered images "
                                 "for detector nodes")
    rate: float = param(10.0, "frames per simulated second", unit="Hz")
    seed: int = param(0, "seed of every random draw (rig error, noise, images, odometry)")
    scene: SceneParams = section(SceneParams)
    ring: RingParams = section(RingParams)
    plate: PlateParams = section(PlateParams)
    cameras: CameraParams = section(CameraParams)
    render: RenderParams = section(RenderParams)
    robot: RobotParams = section(RobotParams)
    ground_truth: GroundTruthParams = section(GroundTruthParams)
    odometry: OdometryParams = section(OdometryParams)
    gmapping: GmappingParams = section(GmappingParams)
    laser: LaserParams = section(LaserParams)
    clock: ClockParams = section(ClockParams)
    lockstep: LockstepParams = section(LockstepParams)
    events: tuple = param([], "scene changes at a simulated time: [{t: 20, marker: 17, move: [0, 0.05, 0]}] moves "
                              "marker 17 by 5 cm along the world's y (along its wall) at t = 20 s (optional "
                              "rotate_deg: [rx, ry, rz], a rotation vector about its centre); the map does not know "
                              "(a bumped marker)")

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"expected corners or images, got {self.mode!r}", key="mode")
        _positive("rate", self.rate)
        for k, e in enumerate(self.events):
            scene_event(e, f"events[{k}]")


# --- the labs: kind (the schema's defaults) and harsh (config/lab_harsh.yaml) ---------------------

LABS = ("harsh", "kind")

#: The package's config/ directory: config/lab_<lab>.yaml.
CONFIG_DIR = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "..", "config"))


def lab_file(lab: str) -> str:
    """config/lab_<lab>.yaml: the keys of config/simulator.yaml that the lab changes."""
    if lab not in LABS:
        raise ConfigError(f"expected one of {' | '.join(LABS)}, got {lab!r}", key="lab")
    return os.path.join(CONFIG_DIR, f"lab_{lab}.yaml")


def lab_config(lab: str, base: Optional[SimulatorConfig] = None) -> SimulatorConfig:
    """``base`` (default: the schema's defaults, the kind lab) with ``lab``'s keys applied, as
    simulation.launch ``lab:=`` loads config/lab_<lab>.yaml over config/simulator.yaml."""
    from ..camera import load_yaml_file

    path = lab_file(lab)
    values = load_yaml_file(path) or {}
    return with_overrides(base if base is not None else SimulatorConfig(), dict(_dotted(values)), source=path)


def _dotted(values: Mapping[str, Any], prefix: str = "") -> Iterator[Tuple[str, Any]]:
    for k, v in values.items():
        if isinstance(v, Mapping):
            yield from _dotted(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v
