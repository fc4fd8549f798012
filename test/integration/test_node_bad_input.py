"""Bad input at the localizer node's boundary, without a ROS master (issue 7 §2, §3).

Needs rospy and the messages (it fails without them). The node class is built with rospy's
publishers, subscribers, services, timers and the tf listener/broadcaster replaced by recorders,
and its subscription callbacks (:class:`ros.ring_input.RingSubscriber`) are called directly with
constructed messages: FiducialArray with NaN/inf/huge coordinates, empty or huge lists,
duplicate, unknown and wrong frame ids; CameraInfo with zero K or a wrong D length; initialpose
with NaN. Each callback must return normally (never raise), warn THROTTLED (rospy's throttled
calls, or the pipeline's own throttle, whose records are captured here), and the node must keep
localizing from the good cameras. A hypothesis fuzz does the same with arbitrary field values.
"""
from __future__ import annotations

import io
import logging
import math
import struct
import time
from typing import List
from unittest import mock

import genpy
import numpy as np
import pytest

import rospy  # noqa: E402
import tf2_ros  # noqa: E402
from fiducial_msgs.msg import Fiducial, FiducialArray  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from sensor_msgs.msg import CameraInfo  # noqa: E402
from hypothesis import given  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from aruco_ring_localization.config import with_overrides  # noqa: E402
from aruco_ring_localization.marker_map import MarkerMap  # noqa: E402
from aruco_ring_localization.ring import CameraRing  # noqa: E402
from aruco_ring_localization.ros.conversions import (make_transform_stamped, model_to_camera_info,  # noqa: E402
                                                     observations_to_fiducials)
from aruco_ring_localization.simulation.ring_sim import RingSimulator  # noqa: E402
from aruco_ring_localization.schemas import LocalizerConfig  # noqa: E402
from aruco_ring_localization.simulation.scene import Scene  # noqa: E402

from fuzz_support import EXAMPLES, FUZZ  # noqa: E402
from hypothesis import settings  # noqa: E402
from helpers import REPO, RING_YAML  # noqa: E402

POSE = (5.2, 4.3, 0.4)  # robot on the plate (x, y, yaw)


_RealBuffer = tf2_ros.Buffer


def _buffer_without_master(*args, **kwargs):
    kwargs["debug"] = False  # debug=True registers a service with the master
    return _RealBuffer(*args, **kwargs)


class Recorder(logging.Handler):
    """Collects rospy log calls and the core's log records: (level, throttled, message).

    The core's per-message warnings go through its own throttle (throttle.ThrottledWarnings): they
    count as throttled here; the pipeline's counters say how many lines each problem gave.
    """

    def __init__(self):
        super().__init__(logging.WARNING)
        self.calls: List[tuple] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.calls.append(("warn" if record.levelno < logging.ERROR else "err", True, record.getMessage()))

    def make(self, level: str, throttled: bool):
        def log(*args, **_kw):
            if throttled:
                args = args[1:]  # the period
            msg = args[0] % args[1:] if len(args) > 1 else (args[0] if args else "")
            self.calls.append((level, throttled, str(msg)))
        return log

    def warnings(self, throttled=None):
        return [m for lvl, thr, m in self.calls if lvl in ("warn", "err") and (throttled is None or thr == throttled)]


@pytest.fixture(scope="module")
def world():
    scene = Scene.default()
    ring = CameraRing.load(str(RING_YAML))
    truth = MarkerMap.load(str(REPO / "test" / "data" / "lab_truth_map.yaml"))
    return scene, ring, truth


@pytest.fixture
def node(world, monkeypatch):
    """A LocalizerNode with fake ROS plumbing; ``node.log`` records the log calls."""
    from aruco_ring_localization.ros import localizer as loc_mod

    _, ring, truth = world
    rec = Recorder()
    for name in ("Subscriber", "Service", "Timer"):  # a new recorder per object
        monkeypatch.setattr(rospy, name, mock.MagicMock(name=name, side_effect=lambda *a, **k: mock.MagicMock()))
    # Publishers with one subscriber each: the node builds messages only for topics someone listens to.
    monkeypatch.setattr(rospy, "Publisher", mock.MagicMock(
        name="Publisher", side_effect=lambda *a, **k: mock.MagicMock(**{"get_num_connections.return_value": 1})))
    monkeypatch.setattr(tf2_ros, "TransformListener", mock.MagicMock())
    monkeypatch.setattr(tf2_ros, "TransformBroadcaster", mock.MagicMock())
    monkeypatch.setattr(tf2_ros, "Buffer", _buffer_without_master)
    for level in ("warn", "err", "info", "debug"):
        monkeypatch.setattr(rospy, f"log{level}", rec.make(level, False))
        monkeypatch.setattr(rospy, f"log{level}_throttle", rec.make(level, True))
        monkeypatch.setattr(rospy, f"log{level}_once", rec.make(level, True))
    rospy.rostime.set_rostime_initialized(True)  # wall time, as without use_sim_time
    core_log = logging.getLogger("aruco_ring_localization")
    core_log.addHandler(rec)
    n = loc_mod.LocalizerNode(_config({"input.camera_info_fallback": False, "input.timeout": 0.05}), ring, truth)
    for cam in ring.cameras:
        n.tf_buffer.set_transform_static(make_transform_stamped(cam.T_base_cam, ring.base_frame, cam.frame_id,
                                                                rospy.Time(0)), "test")
    n.log = rec
    n.published_poses = lambda: [c.args[0] for c in n.pub_pose.publish.call_args_list]
    yield n
    core_log.removeHandler(rec)


def _config(overrides) -> LocalizerConfig:
    return with_overrides(LocalizerConfig(), overrides)


def _each_problem_said_once_per_period(node) -> None:
    """Every problem the pipeline counted went out once: a test lasts less than one throttle period (5 s)."""
    w = node.pipeline.warn
    assert w.counts, "no problem was counted"
    for key, n in w.counts.items():
        assert w.said[key] == 1, f"{key}: {w.said[key]} lines for {n} occurrences"


def _raw(msg, md5sum=None, type_name=None) -> rospy.AnyMsg:
    """``msg`` as rospy.AnyMsg delivers it: its bytes and the publisher's connection header."""
    buff = io.BytesIO()
    msg.serialize(buff)
    raw = rospy.AnyMsg().deserialize(buff.getvalue())
    raw._connection_header = {"md5sum": md5sum or msg._md5sum, "type": type_name or msg._type,
                              "callerid": "/publisher"}
    return raw


def _info(ring, name, **changes):
    msg = model_to_camera_info(ring[name].model, ring[name].frame_id)
    for k, v in changes.items():
        setattr(msg, k, v)
    return msg


def _frame_msgs(world, stamp, extra=None, frame_ids=None):
    """Per-camera FiducialArray of the simulated robot at POSE; ``extra[name]`` fiducials appended."""
    scene, ring, _ = world
    sim = RingSimulator(scene, ring, pixel_noise=0.2, seed=3)
    frame = sim.observe(scene.T_world_base(POSE), stamp)
    out = {}
    for cam in ring.cameras:
        msg = FiducialArray()
        msg.header.stamp = rospy.Time.from_sec(stamp)
        msg.header.frame_id = (frame_ids or {}).get(cam.name, cam.frame_id)
        msg.fiducials = observations_to_fiducials(frame.cameras[cam.name].observations) + list(
            (extra or {}).get(cam.name, []))
        out[cam.name] = msg
    return out


def _feed(node, world, n_frames=3, infos=None, extra=None, frame_ids=None):
    """Send camera_info + detections for every camera, n_frames times; return the stamps used."""
    _, ring, _ = world
    stamps = []
    for k in range(n_frames):
        stamp = time.time()
        stamps.append(stamp)
        for name in ring.names:
            # as rospy hands them over: bytes (the node subscribes with rospy.AnyMsg)
            info = (infos or {}).get(name) or _info(ring, name)
            info.header.seq, info.header.stamp = k + 1, rospy.Time.from_sec(stamp)
            try:
                raw = _raw(info)
            except (struct.error, genpy.SerializationError):  # e.g. a K of 2 values: no publisher can send it
                node.ring_input._on_camera_info(info, name)
            else:
                node.ring_input._on_camera_info_raw(raw, name)
        for name, msg in _frame_msgs(world, stamp, extra, frame_ids).items():
            node.ring_input._on_fiducials_raw(_raw(msg), name)  # as the node's subscription hands them over
        # a skipped camera: the assembler's timeout sends the frame without it
        time.sleep(node.config.input.timeout + 0.01)
        node.ring_input._on_timer(None)
    return stamps


def _fid(fid, corners):
    f = Fiducial()
    f.fiducial_id = fid
    (f.x0, f.y0), (f.x1, f.y1), (f.x2, f.y2), (f.x3, f.y3) = corners
    return f


def _last_error(node):
    poses = node.published_poses()
    assert poses, f"no pose published; warnings: {node.log.warnings()}"
    p = poses[-1].pose.pose.position
    return math.hypot(p.x - POSE[0], p.y - POSE[1])


def test_good_frames_localize(node, world):
    _feed(node, world)
    err = _last_error(node)
    assert err < 0.03, f"position error {err * 100:.2f} cm on clean input"
    assert not node.log.warnings(), node.log.warnings()


BAD_CORNERS = {
    "nan": [(math.nan, 1.0), (10.0, 1.0), (10.0, 10.0), (1.0, 10.0)],
    "inf": [(math.inf, 1.0), (10.0, -math.inf), (10.0, 10.0), (1.0, 10.0)],
    "huge": [(1e30, 1e30), (2e30, 1e30), (2e30, 2e30), (1e30, 2e30)],
    "float_max": [(1.7e308, 0.0), (-1.7e308, 0.0), (0.0, 1.7e308), (0.0, -1.7e308)],
    "degenerate": [(5.0, 5.0)] * 4,
    "bowtie": [(0.0, 0.0), (100.0, 100.0), (100.0, 0.0), (0.0, 100.0)],
}


@pytest.mark.parametrize("kind", sorted(BAD_CORNERS))
def test_malformed_corners_are_dropped_with_a_throttled_warning(node, world, kind):
    _, _, truth = world
    bad = {"cam0": [_fid(truth.ids[0], BAD_CORNERS[kind])], "cam3": [_fid(999, BAD_CORNERS[kind])]}
    _feed(node, world, extra=bad)
    assert _last_error(node) < 0.03, f"{kind}: position error {_last_error(node) * 100:.2f} cm"
    assert node.log.warnings(throttled=True), f"{kind}: no throttled warning: {node.log.calls}"
    assert not node.log.warnings(throttled=False), f"{kind}: unthrottled warning {node.log.warnings(False)}"
    rejected = sum(sum(v.values()) for v in node.pipeline.input.rejected.values())
    assert rejected >= 2 * 3, f"{kind}: {node.pipeline.input.rejected}"
    _each_problem_said_once_per_period(node)


def test_duplicate_ids_in_one_image_are_dropped(node, world):
    scene, ring, truth = world
    msgs = _frame_msgs(world, time.time())
    cam = max(msgs, key=lambda n: len(msgs[n].fiducials))
    dup = msgs[cam].fiducials[0]
    _feed(node, world, extra={cam: [dup, dup]})
    assert node.pipeline.input.rejected[cam].get("duplicate id", 0) >= 3, node.pipeline.input.rejected
    assert _last_error(node) < 0.05


def test_unknown_ids_are_ignored(node, world):
    quad = [(100.0, 100.0), (200.0, 100.0), (200.0, 200.0), (100.0, 200.0)]
    _feed(node, world, extra={name: [_fid(3000 + k, quad)] for k, name in enumerate(world[1].names)})
    assert _last_error(node) < 0.03


def test_negative_and_out_of_range_ids(node, world):
    quad = [(100.0, 100.0), (200.0, 100.0), (200.0, 200.0), (100.0, 200.0)]
    _feed(node, world, extra={"cam1": [_fid(-5, quad), _fid(2 ** 31 - 1, quad)]})
    assert _last_error(node) < 0.03


def test_empty_fiducial_lists_publish_nothing_new_and_do_not_raise(node, world):
    _feed(node, world, n_frames=2)
    before = len(node.published_poses())
    _, ring, _ = world
    for _ in range(3):
        stamp = time.time()
        for name in ring.names:
            msg = FiducialArray()
            msg.header.stamp = rospy.Time.from_sec(stamp)
            msg.header.frame_id = ring[name].frame_id
            node.ring_input._on_fiducials(msg, name)
    # predict-only: the pose may still be published (predicted), but the node is alive
    assert len(node.published_poses()) >= before


def test_huge_fiducial_list(node, world):
    rng = np.random.default_rng(7)
    quads = [_fid(int(i), [(x, y), (x + 20, y), (x + 20, y + 20), (x, y + 20)])
             for i, (x, y) in zip(rng.integers(0, 1000, 3000), rng.uniform(0, 1200, (3000, 2)))]
    t0 = time.perf_counter()
    _feed(node, world, n_frames=1, extra={"cam2": quads})
    assert time.perf_counter() - t0 < 30.0
    # The good cameras still give a pose (cam2's duplicate-laden garbage is dropped or rejected).
    assert _last_error(node) < 0.10, f"{_last_error(node) * 100:.1f} cm"


@pytest.mark.parametrize("frame_id", ["no_such_frame", "", "/cam0_optical_frame"])
def test_wrong_frame_id_skips_that_camera(node, world, frame_id):
    _feed(node, world, frame_ids={"cam0": frame_id})
    assert _last_error(node) < 0.05
    if frame_id == "no_such_frame":
        assert any("no tf" in w for w in node.log.warnings(throttled=True)), node.log.calls


@pytest.mark.parametrize("change", [
    {"K": [0.0] * 9}, {"K": [math.nan] * 9}, {"D": [0.1, 0.2]}, {"width": 0, "height": 0},
    {"distortion_model": "no_such_model"}, {"K": [1.0, 2.0]},
])
def test_bad_camera_info_ignores_the_camera(node, world, change):
    _, ring, _ = world
    infos = {"cam0": _info(ring, "cam0", **change)}
    _feed(node, world, infos=infos)
    assert any("camera_info" in w for w in node.log.warnings(throttled=True)), (change, node.log.calls)
    assert _last_error(node) < 0.05
    assert node.pipeline.input.skipped["cam0"], "the camera with bad camera_info was used"


def test_repeated_camera_info_is_not_deserialised_and_a_change_is_applied(node, world, monkeypatch):
    """camera_info arrives as bytes: the same bytes after seq and stamp are dropped before
    deserialising; a new K (or a new frame_id with the same intrinsics) is read."""
    from aruco_ring_localization.ros import ring_input

    _, ring, _ = world
    reads, applied = [], []
    real_info, real_apply = ring_input.CameraInfo, node.pipeline.on_camera_info

    class CountingInfo(real_info):
        __slots__ = ()

        def deserialize(self, buff):
            reads.append(len(buff))
            return super().deserialize(buff)

    from aruco_ring_localization.ros import conversions

    monkeypatch.setattr(conversions, "CameraInfo", CountingInfo)   # where camera_info_from_bytes reads it
    monkeypatch.setattr(node.pipeline, "on_camera_info",
                        lambda cam, model: (applied.append(model), real_apply(cam, model))[1])
    info = _info(ring, "cam0")
    for seq in range(1, 6):  # what a camera sends with every image: same content, new seq and stamp
        info.header.seq, info.header.stamp = seq, rospy.Time.from_sec(100.0 + 0.1 * seq)
        node.ring_input._on_camera_info_raw(_raw(info), "cam0")
    assert len(reads) == 1 and len(applied) == 1, (reads, applied)
    info.header.frame_id = "cam0_other"  # other bytes, same intrinsics: read, not applied again
    node.ring_input._on_camera_info_raw(_raw(info), "cam0")
    assert len(reads) == 2 and len(applied) == 1, (reads, applied)
    K = list(info.K)
    K[0] *= 1.01
    info.K = K
    node.ring_input._on_camera_info_raw(_raw(info), "cam0")
    node.ring_input._on_camera_info_raw(_raw(info), "cam0")
    assert len(reads) == 3 and len(applied) == 2, (reads, applied)
    assert node.pipeline.input.camera_model("cam0").K[0, 0] == pytest.approx(K[0])
    assert not node.log.warnings(), node.log.calls


def test_camera_info_connection_pauses_after_a_repeat_only(node, world):
    """The subscription's callback: after a repeat of the camera_info in force, the connection's
    thread waits input/camera_info_check_period (rospy reads nothing from it meanwhile); after a
    new, a changed, an unusable or a mistyped camera_info it does not; shutdown ends a wait."""
    _, ring, _ = world
    ri = node.ring_input
    assert ri.info_check_period == LocalizerConfig().input.camera_info_check_period == 2.0
    waits = []

    class Stopping:
        def wait(self, timeout):
            waits.append(timeout)
            return False

    real_stopping, ri._stopping = ri._stopping, Stopping()
    info = _info(ring, "cam0")
    ri._on_camera_info_sub(_raw(info), "cam0")        # the first: applied, read on at once
    assert waits == [] and node.pipeline.input.camera_model("cam0") is not None
    info.header.seq = 2
    ri._on_camera_info_sub(_raw(info), "cam0")        # a repeat: pause
    assert waits == [2.0]
    K = list(info.K)
    K[0] *= 1.01
    info.K = K
    ri._on_camera_info_sub(_raw(info), "cam0")        # changed: applied, no pause
    assert waits == [2.0]
    assert node.pipeline.input.camera_model("cam0").K[0, 0] == pytest.approx(K[0])
    infos = [m for lvl, _, m in node.log.calls if lvl == "info" and "cam0 intrinsics from camera_info" in m]
    assert len(infos) == 1 and f"cam0 intrinsics from camera_info: fx {info.K[0] / 1.01:.3f}" in infos[0], infos
    ri._on_camera_info_sub(_raw(info), "cam0")        # its repeat: pause
    assert waits == [2.0, 2.0]
    ri._on_camera_info_sub(_raw(_info(ring, "cam0", K=[0.0] * 9)), "cam0")   # unusable: no pause
    ri._on_camera_info_sub(_raw(_info(ring, "cam0", width=7), md5sum=Fiducial._md5sum, type_name=Fiducial._type),
                           "cam0")                    # another type: no pause
    assert any(Fiducial._type in w for w in node.log.warnings(throttled=True)), node.log.calls
    assert waits == [2.0, 2.0]
    ri.info_check_period = 0.0                        # 0: never paused
    ri._on_camera_info_sub(_raw(info), "cam0")
    assert waits == [2.0, 2.0]
    ri._stopping = real_stopping
    assert not ri._stopping.is_set()
    ri.shutdown()
    assert ri._stopping.is_set() and ri._stopping.wait(10.0)   # a wait in progress returns at once


def test_tf_listener_drops_our_own_tf_as_bytes_and_stores_and_checks_the_others(node):
    """Our /tf messages coming back are dropped before deserialising (what we send is put in the
    buffer as it goes out); another node's are stored under its name and go to the authority
    check; another type or unreadable bytes are warned about; a jump back in time clears the buffer."""
    from tf2_msgs.msg import TFMessage

    listener, buf = node.tf_listener, node.tf_buffer
    own = listener.own_name
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 0.0]
    stamp = rospy.Time.now()

    def tf_raw(sender, child="base_link", buff=None):
        raw = _raw(TFMessage(transforms=[make_transform_stamped(T, "map", child, stamp)]))
        raw._connection_header["callerid"] = sender
        if buff is not None:
            raw._buff = buff
        return raw

    listener._on_tf(tf_raw(own, buff=b"\x01garbage"))   # ours: not even read
    assert not buf.can_transform("map", "base_link", rospy.Time(0)) and not node.log.warnings(), node.log.calls
    node.publish_tf(T, stamp)                             # what we send is in the buffer at once
    assert buf.can_transform("map", "base_link", rospy.Time(0))
    assert node._tf_child == "base_link"
    listener._on_tf(tf_raw("/other_localizer", child="base_link"))   # another node on our child frame
    assert any("/other_localizer also publishes tf map -> base_link" in w for w in node.log.warnings(True)), \
        node.log.calls
    listener._on_tf(tf_raw("/odometry", child="odom_only"))          # another frame: stored, no warning
    assert buf.can_transform("map", "odom_only", rospy.Time(0))
    assert sum("also publishes tf" in w for w in node.log.warnings(True)) == 1, node.log.calls
    wrong = tf_raw("/confused")
    wrong._connection_header["md5sum"] = Fiducial._md5sum
    listener._on_tf(wrong)
    listener._on_tf(tf_raw("/broken", buff=b"\x05\x00\x00\x00ab"))
    assert any("/tf from /confused" in w and "ignored" in w for w in node.log.warnings(True)), node.log.calls
    assert any("unreadable /tf message from /broken" in w for w in node.log.warnings(True)), node.log.calls
    listener._last_update = rospy.Time.now() + rospy.Duration(60.0)   # ROS time went back (a bag loop)
    node.publish_tf(T, stamp)
    assert not buf.can_transform("map", "odom_only", rospy.Time(0)), "the buffer was not cleared"
    assert any("jumped back" in w for w in node.log.warnings(False)), node.log.calls


def test_camera_info_of_another_type_or_unreadable_is_warned_and_ignored(node, world):
    _, ring, _ = world
    info = _info(ring, "cam0")
    node.ring_input._on_camera_info_raw(_raw(info, md5sum=Fiducial._md5sum, type_name=Fiducial._type), "cam0")
    assert any("camera_info" in w and Fiducial._type in w for w in node.log.warnings(throttled=True)), node.log.calls
    truncated = _raw(info)
    truncated._buff = truncated._buff[:40]
    node.ring_input._on_camera_info_raw(truncated, "cam0")
    assert any("unreadable camera_info" in w for w in node.log.warnings(throttled=True)), node.log.calls
    assert node.pipeline.input.camera_model("cam0") is None
    # an unusable camera_info is read (and warned about, throttled) every time, not remembered as seen
    bad = _info(ring, "cam0", K=[0.0] * 9)
    for seq in (1, 2):
        bad.header.seq = seq
        node.ring_input._on_camera_info_raw(_raw(bad), "cam0")
    assert sum("unusable camera_info" in w for w in node.log.warnings(throttled=True)) == 2, node.log.calls
    assert node.pipeline.input.camera_model("cam0") is None
    node.ring_input._on_camera_info_raw(_raw(info), "cam0")  # then a good one is applied
    assert node.pipeline.input.camera_model("cam0") is not None


def test_fiducial_vertices_cut_short_or_of_another_type_are_warned_and_dropped(node, world):
    _, ring, _ = world
    _feed(node, world, n_frames=2)
    poses = len(node.published_poses())
    stamp = time.time()
    msgs = _frame_msgs(world, stamp)
    for name, msg in msgs.items():
        raw = _raw(msg)
        raw._buff = raw._buff[:-5]  # the last fiducial cut short
        node.ring_input._on_fiducials_raw(raw, name)
    assert any("unreadable fiducial_vertices" in w and "fiducials:" in w for w in node.log.warnings(throttled=True)), \
        node.log.calls
    node.ring_input._on_fiducials_raw(_raw(_info(ring, "cam0")), "cam0")  # a CameraInfo publisher on the topic
    node.ring_input._on_fiducials_raw(_raw(msgs["cam1"], md5sum=CameraInfo._md5sum, type_name=CameraInfo._type),
                                      "cam1")
    assert sum(CameraInfo._type in w for w in node.log.warnings(throttled=True)) == 2, node.log.calls
    time.sleep(node.config.input.timeout + 0.02)
    node.ring_input._on_timer(None)
    assert len(node.published_poses()) == poses, "a pose from unreadable messages"
    assert "cam0" not in node.ring_input.last_arrival or node.ring_input.last_arrival["cam0"] < stamp
    _feed(node, world, n_frames=1)  # and the next good messages localize
    assert len(node.published_poses()) == poses + 1
    assert _last_error(node) < 0.05


def test_periodic_tasks_run_on_the_poll_timer_and_a_failing_one_does_not_stop_it(node, world, monkeypatch):
    """The diagnostics and the marker array go out from the ring input's poll timer (one timer thread)."""
    clock = [1000.0]
    monkeypatch.setattr(node.ring_input, "now", lambda: clock[0])
    ran, polls = [], []
    node.ring_input._periodic.clear()
    node.ring_input.every(1.0, lambda: ran.append(("a", clock[0])))

    def broken():
        raise RuntimeError("boom")

    node.ring_input.every(0.5, broken)
    real_poll = node.pipeline.poll
    monkeypatch.setattr(node.pipeline, "poll", lambda now: (polls.append(now), real_poll(now))[1])
    for _ in range(25):  # 2.5 s at the 20 Hz poll timer
        clock[0] += 0.1
        node.ring_input._on_timer(None)
    assert len(polls) == 25
    assert [t for _, t in ran] == pytest.approx([1001.0, 1002.0]), ran
    assert any("broken" in w and "boom" in w for w in node.log.warnings()), node.log.calls
    clock[0] -= 60.0  # the clock went back (a bag loop): the tasks run at once and go on from there
    node.ring_input._on_timer(None)
    assert ran[-1][1] == pytest.approx(clock[0])


def test_poll_timer_skips_a_poll_that_could_find_nothing_new(node, world, monkeypatch):
    """A second poll at the same ROS time with no other pipeline call in between is skipped (under
    use_sim_time the 20 Hz timer fires twice per 10 Hz /clock step); any call in between, or a clock
    that moved, polls again, and a ring frame waiting for its timeout still goes out."""
    _, ring, _ = world
    clock = [time.time()]
    monkeypatch.setattr(node.ring_input, "now", lambda: clock[0])
    polls = []
    real_poll = node.pipeline.poll
    monkeypatch.setattr(node.pipeline, "poll", lambda now: (polls.append(now), real_poll(now))[1])
    node.ring_input._periodic.clear()
    for name in ring.names:
        node.ring_input._on_camera_info_raw(_raw(_info(ring, name)), name)
    msgs = _frame_msgs(world, clock[0])
    for name in ring.names[:-1]:   # the last camera does not report: the frame waits for input/timeout
        node.ring_input._on_fiducials_raw(_raw(msgs[name]), name)
    poses = len(node.published_poses())
    node.ring_input._on_timer(None)
    node.ring_input._on_timer(None)   # same clock, nothing in between: skipped
    assert polls == [clock[0]]
    node.on_cmd_vel(mock.MagicMock(**{"linear.x": 0.0, "linear.y": 0.0, "angular.z": 0.0}))
    node.ring_input._on_timer(None)   # a call in between: polled
    assert polls == [clock[0], clock[0]]
    assert len(node.published_poses()) == poses, "the frame went out before its timeout"
    clock[0] += node.config.input.timeout + 0.01
    node.ring_input._on_timer(None)   # the clock moved past the timeout: polled, the frame goes out
    node.ring_input._on_timer(None)
    assert len(polls) == 3
    assert len(node.published_poses()) == poses + 1
    assert node.pipeline.last_track.stamp == pytest.approx(msgs[ring.names[0]].header.stamp.to_sec())


def test_poll_timer_queues_no_call_when_nothing_ran_since_the_last_poll(node, world, monkeypatch):
    """The timer's second firing at one clock value takes neither lock (no call queued); a call
    waiting in the inbox, one that ran since, or a clock that moved makes it poll again."""
    _, ring, _ = world
    clock = [time.time()]
    ri = node.ring_input
    monkeypatch.setattr(ri, "now", lambda: clock[0])
    ri._periodic.clear()
    calls = []
    real_call = ri.call
    monkeypatch.setattr(ri, "call", lambda fn, *a: (calls.append(getattr(fn, "__name__", fn)), real_call(fn, *a))[1])
    ri._on_timer(None)
    ri._on_timer(None)   # same clock, nothing in between: no call at all
    assert calls == ["_poll"]
    from aruco_ring_localization.ros.ring_input import _Call
    ri._inbox.append(_Call(lambda: None, ()))   # a call that arrived, not yet run
    assert not ri._idle_since_poll()
    ri._on_timer(None)   # polls, after running the waiting call
    assert calls == ["_poll", "_poll"] and not ri._inbox
    ri._on_timer(None)
    assert calls == ["_poll", "_poll"]
    node.on_cmd_vel(mock.MagicMock(**{"linear.x": 0.0, "linear.y": 0.0, "angular.z": 0.0}))
    ri._on_timer(None)   # a call ran since
    assert calls == ["_poll", "_poll", "on_motion", "_poll"]
    clock[0] += 0.05
    ri._on_timer(None)   # the clock moved
    assert calls[-1] == "_poll" and len(calls) == 5


def test_localizer_node_publishes_diagnostics_and_markers_from_the_poll_timer(node):
    names = [getattr(fn, "__name__", "") for _, fn, _ in node.ring_input._periodic]
    assert names == ["publish_diagnostics", "publish_markers"], names


def test_missing_camera_info_and_tf_for_one_camera(node, world):
    _, ring, _ = world
    # No camera_info ever for cam5: skipped with a throttled hint, the others work.
    stamp = time.time()
    for name in ring.names:
        if name != "cam5":
            node.ring_input._on_camera_info_raw(_raw(_info(ring, name)), name)
    for name, msg in _frame_msgs(world, stamp).items():
        node.ring_input._on_fiducials(msg, name)
    time.sleep(node.config.input.timeout + 0.02)
    node.ring_input._on_timer(None)
    assert node.pipeline.input.skipped["cam5"], node.pipeline.input.skipped
    assert any("camera_info" in w for w in node.log.warnings(throttled=True))
    assert _last_error(node) < 0.05


@pytest.mark.parametrize("field,value", [("x", math.nan), ("y", math.inf), ("qw", math.nan), ("qz", 0.0)])
def test_initialpose_with_nan_is_ignored(node, world, field, value):
    _feed(node, world, n_frames=2)
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = "map"
    msg.pose.pose.position.x, msg.pose.pose.position.y = 1.0, 1.0
    msg.pose.pose.orientation.w = 1.0
    if field in ("x", "y"):
        setattr(msg.pose.pose.position, field, value)
    else:
        msg.pose.pose.orientation.w = 0.0 if field == "qz" else value  # qz: all-zero quaternion
    node.on_initialpose(msg)
    assert any("initialpose" in w for w in node.log.warnings()), node.log.calls
    pose = node.pipeline.filter.pose
    assert math.hypot(pose[0] - POSE[0], pose[1] - POSE[1]) < 0.05, f"track moved to {pose}"


def test_diagnostics_and_markers_callbacks_run(node, world):
    _feed(node, world, n_frames=1)
    node.publish_diagnostics()
    node.publish_markers()
    arr = node.diagnostics.updater.publisher.publish.call_args[0][0]  # diagnostic_updater's /diagnostics
    assert any(s.name.endswith(": filter") for s in arr.status), [s.name for s in arr.status]
    assert {s.hardware_id for s in arr.status if ": camera " in s.name} == set(node.pipeline.input.camera_names)
    # Nobody on /diagnostics (not latched): nothing is built or published.
    publisher = node.diagnostics.updater.publisher
    publisher.get_num_connections.return_value = 0
    sent = publisher.publish.call_count
    with mock.patch.object(node.pipeline, "diagnostics", side_effect=AssertionError("built for nobody")):
        node.publish_diagnostics()
    assert publisher.publish.call_count == sent


# --- fuzz ------------------------------------------------------------------------------------

floats = st.floats(allow_nan=True, allow_infinity=True) | st.floats(-2000, 2000)
fiducial = st.builds(lambda i, c: _fid(i, [(c[0], c[1]), (c[2], c[3]), (c[4], c[5]), (c[6], c[7])]),
                     st.integers(-2 ** 31, 2 ** 31 - 1) | st.sampled_from([17, 42, 95, 126, 203]),
                     st.lists(floats, min_size=8, max_size=8))


@settings(FUZZ, max_examples=max(40, EXAMPLES // 8))  # each example builds a node (~0.2 s)
@given(st.data())
def test_fuzz_node_callbacks_never_raise(world, data):
    """Arbitrary detections, camera_info and initialpose: no callback ever raises."""
    scene, ring, truth = world
    with mock.patch.object(rospy, "Publisher"), mock.patch.object(rospy, "Subscriber"), \
            mock.patch.object(rospy, "Service"), mock.patch.object(rospy, "Timer"), \
            mock.patch.object(tf2_ros, "TransformListener"), mock.patch.object(tf2_ros, "TransformBroadcaster"), \
            mock.patch.object(tf2_ros, "Buffer", _buffer_without_master), \
            mock.patch.object(rospy, "logwarn_throttle"), mock.patch.object(rospy, "logwarn"), \
            mock.patch.object(rospy, "loginfo"):
        from aruco_ring_localization.ros import localizer as loc_mod

        rospy.rostime.set_rostime_initialized(True)
        n = loc_mod.LocalizerNode(_config({"input.camera_info_fallback": True, "input.use_tf": False}), ring, truth)
        base = time.time()
        for _ in range(data.draw(st.integers(1, 6), label="events")):
            name = data.draw(st.sampled_from(ring.names), label="camera")
            kind = data.draw(st.sampled_from(["fid", "fid", "rawfid", "info", "raw", "initialpose", "timer"]),
                             label="kind")
            if kind == "fid":
                msg = FiducialArray()
                msg.header.stamp = rospy.Time.from_sec(base + data.draw(st.floats(-5, 5), label="dt"))
                msg.header.frame_id = data.draw(st.sampled_from([ring[name].frame_id, "", "x", "/base_link"]))
                msg.fiducials = data.draw(st.lists(fiducial, max_size=6), label="fiducials")
                if data.draw(st.booleans(), label="as bytes"):
                    n.ring_input._on_fiducials_raw(_raw(msg), name)
                else:
                    n.ring_input._on_fiducials(msg, name)
            elif kind == "rawfid":  # arbitrary bytes on fiducial_vertices, or a cut-off message
                msg = _frame_msgs(world, base)[name]
                raw = _raw(msg)
                raw._buff = data.draw(st.binary(max_size=600) | st.integers(0, len(raw._buff)).map(
                    lambda k, b=raw._buff: b[:k]), label="bytes")
                n.ring_input._on_fiducials_raw(raw, name)
            elif kind == "info":
                info = model_to_camera_info(ring[name].model, ring[name].frame_id)
                info.K = data.draw(st.lists(floats, min_size=9, max_size=9) | st.just(list(info.K)), label="K")
                info.D = data.draw(st.lists(floats, max_size=8), label="D")
                info.width = data.draw(st.integers(0, 5000), label="w")
                info.height = data.draw(st.integers(0, 5000), label="h")
                info.distortion_model = data.draw(st.sampled_from(["plumb_bob", "equidistant", "", "bad"]))
                try:
                    raw = _raw(info)
                except (struct.error, genpy.SerializationError):
                    n.ring_input._on_camera_info(info, name)
                else:
                    n.ring_input._on_camera_info_raw(raw, name)
            elif kind == "raw":  # arbitrary bytes on camera_info, or a cut-off message
                raw = _raw(model_to_camera_info(ring[name].model, ring[name].frame_id))
                raw._buff = data.draw(st.binary(max_size=400) | st.integers(0, len(raw._buff)).map(
                    lambda k, b=raw._buff: b[:k]), label="bytes")
                n.ring_input._on_camera_info_raw(raw, name)
            elif kind == "initialpose":
                msg = PoseWithCovarianceStamped()
                msg.header.frame_id = data.draw(st.sampled_from(["map", "", "odom"]), label="frame")
                p = msg.pose.pose
                p.position.x, p.position.y, p.orientation.z, p.orientation.w = data.draw(
                    st.lists(floats, min_size=4, max_size=4), label="pose")
                n.on_initialpose(msg)
            else:
                n.ring_input._on_timer(None)
        n.publish_diagnostics()


# --- start-up with bad files: a clear fatal message naming the file and key, exit code 1 ---------

def _bad_files(tmp_path):
    ok_map = (REPO / "test" / "data" / "lab_truth_map.yaml").read_text()
    files = {
        "missing": (str(tmp_path / "nope.yaml"), "not found"),
        "empty": ("", "empty"),
        "negative size": (ok_map.replace("size: 0.2", "size: -0.2", 1), "markers[0].size"),
        "duplicate id": (ok_map.replace("- id: 42", "- id: 17", 1), "markers[1].id"),
        "newer version": (ok_map.replace("format_version: 1", "format_version: 2", 1), "format_version"),
        "truncated": (ok_map[: ok_map.index("rotation: [") + 14], "line"),
    }
    out = {}
    for name, (text, key) in files.items():
        if name == "missing":
            out[name] = (text, key)
            continue
        path = tmp_path / f"{name.replace(' ', '_')}.yaml"
        path.write_text(text)
        out[name] = (str(path), key)
    return out


@pytest.mark.parametrize("case", ["missing", "empty", "negative size", "duplicate id", "newer version", "truncated"])
def test_localizer_exits_cleanly_on_a_bad_map_file(tmp_path, monkeypatch, case):
    from aruco_ring_localization.ros import localizer as loc_mod

    path, key = _bad_files(tmp_path)[case]
    rec = Recorder()
    monkeypatch.setattr(rospy, "init_node", lambda *a, **k: None)
    monkeypatch.setattr(rospy, "spin", lambda: pytest.fail("the node started with a bad map"))
    monkeypatch.setattr(rospy, "signal_shutdown", lambda *a: None)
    monkeypatch.setattr(rospy, "logfatal", rec.make("fatal", False))
    monkeypatch.setattr(loc_mod.log_bridge, "install", lambda: None)
    monkeypatch.setattr(loc_mod, "read_config", lambda cls, **k: with_overrides(cls(), {"map_file": path}))
    assert loc_mod.main([]) == 1
    fatal = [m for lvl, _, m in rec.calls if lvl == "fatal"]
    assert fatal and path in fatal[0] and key in fatal[0], f"{case}: {fatal}"


def test_mapper_exits_cleanly_on_a_bad_ring_file(tmp_path, monkeypatch):
    from aruco_ring_localization.ros import mapper as mapper_mod

    ring = tmp_path / "ring.yaml"
    ring.write_text(RING_YAML.read_text().replace("name: cam3", "name: cam2", 1)
                    .replace("camera_info: camera_info/", f"camera_info: {RING_YAML.parent}/camera_info/"))
    rec = Recorder()
    monkeypatch.setattr(rospy, "init_node", lambda *a, **k: None)
    monkeypatch.setattr(rospy, "spin", lambda: pytest.fail("the node started with a bad ring file"))
    monkeypatch.setattr(rospy, "logfatal", rec.make("fatal", False))
    monkeypatch.setattr(mapper_mod.log_bridge, "install", lambda: None)
    monkeypatch.setattr(mapper_mod, "read_config", lambda cls, **k: with_overrides(cls(), {"ring_file": str(ring)}))
    assert mapper_mod.main([]) == 1
    fatal = [m for lvl, _, m in rec.calls if lvl == "fatal"]
    assert fatal and str(ring) in fatal[0] and "duplicate" in fatal[0], fatal
