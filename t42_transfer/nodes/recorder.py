"""Recorder node: the hand topics, as received, into rosbag2 MCAP bags, begun and ended at step boundaries.

Wiring (relative names: remap them with ``--ros-args -r``, or run under a namespace):

* the hand topics of ``params.topics`` (default ``hand/object_pose``, ``hand/joint_states``, ``hand/applied_action``;
  :data:`RECORDABLE` knows their types): subscribed raw with a ``params.queue_depth`` deep RELIABLE queue; each
  message's CDR bytes are written UNCHANGED, logged at its receive time (the node's ROS time), under the topic's
  fully resolved name (``/left/hand/object_pose`` under namespace ``/left``, or the name it is remapped to);
* the typed events of ``params.topics`` (default both: ``t42/plan_result`` as t42_interfaces/msg/PlanResult,
  ``t42/model_updated`` as ModelUpdated; :data:`EVENT_TOPICS`): subscribed raw, VOLATILE (the events as they
  happen), written as ``hand/status`` is, their bytes unchanged, with their full ``ros2msg`` definitions in the
  MCAP schema (:mod:`msg_adapters.interfaces`), so rosbags, mcap-ros2-support and Foxglove decode them without
  this package; ``read_bag`` ignores them (they are no steps).  Leave them out of ``topics`` to record none;
* ``~/start``, ``~/stop``, ``~/split`` (std_srvs/srv/Trigger): private names, as ``ros2 bag record``'s own services
  (``~/split_bagfile``...), so they are ``/recorder/start`` for the default node name and follow a renamed node
  (``__node:=rec_left`` -> ``/rec_left/start``) or a namespace (``/left/recorder/start``). Start opens a bag, stop
  closes it, split closes it and opens the next; each answers ``success`` and a message naming the bag;
* ``~/pause``, ``~/resume`` (std_srvs/srv/Trigger): pause drops the messages of the steps after the one in
  progress (counted in ``paused_dropped``; statuses too, so none splits), the bag stays open; resume records
  again into the same bag from the first step after the newest stamp received (a whole step).  Pausing when
  not recording or already paused, or resuming when not paused, answers ``success=False`` with why; stop ends
  a pause.  The steps dropped leave a gap in the episode (two episodes to a reader when it is over 1 s);
* ``recorder/bag_closed`` (t42_interfaces/msg/BagClosed, :data:`~msg_adapters.names.EVENTS` QoS: a late joiner gets
  the recent ones): one per bag closed and final (``metadata.yaml`` written), published after the bag was read back
  with ``read_bag`` (its ``episodes`` are the reader's count, 0 for a bag of no whole episode), so the bag is readable
  when the event arrives.  ``messages``, ``start``/``end`` (log times of its first and last message), ``reason``:
  ``stop``, ``split``, the status word that split it in episode mode (``reset``, ``dropped``...), ``write_failed`` (a
  full disk; only if the bag could still be finalised), ``shutdown``, ``snapshot`` or ``clock_restart``.  Relative,
  as rosbag2's ``events/write_split``;
* ``hand/status`` (std_msgs/msg/String): always recorded, written into the open bag as it comes (a driver's ``late``
  word there tells a reader that a step came late and none is missing); in ``mode="episode"`` a status whose first
  word is in ``params.split_on`` also splits the bag, so each bag holds one episode (see "Steps" for where).  Statuses
  and events go only into a bag that holds a step; a status naming a step that comes before the bag's first step
  is written (a ``late`` second step) goes in after it (:mod:`~t42_transfer.nodes.recorder_loose`);
* ``~/snapshot`` (std_srvs/srv/Trigger), snapshot mode (``snapshot_s`` > 0, rosbag2's ``--snapshot-mode``): the last
  ``snapshot_s`` seconds' steps, kept in memory, go to a bag in ``out_dir/snapshots`` (``recorder_snapshot``).

Steps.  A control step is the state (object pose and joint states) and the action applied from it, all with ONE header
stamp (the mock driver's and the bag convention of :mod:`t42_transfer.data.bag`).  Each topic has its own queue, so
the messages of a step arrive in any order and interleaved with the next step's; a bag begun or ended "now" could hold
an action without its state (a transfer refuses such a bag).  So messages are grouped by stamp (:class:`StepBuffer`)
and whole steps are written, in stamp order, once complete: every recorded topic delivered its message for the stamp
or a later one, or ``params.step_hold_s`` passed as :mod:`t42_transfer.data.bag.steps` says (an episode's final state
waits for an action that never comes; a step lacking part of its state waits up to ``HOLD_CAP`` times that: a driver
stalled between its messages is silent too).  A message that comes after its step was written joins the step in its
bag while that bag is open and the step lacks the topic (a reader aligns a bag's messages by stamp, not by order); one
for a step in a closed bag, or a duplicate, is dropped with a warning.  Bag changes happen between steps:

* start, stop, split: after the step in progress (the newest stamp received): the bag opens, closes, or closes and the
  next opens at once when no step is in progress, else as soon as that step is complete (the answer says which); the
  step in progress belongs to the time before the request;
* episode mode: a split word splits after the step in progress, and an end status (``dropped``, ``lost_contact``,
  ``overload``) after the steps stamped up to its receive time too (the final state, stamped before it, may arrive
  after it: it stays in its episode; this assumes the driver stamps with the recorder's clock, as on one machine or
  with ``use_sim_time`` on both).  Only a bag holding messages is split, so the ``reset`` that follows an episode end
  (or one published on start) opens no empty bag;
* stamps restarting over a second behind those written (a respawned sim-time driver, whose first steps may come before
  its first ``/clock``): the bag is split before the new clock's first step (reason ``clock_restart``), whose messages
  received on the old clock are logged at their stamps (:class:`~t42_transfer.data.bag.recording.LogTimes`), so both
  bags read.  Shutting down carries out no waiting start or split (it would make an empty bag).

A bag never begins with a step whose state was not received (an action alone, a pose alone: dropped with a warning),
and on close only steps holding their whole state are written.

Bags are written as :mod:`t42_transfer.data.bag` writes them (rosbags ``Writer(version=9)``, MCAP, ``ros_distro:
jazzy``, ``offered_qos_profiles=[RECORD_QOS]``, ``metadata.yaml`` on close, its custom data naming the topic each
hand topic went to: remapped ones read too) as ``<prefix>_<NNN>`` in ``out_dir``, ``NNN`` counting on from the
highest index there, past a name another writer takes meanwhile: no bag is overwritten.  A bag that does not open
is a write failure, as a full disk: ``~/start`` or free space resumes.

Nothing is held back longer than a step: every ``params.flush_period_s`` (steady time) the open chunk is closed and
the file flushed, so a recorder killed with SIGKILL leaves a bag whose MCAP is readable up to the last flush (``t42
bag repair`` then rewrites its summary and ``metadata.yaml``), and memory stays bounded by one chunk (rosbags also
closes a chunk at 1 MiB).  A bag file found gone then (``out_dir`` removed) is a write failure too, reported as
one, and a new bag opens at once where it can.

A message whose bytes do not decode as its topic's type is logged and not written (a bag stays readable); messages
logged at 0 ns (``use_sim_time`` with no ``/clock``) for ``NO_CLOCK_S`` are warned of.  No callback or service handler
raises; failures are logged (services answer ``success=False``).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from functools import partial
from pathlib import Path
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger
from t42_interfaces.msg import BagClosed

from msg_adapters import RCLPY, diagnostic_array, names, rclpy_class, stamp_to_ns
from msg_adapters.diagnostics import PERIOD_S as DIAGNOSTICS_PERIOD_S
from msg_adapters.events import SHUTDOWN
from t42_transfer.data.bag.recording import CLOCK_RESTART, Pause, recorded_hand_topics
from t42_transfer.data.bag.steps import Step, StepBuffer, WrittenSteps
from t42_transfer.nodes.recorder_bags import BagSeries
from t42_transfer.nodes.recorder_changes import BagChanges, Change
from t42_transfer.nodes.recorder_loose import LooseMessages
from t42_transfer.nodes.recorder_params import (
    EVENT_TOPICS,
    RECORDABLE,
    Announcer,
    RecorderParams,
    latched_offers,
)
from t42_transfer.nodes.recorder_snapshot import Snapshots
from t42_transfer.ros.dirs import claim, in_namespace
from t42_transfer.ros.logs import ThrottledLog
from t42_transfer.ros.node_lifetime import destroyed_if_init_fails
from t42_transfer.ros.params import LiveParams
from t42_transfer.ros.qos import profile, recording

STATE_TOPICS = (names.OBJECT_POSE, names.JOINT_STATES)
"""The messages that make a step's state; the rest of a step (``hand/applied_action``) is applied from it."""

NO_CLOCK_S = 2.0  # messages logged at 0 ns (use_sim_time with no /clock) this long are warned of, throttled

STATUS_NAME = "t42_transfer: recorder"
"""The recorder's status name on ``diagnostics``: at once on a write failure and on the resume, and each
:data:`~msg_adapters.diagnostics.PERIOD_S` (ERROR while writing fails; OK recording, paused or idle)."""


# --------------------------------------------------------------------------- the node
class Recorder(LooseMessages, Node):
    """Records the hand topics into bags at step boundaries; see the module docstring."""

    params_class = RecorderParams  # the one its LiveParams declares; t42 node NAME --help lists it

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("recorder", **node_kwargs)
        self._params = LiveParams(self, self.params_class, self._on_params)
        p = self.params
        self.log = self.get_logger()
        self.per_message = ThrottledLog(self.log)
        """Warnings about single messages: a flood gives a line a second, with a count."""
        self.out_dir = in_namespace(p.out_dir, self.get_namespace()).absolute()
        """Where the bags go, absolute (a listener elsewhere reads the announced paths): ``recordings/left``."""
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ValueError(f"{self.get_fully_qualified_name()}: out_dir {self.out_dir}: {err.strerror}") from None
        try:
            claim(self.out_dir, self.get_namespace(), p.share_dirs)
        except ValueError as err:
            raise ValueError(f"{self.get_fully_qualified_name()}: out_dir {err}") from None
        self.received = 0
        """Messages received on the recorded topics and handled (counted when their callback ends)."""
        self.dropped = 0
        """Messages not written (undecodable bytes, too late for their step's bag, orphans, a failed write)."""
        self.late_kept = 0
        """Messages that came after their step was written and joined it in its bag."""
        self._written = WrittenSteps()
        self._diagnostics = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 10)
        self._changes = BagChanges()
        self._lock = threading.RLock()
        self._closed = False
        self._no_clock_since = 0.0  # steady time of the first message logged at 0 ns (no /clock yet); 0.0: none
        self._first_stamp: int | None = None
        """The oldest stamp received: a status's border before it (history, heard on joining) is no border."""
        self._pause = Pause()
        self._held: deque[tuple[str, int, bytes, str, int]] = deque(maxlen=names.EVENTS.depth)
        """Statuses that named a step and came while the bag held none: (topic, log time, bytes, type, step)."""
        self._announcer = Announcer(self.create_publisher(BagClosed, names.BAG_CLOSED, profile(names.EVENTS)),
                                    self.log)

        self._types = self._subscribe(p)
        """Resolved topic -> type, of the topics grouped into steps."""
        self._state_topics = {self.resolve_topic_name(t) for t in STATE_TOPICS if t in p.topics}
        offers = latched_offers(self.resolve_topic_name, p.topics)
        custom = recorded_hand_topics(self.resolve_topic_name)
        self._series = BagSeries(p, self.out_dir, self._types, offers, custom, self._announcer, self.log, self._report)
        """The continuous bags: the open one, those closed, a write failure."""
        self.snapshots = Snapshots(p, self.out_dir, self._types, self._state_topics, self._announcer, self.log,
                                   offers, custom)
        """Snapshot mode (``snapshot_s`` > 0): the last seconds in memory, written as a bag on a trigger."""
        self._buffer = StepBuffer(self._types, p.step_hold_s, self._status_lag_s(p), required=self._state_topics)
        self._status_topic = self.resolve_topic_name(names.HAND_STATUS)
        self.create_subscription(String, names.HAND_STATUS, self._on_status, profile(names.EVENT_READER), raw=True)
        for service, action in ((names.RECORDER_START, self.start), (names.RECORDER_STOP, self.stop),
                                (names.RECORDER_SPLIT, self.split), (names.RECORDER_PAUSE, self.pause),
                                (names.RECORDER_RESUME, self.resume), (names.RECORDER_SNAPSHOT, self.snapshot)):
            self.create_service(Trigger, service, partial(self._answer, action), qos_profile=profile(names.REQUESTS))
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._flush_timer = self.create_timer(p.flush_period_s, self.flush, clock=steady)
        self._hold_timer = self.create_timer(p.step_hold_s / 2, self._on_hold_timer, clock=steady)
        self._diagnostics_timer = self.create_timer(DIAGNOSTICS_PERIOD_S, self._report_state, clock=steady)
        if p.start_immediately:
            ok, message = self.start()
            if not ok:
                raise ValueError(f"{self.get_fully_qualified_name()}: could not start recording: {message}")

    def _subscribe(self, p: RecorderParams) -> dict[str, str]:
        """Subscribe to ``p.topics``: the events as they come, the rest into steps (whose resolved topic -> type
        this returns)."""
        qos, types = recording(p.queue_depth), {}
        for name in p.topics:
            msgtype, topic = RECORDABLE[name], self.resolve_topic_name(name)  # namespace and remapping applied
            if name in EVENT_TOPICS:  # as they come: VOLATILE, so any reliable publisher matches
                self.create_subscription(rclpy_class(msgtype), topic, partial(self._on_event, topic, msgtype),
                                         profile(names.EVENT_READER), raw=True)
                continue
            self.create_subscription(rclpy_class(msgtype), topic, partial(self._on_message, topic, msgtype), qos,
                                     raw=True)
            types[topic] = msgtype
        return types

    # ------------------------------------------------------------------ state
    @property
    def params(self) -> RecorderParams:
        return self._params.value

    @property
    def recording(self) -> bool:
        """Whether a bag is open now."""
        return self._series.bag is not None

    @property
    def current_bag(self) -> Path | None:
        """Path of the open bag, if any."""
        bag = self._series.bag
        return None if bag is None else bag.path

    @property
    def current_count(self) -> int:
        """Messages written to the open bag (0 when none is open)."""
        bag = self._series.bag
        return 0 if bag is None else bag.count

    @property
    def bags(self) -> list[Path]:
        """Every bag this recorder has closed, in order."""
        return self._series.closed

    @property
    def write_failure(self) -> str | None:
        """Why writing stopped (a full disk): steps are dropped, counted, until space returns or ~/start."""
        return self._series.failure

    @property
    def waiting_changes(self) -> int:
        """Requested bag changes waiting for the step in progress."""
        return len(self._changes)

    def start(self) -> tuple[bool, str]:
        """Open a new bag after the step in progress; (success, message)."""
        with self._lock:
            if self._changes.will_record and self.write_failure is not None:
                return self._series.resume(f"{names.RECORDER_START} called")
            if self._changes.will_record:
                bag = self._series.bag
                return False, f"already recording to {bag.path if bag is not None else 'a bag'}"
            return self._request("start", self._buffer.latest_stamp)

    def stop(self) -> tuple[bool, str]:
        """Close the open bag after the step in progress; (success, message)."""
        with self._lock:
            if not self._changes.will_record:
                return False, "not recording"
            if self.paused:
                self.resume()
            return self._request("stop", self._buffer.latest_stamp)

    def split(self) -> tuple[bool, str]:
        """Close the open bag after the step in progress and open the next; (success, message)."""
        with self._lock:
            if not self._changes.will_record:
                return False, "not recording; call start"
            if self.write_failure is not None:
                return False, f"not writing, nothing to split: {self.write_failure}"
            return self._request("split", self._buffer.latest_stamp)

    @property
    def paused(self) -> bool:
        """Whether messages are being dropped until ~/resume."""
        return self._pause.paused

    @property
    def paused_dropped(self) -> int:
        """Messages dropped while paused (recorded topics and statuses), in all."""
        return self._pause.dropped

    def pause(self) -> tuple[bool, str]:
        """Drop the messages of the steps after the one in progress, the bag kept open; (success, message)."""
        with self._lock:
            if not self._changes.will_record:
                return False, "not recording: nothing to pause (call start)"
            return self._pause.pause(self.current_bag or "the next bag")

    def resume(self) -> tuple[bool, str]:
        """Record again, into the same bag, from the first step after the newest stamp received; (success,
        message)."""
        with self._lock:
            return self._pause.resume(self.current_bag or "no bag")

    def snapshot(self) -> tuple[bool, str]:
        """Write the steps of the last ``snapshot_s`` seconds as a bag, after the step in progress; (success,
        message)."""
        with self._lock:
            if self.snapshots.buffer is None:
                return self.snapshots.take(None)  # off: says so
            return self._request("snapshot", self._buffer.latest_stamp)

    def flush(self) -> None:
        """Write out what the open bag holds so far; failures are logged (it runs from a timer).  After a write
        failure, recording resumes here once there is room again."""
        with self._lock:
            self._series.flush(self._changes.will_record)

    def close(self) -> None:
        """Write the waiting steps that hold their whole state, carry out waiting changes, close the bag."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                whole = [s for s in self._buffer.drain() if self._state_topics <= s.topics]
                self._write_steps(whole)
                self._changes.shutting_down()
                self._carry_out(None)
                if self.recording:
                    self._series.close(SHUTDOWN)
            except Exception as err:  # close() never raises
                self.log.error(f"closing the recorder failed: {err!r}")
        self._announcer.close()

    # ------------------------------------------------------------------ bag changes
    def _request(self, kind: str, after: int | None, why: str = "", word: str = "") -> tuple[bool, str]:
        """Queue a bag change after the steps up to ``after``; carry out what can be; (success, the answer)."""
        change = self._changes.add(Change(kind, after, why, word))
        done = self._carry_out(self._buffer.oldest_pending)
        if kind in done:
            return done[kind]
        return True, f"{kind}: after the step in progress (stamp {change.after} ns) is complete"

    def _carry_out(self, next_stamp: int | None) -> dict[str, tuple[bool, str]]:
        """Carry out the changes due before the step stamped ``next_stamp`` (None: every change); what each did."""
        return {change.kind: self._change(change) for change in self._changes.due(next_stamp)}

    def _change(self, change: Change) -> tuple[bool, str]:
        """Carry out ``change``: (whether every close and open it took worked, what happened)."""
        if change.kind == "snapshot":
            return self.snapshots.take(change.after, change.word)
        series = self._series
        if change.kind == "start":
            return series.open()
        if change.kind == "stop":
            failure, series.failure = series.failure, None
            if series.bag is not None:
                return series.close(change.kind)
            return (True, "not recording") if failure is None else (True, f"stopped; writing had failed: {failure}")
        if series.bag is None:
            return (False, f"not writing: {series.failure}") if series.failure else (True, "not recording")
        if change.kind == "episode" and series.bag.count == 0:
            return True, f"{series.bag.path} is empty: not split"
        said = not change.why  # a change with a cause says both halves in one line, with the cause
        closed_ok, closed = series.close(change.word or change.kind, say=said)
        opened_ok, opened = series.open(say=said)
        message = f"{closed}; {opened}"
        if change.why:
            self.log.info(f"{change.why}: {message}")
        return closed_ok and opened_ok, message

    # ------------------------------------------------------------------ diagnostics
    def _report_state(self) -> None:
        """The periodic status: what a monitor that joined late needs (a write failure is still an ERROR)."""
        failure, bag, paused = self.write_failure, self._series.bag, self.paused
        if failure is not None:
            self._report("ERROR", failure)
        elif bag is not None:
            self._report("OK", f"{'paused' if paused else 'recording'} {bag.path} ({bag.count} messages)")
        else:
            self._report("OK", f"not recording (call {names.RECORDER_START})")

    def _report(self, level: str, message: str) -> None:
        counts = {"dropped": self.dropped, "late_kept": self.late_kept}
        self._diagnostics.publish(diagnostic_array(STATUS_NAME, level, message, counts,
                                                   self.get_clock().now().nanoseconds, kit=RCLPY))

    # ------------------------------------------------------------------ steps
    def _write_steps(self, steps: list[Step]) -> None:
        for step in steps:
            self._carry_out(step.stamp)
            self.snapshots.add_step(step)
            bag = self._series.bag
            if bag is None:
                if self.write_failure is not None:
                    self.dropped += len(step.messages)
                continue
            if bag.count == 0 and not self._state_topics <= step.topics:
                self.dropped += len(step.messages)
                self.per_message.warning(f"{bag.path} does not begin with the step stamped {step.stamp} ns: it lacks "
                                         f"{', '.join(sorted(self._state_topics - step.topics))} (received before the "
                                         "bag began, or lost)")
                continue
            try:
                first = bag.count == 0
                self._series.write_step(step)
                self._written.add(step, bag)
                if first:
                    self._write_held(step.stamp)
            except OSError as err:  # a full disk: stop writing, say so once
                self.dropped += len(step.messages)
                self._series.failed(bag.path, err)
            except Exception as err:
                self.dropped += len(step.messages)
                self.log.error(f"could not write the step stamped {step.stamp} ns to {bag.path}: {err!r}")

    def _on_message(self, topic: str, msgtype: str, data: bytes) -> None:
        try:
            log_ns = self.get_clock().now().nanoseconds
            if log_ns == 0:  # said once it lasts: a driver's first steps may come before its first /clock
                self._no_clock_since = self._no_clock_since or time.monotonic()
                if time.monotonic() - self._no_clock_since > NO_CLOCK_S:
                    self.per_message.warning(f"use_sim_time is true and no /clock has come in {NO_CLOCK_S:g} s: "
                                             "messages are logged at 0 ns")
            if (msg := self._decoded(topic, msgtype, data)) is None:
                return
            stamp = stamp_to_ns(msg.header.stamp)
            with self._lock:
                if self._closed:
                    return
                if self._pause.drops(stamp):
                    return
                if self._first_stamp is None or stamp < self._first_stamp:
                    self._first_stamp = stamp
                restarts = self._buffer.restarts
                released, late = self._buffer.add(topic, stamp, log_ns, bytes(data), time.monotonic())
                if self._buffer.restarts != restarts:
                    released = self._clock_restarted(stamp, log_ns, released)
                if late:
                    self._write_late(topic, stamp, log_ns, bytes(data))
                self._write_steps(released)
                self._carry_out(self._buffer.oldest_pending)
        except Exception as err:  # never raise from a callback
            self.dropped += 1
            self.log.error(f"could not record a message on {topic}: {err!r}")
        finally:
            self.received += 1

    def _clock_restarted(self, stamp: int, log_ns: int, released: list[Step]) -> list[Step]:
        """The stamps restarted behind those written (a respawned sim-time driver), at ``stamp``: the old clock's
        steps and waiting changes go into the open bag, which closes; the new clock's steps, of which those in
        ``released`` are returned, go into the next (a reader needs a bag's stamps to increase)."""
        self._write_steps([s for s in released if s.stamp != stamp])
        self._carry_out(None)
        self._pause.restart(stamp)
        if self.current_count:
            self._change(Change("split", None, f"the stamps restarted at {stamp} ns", CLOCK_RESTART))
        self._series.restart(log_ns, stamp)
        return [s for s in released if s.stamp == stamp]

    def _on_hold_timer(self) -> None:
        with self._lock:
            if self._closed:
                return
            try:
                self._write_steps(self._buffer.release(time.monotonic()))
                self._carry_out(self._buffer.oldest_pending)
            except Exception as err:
                self.log.error(f"could not write waiting steps: {err!r}")

    # ------------------------------------------------------------------ services, params
    def _answer(self, action: Any, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            ok, message = action()
        except Exception as err:  # a service handler must answer, not raise
            self.log.error(f"recorder service failed: {err!r}")
            ok, message = False, f"failed: {type(err).__name__}: {err}"
        response.success, response.message = ok, message
        return response

    @staticmethod
    def _status_lag_s(p: RecorderParams) -> float:
        """In episode mode a whole step waits half ``step_hold_s`` for a status that splits before it."""
        return p.step_hold_s / 2 if p.mode == "episode" else 0.0

    def _on_params(self, old: RecorderParams, new: RecorderParams) -> None:
        # a new period counts from now (rcl keeps the old next call time otherwise)
        if new.flush_period_s != old.flush_period_s:
            self._flush_timer.timer_period_ns = round(new.flush_period_s * 1e9)
            self._flush_timer.reset()
        if new.step_hold_s != old.step_hold_s:
            with self._lock:
                self._buffer.hold_s = new.step_hold_s
        with self._lock:
            self._series.configure(new)
            self.snapshots.configure(new)
            self._buffer.min_age_s = self._status_lag_s(new)
            self._hold_timer.timer_period_ns = round(new.step_hold_s / 2 * 1e9)
            self._hold_timer.reset()
