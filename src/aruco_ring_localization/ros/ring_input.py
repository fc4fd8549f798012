"""The ring's subscriptions, wired to a pipeline (shared by the mapper and the localizer nodes).

:class:`RingSubscriber` subscribes, for each input camera ``c`` of the pipeline, to
``<ns>/fiducial_vertices`` (fiducial_msgs/FiducialArray) and ``<ns>/camera_info``
(sensor_msgs/CameraInfo), where ``<ns>`` is the camera's ``namespace`` in the ring file (relative,
so the node's namespace applies), converts the messages and calls the pipeline's events
(:mod:`aruco_ring_localization.pipeline`) with ``now`` = ROS time:

* camera_info -> ``on_camera_info`` once per change (logged, at most every 5 s per camera; an
  unusable one: throttled warning). The subscription takes the raw bytes (``rospy.AnyMsg``): a
  message whose bytes after the header's seq and stamp are those of the last one applied is
  dropped without being deserialised (each camera sends the same one with every image: 8 per ring
  frame); another is checked to be a sensor_msgs/CameraInfo (the publisher's md5sum) and
  deserialised. After such a repeat, the connection's thread (rospy reads each connection on its
  own thread and calls the callback there) waits ``input/camera_info_check_period`` (wall time)
  before it reads again: what came meanwhile waits in the socket, and rospy's next read takes it
  all and hands over only the newest (``queue_size`` 1). So a changed camera_info is applied
  within that delay, and the 8 camera_info connections cost one thread wake-up each per period
  instead of one per ring frame;
* with ``use_tf``, ``T_base_cam`` looked up in tf once per (camera, header.frame_id) ->
  ``on_extrinsics``; until tf has it the pipeline skips that camera and says so;
* fiducial_vertices -> ``on_detections``, also taken as bytes (``rospy.AnyMsg``, type-checked by
  md5sum): the fixed-size fiducial records are read with one ``numpy.frombuffer``
  (:func:`conversions.fiducial_array_bytes_to_observations`), not a genpy object per fiducial; a
  timer calls ``poll`` (timeouts, predict-only output),
  and the node's own periodic tasks (:meth:`RingSubscriber.every`: the localizer's diagnostics
  and marker array) on the same timer thread: under ``use_sim_time`` every /clock message wakes
  every rospy timer thread, so one timer instead of three is two thread wake-ups less per /clock.

Every pipeline call runs under one lock (:meth:`call`, also for the node's other inputs), in the
order the calls arrived, with ``now`` read as they arrive: rospy runs each subscription's callback
in its own thread, and a lock is not fair, so without this a timer poll that came after a camera's
message could run before it and time the ring frame out while its cameras wait at the lock (a
mapper busy with its live preview split ring frames so). What the calls return is queued in call
order and handed to ``deliver`` by one thread at a time, in that order. A package error
(:class:`ArucoRingError`) from a message is logged throttled: a bad message never kills the node.

Bounded work per message (issue 14): rospy calls a subscriber's callback on the thread that reads
its connection, so a slow callback leaves messages in the socket, where ``queue_size`` cannot drop
them (a flood backed up 14 s). The localizer's subscriptions read up to :data:`BUFF_SIZE` bytes at
once, so rospy sees every waiting message and keeps only the newest ``queue_size``; a detection message
is converted only up to ``input/max_detections`` + 1 quads (the pipeline drops a longer one whole).
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Any, Callable, Dict, List, Optional, Set

import numpy as np
import rospy
import tf2_ros
from fiducial_msgs.msg import FiducialArray
from sensor_msgs.msg import CameraInfo

from ..errors import ArucoRingError, MeasurementError
from .conversions import (camera_info_body, camera_info_from_bytes, camera_info_to_model,
                          fiducial_array_bytes_to_observations, fiducial_array_to_observations, msg_to_transform,
                          stamp_to_sec, type_mismatch)

WARN_PERIOD = 5.0  # s between repeats of one throttled warning

#: rospy's per-read buffer for our subscriptions, bytes: larger than any backlog the kernel holds
#: (a 3,000-quad FiducialArray is 120 kB), so queue_size drops old messages instead of the socket
#: keeping them (rospy's default, 64 kB, is smaller than such a message).
BUFF_SIZE = 1 << 24

#: Detection messages the mapper keeps per camera while its callback is busy: 10 s of a 10 Hz
#: ring. With 5, a callback stalled for a second on a loaded machine (load 19 on 2 cores) lost a
#: camera's message and the mapper added ring frames without every camera.
MAPPER_QUEUE_SIZE = 100


class _Now:
    """Placeholder in :meth:`RingSubscriber.call`'s arguments for the node's clock at arrival."""

    def __repr__(self) -> str:
        return "NOW"


NOW = _Now()


class _Call:
    __slots__ = ("fn", "args", "out", "error")

    def __init__(self, fn: Callable[..., Any], args: tuple):
        self.fn, self.args = fn, args
        self.out: Any = None
        self.error: Optional[BaseException] = None


class RingSubscriber:
    """Subscriptions of the ring's cameras feeding ``pipeline``; ordered delivery of its outputs.

    Args:
        pipeline: a :class:`LocalizationPipeline` or :class:`MappingPipeline`.
        deliver: called with each non-empty output of a pipeline call, in call order.
        name: the node's name, in log lines.
        use_tf: extrinsics from tf (else the pipeline uses the ring file's).
        poll_period: period (s) of the timer calling ``pipeline.poll``.
        tf_buffer: an existing tf2 Buffer to share (one with a listener is created otherwise).
        queue_size: detection messages kept per camera when the callback falls behind (the
            localizer keeps 1: an older frame would only be overtaken; the mapper keeps
            :data:`MAPPER_QUEUE_SIZE`: a map wants every ring frame whole).
        buff_size: rospy's read buffer per subscription, bytes: the localizer's :data:`BUFF_SIZE`
            (never a backlog); rospy's default 64 kB for the mapper. That buffer does not keep
            a backlog in the socket for small messages: one read takes dozens of detection
            messages (about 1 kB each) and rospy keeps only the newest ``queue_size`` of them,
            so the mapper's queue is what must be deep.
    """

    def __init__(self, pipeline: Any, deliver: Callable[[Any], None], name: str, use_tf: bool = True,
                 poll_period: float = 0.05, tf_buffer: Optional[tf2_ros.Buffer] = None, queue_size: int = 5,
                 buff_size: int = 65536):
        self.pipeline = pipeline
        self._deliver_fn = deliver
        self._name = name
        self.use_tf = use_tf
        self.lock = threading.Lock()           # guards the pipeline
        self._deliver_lock = threading.Lock()  # one deliver() at a time
        self._queue: "collections.deque[Any]" = collections.deque()  # filled in call order under lock
        self._inbox_lock = threading.Lock()    # guards the inbox only (held for an append or a pop)
        self._inbox: "collections.deque[_Call]" = collections.deque()  # calls in arrival order
        self._info_keys: Dict[str, tuple] = {}
        self._info_bytes: Dict[str, bytes] = {}  # camera -> camera_info bytes after seq and stamp, last applied
        self._info_logged: Dict[str, float] = {}  # camera -> wall time its intrinsics were last logged
        #: wall seconds a camera_info connection is not read after a repeat of the one in force (0: never paused)
        self.info_check_period = float(getattr(pipeline.input.params, "camera_info_check_period", 0.0))
        self._stopping = threading.Event()        # set at shutdown: ends the camera_info pauses
        self._periodic: List[list] = []           # [period, function, last run (ROS time)] (every())
        self._runs = 0                            # pipeline calls run so far (under the lock)
        self._polled: Optional[tuple] = None      # (now, _runs) of the last poll that ran (_poll)
        #: camera -> ROS time its last fiducial_vertices message arrived (before waiting for the lock).
        self.last_arrival: Dict[str, float] = {}
        #: cameras whose message is being handled right now (waiting for the lock, typically).
        self._handling: Set[str] = set()
        self._tf_frames: Dict[str, str] = {}   # camera -> frame_id its extrinsics were looked up for
        ring = pipeline.input.calibrated_ring
        self._ring = ring
        if use_tf:
            self.tf_buffer = tf_buffer or tf2_ros.Buffer()
            self._tf_listener = None if tf_buffer else tf2_ros.TransformListener(self.tf_buffer)
        self._subs: List[rospy.Subscriber] = []
        for camera in pipeline.camera_names:
            ns = ring[camera].namespace.strip("/")
            prefix = f"{ns}/" if ns else ""
            self._subs.append(rospy.Subscriber(f"{prefix}fiducial_vertices", rospy.AnyMsg, self._on_fiducials_raw,
                                               callback_args=camera, queue_size=queue_size, buff_size=buff_size))
            self._subs.append(rospy.Subscriber(f"{prefix}camera_info", rospy.AnyMsg, self._on_camera_info_sub,
                                               callback_args=camera, queue_size=1, buff_size=buff_size))
        rospy.on_shutdown(self._stopping.set)
        # reset=True: a bag loop moves ROS time backwards, which would otherwise kill the timer thread.
        self._timer = rospy.Timer(rospy.Duration(poll_period), self._on_timer, reset=True)
        p = pipeline.input.params
        rospy.loginfo("%s: %d cameras (%s), slop %s, timeout %.3f s, extrinsics from %s, intrinsics from "
                      "camera_info%s", name, len(pipeline.camera_names), ", ".join(pipeline.camera_names), p.slop,
                      p.timeout, "tf" if use_tf else "the ring file",
                      " (ring file as fallback)" if p.camera_info_fallback else "")

    # --- calls into the pipeline ------------------------------------------------------------

    @staticmethod
    def now() -> float:
        """The pipeline's clock: ROS time (simulated time under use_sim_time), s."""
        return rospy.get_time()

    def call(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)`` under the pipeline lock, after every call that arrived before it; an
        argument :data:`NOW` is replaced by the node's clock at arrival. A non-empty result is
        delivered in order. Returns the result; raises what ``fn`` raised, in the caller's thread."""
        with self._inbox_lock:
            # ``now`` read and the call queued together, so the inbox is in the order of the clock.
            item = _Call(fn, tuple([self.now() if a is NOW else a for a in args]))
            self._inbox.append(item)
        inbox, queue = self._inbox, self._queue
        with self.lock:
            # Whoever holds the lock runs every call queued so far, so ours has run when we get it.
            # Only the lock's holder pops; others append under the inbox lock (deque's append and
            # popleft are atomic), so the inbox lock is not needed here.
            while inbox:
                # Counted before it leaves the inbox: a call is always either waiting there or in
                # _runs (what _on_timer's lock-free test of "nothing ran since the last poll" reads).
                self._runs += 1
                c = inbox.popleft()
                try:
                    c.out = c.fn(*c.args)
                except Exception as exc:  # noqa: BLE001 - handed to the caller's thread below
                    c.error = exc
                    continue
                if c.out:
                    queue.append(c.out)
        if queue:
            # (Empty: nothing to deliver from our calls, and an output queued after this check is
            # delivered by the thread that queued it, which drains after it released the lock.)
            self._drain()
        if item.error is not None:
            raise item.error
        return item.out

    def every(self, period: float, fn: Callable[[], None]) -> None:
        """Call ``fn()`` about every ``period`` s of ROS time from the poll timer's thread (within
        one poll period; at once again when the clock went back), outside the pipeline lock."""
        self._periodic.append([float(period), fn, self.now()])

    def silent_cameras(self, silence: float) -> List[str]:
        """Cameras from which no fiducial_vertices message arrived for ``silence`` s (or ever), and
        none is being handled.

        rospy hands a topic's messages to its callback one at a time: while the pipeline is busy (a
        map preview, a save) every camera's callback waits for the lock and no arrival can be
        stamped; against the clock alone all eight looked silent while frames kept being added. A
        camera whose message is waiting is not silent.
        """
        now = self.now()
        handling = set(self._handling)
        return [c for c in self.pipeline.camera_names
                if c not in handling and now - self.last_arrival.get(c, -np.inf) > silence]

    def input_age(self) -> float:
        """Seconds since any camera's last fiducial_vertices message (inf before the first; 0 while one
        is being handled)."""
        if self._handling:
            return 0.0
        return self.now() - max(self.last_arrival.values()) if self.last_arrival else float("inf")

    def shutdown(self) -> None:
        """Stop the subscriptions and the timer."""
        self._stopping.set()
        self._timer.shutdown()
        for s in self._subs:
            s.unregister()

    # --- callbacks --------------------------------------------------------------------------

    def _on_camera_info_sub(self, msg: rospy.AnyMsg, camera: str) -> None:
        """The camera_info subscription's callback, on the connection's own thread: the message is
        handled (:meth:`_on_camera_info_raw`); after a repeat of the camera_info in force the
        thread waits ``info_check_period`` s before rospy reads that connection again (module
        docstring), or until shutdown."""
        if self._on_camera_info_raw(msg, camera) and self.info_check_period > 0.0:
            self._stopping.wait(self.info_check_period)

    def _on_camera_info_raw(self, msg: rospy.AnyMsg, camera: str) -> bool:
        """camera_info as bytes: dropped at once when all but the header's seq and stamp (its first
        12 bytes) are those of the last message applied; else type-checked, deserialised and
        handed to :meth:`_on_camera_info`. True for such a repeat (nothing new), else False."""
        body = camera_info_body(msg._buff)
        if self._info_bytes.get(camera) == body:
            return True
        if not self._of_type(msg, CameraInfo, camera, "camera_info"):
            return False
        try:
            info = camera_info_from_bytes(msg._buff)
        except MeasurementError as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"{self._name}: {camera}: {exc}")
            return False
        if self._on_camera_info(info, camera):
            self._info_bytes[camera] = body
        return False

    def _on_camera_info(self, msg: CameraInfo, camera: str) -> bool:
        """Hand a changed camera_info to the pipeline; True when the camera's intrinsics in force
        are this message's (applied now or before), False for an unusable one."""
        key = (tuple(msg.K), tuple(msg.D), msg.distortion_model, msg.width, msg.height)
        if self._info_keys.get(camera) == key:
            return True
        try:
            model = camera_info_to_model(msg, name=camera)
        except ArucoRingError as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"{self._name}: {camera}: unusable camera_info: {exc}")
            return False
        self.call(self.pipeline.on_camera_info, camera, model)
        self._info_keys[camera] = key
        wall = time.monotonic()
        if wall - self._info_logged.get(camera, -np.inf) >= WARN_PERIOD:  # a flip-flopping publisher: not every one
            self._info_logged[camera] = wall
            rospy.loginfo("%s: %s intrinsics from camera_info: fx %.3f fy %.3f cx %.3f cy %.3f, %dx%d, %s",
                          self._name, camera, msg.K[0], msg.K[4], msg.K[2], msg.K[5], msg.width, msg.height,
                          msg.distortion_model or "no distortion model")
        return True

    def _look_up_extrinsics(self, camera: str, frame_id: str) -> None:
        """Look T_base_cam up in tf once per (camera, frame_id) and hand it to the pipeline."""
        frame_id = (frame_id or self._ring[camera].frame_id).lstrip("/")
        if self._tf_frames.get(camera) == frame_id:
            return
        base = self._ring.base_frame
        try:
            msg = self.tf_buffer.lookup_transform(base, frame_id, rospy.Time(0))
            T = msg_to_transform(msg.transform, f"tf {base} -> {frame_id}")
        except (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException) as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"{self._name}: {camera}: no tf {base} -> {frame_id} yet "
                                                f"({type(exc).__name__})")
            return
        except ArucoRingError as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"{self._name}: {camera}: bad tf: {exc}")
            return
        self.call(self.pipeline.on_extrinsics, camera, T)
        self._tf_frames[camera] = frame_id
        drift = np.linalg.norm(T[:3, 3] - self._ring[camera].T_base_cam[:3, 3])
        rospy.loginfo("%s: %s extrinsics from tf %s -> %s (%.1f mm from the ring file)", self._name, camera, base,
                      frame_id, 1000.0 * drift)

    def _of_type(self, msg: rospy.AnyMsg, cls, camera: str, topic: str) -> bool:
        """Whether the bytes ``msg`` on ``camera``'s ``topic`` are a ``cls`` (the publisher's md5sum);
        else warned about (throttled, naming the publisher and its type) and False."""
        wrong = type_mismatch(msg, cls)
        if wrong is None:
            return True
        rospy.logwarn_throttle(WARN_PERIOD, f"{self._name}: {camera}: {topic} {wrong}: ignored")
        return False

    def _on_fiducials_raw(self, msg: rospy.AnyMsg, camera: str) -> None:
        """fiducial_vertices as bytes (what the subscription hands over): type-checked, read, handled
        as :meth:`_on_fiducials`; a message cut short is warned about (throttled) and dropped."""
        if not self._of_type(msg, FiducialArray, camera, "fiducial_vertices"):
            return
        try:
            stamp, frame_id, observations = fiducial_array_bytes_to_observations(
                msg._buff, limit=self.pipeline.input.params.max_detections + 1)
        except ArucoRingError as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"{self._name}: {camera}: unreadable fiducial_vertices "
                                                f"({len(msg._buff)} bytes): {exc}")
            return
        self._handle_detections(camera, stamp, frame_id, observations)

    def _on_fiducials(self, msg: FiducialArray, camera: str) -> None:
        """A deserialised fiducial_vertices message (tests, tools): as :meth:`_on_fiducials_raw`."""
        self._handle_detections(camera, msg.header.stamp, msg.header.frame_id, msg)

    def _handle_detections(self, camera: str, stamp: Any, frame_id: str, observations: Any) -> None:
        """``stamp``: s, or the message's header stamp; ``observations``: a list, or the FiducialArray
        to convert (after the arrival is noted, as for the bytes)."""
        self.last_arrival[camera] = self.now()
        self._handling.add(camera)
        try:
            if self.use_tf:
                self._look_up_extrinsics(camera, frame_id)
            if isinstance(observations, FiducialArray):
                observations = fiducial_array_to_observations(observations,
                                                              limit=self.pipeline.input.params.max_detections + 1)
            if not isinstance(stamp, float):
                stamp = stamp_to_sec(stamp)
            self.call(self.pipeline.on_detections, camera, stamp, observations, NOW)
        except ArucoRingError as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"{self._name}: {camera}: {exc}")
        finally:
            self._handling.discard(camera)

    def _poll(self, now: float) -> Any:
        """``pipeline.poll(now)``, unless the last poll ran at this same ``now`` and no other call ran
        since (under the pipeline lock): it would find the same state at the same clock, so nothing
        new (its ring frames, its prediction and its warnings went out then). Under ``use_sim_time``
        the 20 Hz timer polls twice at each 10 Hz /clock step, the second time for nothing."""
        if self._polled == (now, self._runs - 1):
            return None
        self._polled = (now, self._runs)
        return self.pipeline.poll(now)

    def _idle_since_poll(self) -> bool:
        """Whether the last poll ran at the clock's present value and no pipeline call ran or waits
        since: a poll now would be skipped by :meth:`_poll`. Read without the lock, in this order
        (the inbox, then the count of calls run, then the last poll): a call that is neither in the
        inbox nor counted has not arrived yet, so a poll skipped here stands for one that came just
        before it."""
        if self._inbox:
            return False
        runs = self._runs
        polled = self._polled
        return polled is not None and polled[1] == runs and polled[0] == self.now()

    def _on_timer(self, _event) -> None:
        # Under use_sim_time the 20 Hz timer fires twice per 10 Hz /clock step: the second firing
        # would queue a call and take both locks only for _poll to skip it.
        if not self._idle_since_poll():
            try:
                self.call(self._poll, NOW)
            except ArucoRingError as exc:
                rospy.logwarn_throttle(WARN_PERIOD, f"{self._name}: {exc}")
        if self._periodic:
            now = self.now()
            for task in self._periodic:
                period, fn, last = task
                if now - last >= period or now < last:
                    task[2] = now
                    try:
                        fn()
                    except Exception as exc:  # noqa: BLE001 - the poll timer must outlive a task's bug
                        rospy.logerr_throttle(WARN_PERIOD, f"{self._name}: {getattr(fn, '__name__', fn)}: "
                                                           f"{type(exc).__name__}: {exc}")

    def _drain(self) -> None:
        # Outputs were queued in call order under the lock; whichever thread drains delivers them in
        # that order, one at a time.
        with self._deliver_lock:
            while self._queue:
                out = self._queue.popleft()
                try:
                    self._deliver_fn(out)
                except ArucoRingError as exc:
                    rospy.logwarn_throttle(WARN_PERIOD, f"{self._name}: output skipped: {exc}")
