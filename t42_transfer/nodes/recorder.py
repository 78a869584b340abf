"""Recorder node: the hand topics, as received, into rosbag2 MCAP bags.

Wiring (defaults; every name is a :class:`RecorderParams` field):

* the hand topics of :data:`msg_adapters.HAND_TOPICS` (``params.topics``):
  subscribed raw; each message's CDR bytes are written UNCHANGED, logged at the
  receive time ``transport.now_ns()``;
* ``/recorder/start``, ``/recorder/stop``, ``/recorder/split`` (std_srvs/srv/Trigger):
  start opens a bag when none is open, stop closes the open one, split closes it
  and opens the next; each answers ``success`` and a message naming the bag;
* ``/hand/status`` (std_msgs/msg/String, only in ``mode="episode"``): a status whose
  first word is one of ``params.split_on`` (``reset``, ``dropped``,
  ``lost_contact``, ``overload``) splits the bag, so each bag holds one episode.
  Topics are not ordered against each other (one queue per subscription), so the
  split is placed in time, not in arrival order: the bag splits before the first
  recorded message whose header stamp (receive time for messages without a
  header) is later than ``T``, where ``T`` is the receive time of an end status
  (``dropped``, ``lost_contact``, ``overload``: the final state, stamped before
  it, stays in its episode) and, for any other split word such as ``reset``, the
  latest stamp recorded so far (what follows belongs to the new episode).  A split
  only happens when the open bag holds messages, so the ``reset`` that follows an
  episode end (or one published on start) opens no empty bag.

Bags are written as :mod:`t42_transfer.data.bag_io` writes them (rosbags
``Writer(version=9)``, MCAP, ``offered_qos_profiles=[RECORD_QOS]``, one connection
per recorded topic, ``metadata.yaml`` on close) and are named ``<prefix>_<NNN>``
in ``out_dir``: ``NNN`` counts on from the highest index already there, so no bag
is ever overwritten.  :func:`t42_transfer.data.bag_io.read_bag` reads them.

Nothing is held back: every ``params.flush_period_s`` (transport timer) the open
chunk is closed and the file flushed, so a recorder killed with SIGKILL leaves a
bag whose MCAP is readable up to the last flush (``t42 bag repair`` then rewrites
its summary and ``metadata.yaml``), and memory stays bounded by one chunk (rosbags
also closes a chunk at 1 MiB).  Each topic is subscribed RELIABLE with a
``params.queue_depth`` deep KEEP_LAST queue, so a spin loop stalled by a flush or
the CPU scheduler loses nothing at kHz rates (``bench/bench_recorder.py``: none
lost at 1 and 5 kHz; ROS's default depth of 10 lost 0.5% at 5 kHz).

A message whose bytes do not decode as its topic's type is logged with
``transport.logger.warning`` and not written (a bag stays readable).  No callback
or service handler raises; failures are logged (services answer ``success=False``).
"""

from __future__ import annotations

import re
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from rosbags.rosbag2 import StoragePlugin, Writer

from msg_adapters import HAND_TOPICS
from t42_transfer.data.bag_io import RECORD_QOS
from t42_transfer.ros import qos
from t42_transfer.ros.naming import typestore_for, validate_name
from t42_transfer.ros.transport import Transport, deserialize, service_classes

STRING = "std_msgs/msg/String"
TRIGGER = "std_srvs/srv/Trigger"

START_SERVICE = "/recorder/start"
STOP_SERVICE = "/recorder/stop"
SPLIT_SERVICE = "/recorder/split"
STATUS_TOPIC = "/hand/status"

MODES = ("recording", "episode")
SPLIT_EVENTS = ("reset", "dropped", "lost_contact", "overload")
"""First words of a ``/hand/status`` message that split (``status_message`` of the mock driver)."""
END_EVENTS = ("dropped", "lost_contact", "overload")
"""Split words sent after an episode's final state (the others precede the next episode's first)."""

_PREFIX = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


@dataclass(frozen=True)
class RecorderParams:
    """Parameters of :class:`Recorder` (the node's ROS parameters)."""

    out_dir: str | Path
    """Directory the bags are created in (made if missing)."""
    mode: str = "recording"
    """``"recording"``: bags change only on the services; ``"episode"``: also split on status events."""
    prefix: str | None = None
    """Bag name prefix; ``None`` uses the mode (``episode_000``, ``recording_000``...)."""
    start_immediately: bool = True
    """Open the first bag on construction (else wait for ``/recorder/start``)."""
    topics: Mapping[str, str] = field(default_factory=lambda: dict(HAND_TOPICS))
    """Recorded topics and their message types."""
    status_topic: str = STATUS_TOPIC
    split_on: tuple[str, ...] = SPLIT_EVENTS
    """Status words that split the bag in ``"episode"`` mode."""
    start_service: str = START_SERVICE
    stop_service: str = STOP_SERVICE
    split_service: str = SPLIT_SERVICE
    flush_period_s: float = 1.0
    """At most this much recording is lost when the process dies (the open chunk is written out this often)."""
    queue_depth: int = 1000
    """KEEP_LAST depth of each recorded topic's subscription: messages it can hold while the node is busy."""

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if not _PREFIX.match(self.bag_prefix):
            raise ValueError(f"prefix must be a plain file name part ([A-Za-z0-9_.-]), got {self.prefix!r}")
        topics = dict(self.topics)
        if not topics:
            raise ValueError("topics must name at least one topic")
        for topic, msgtype in topics.items():
            validate_name(topic)
            typestore_for(msgtype)  # KeyError for an unknown type
        object.__setattr__(self, "topics", topics)
        object.__setattr__(self, "split_on", tuple(self.split_on))
        if not self.flush_period_s > 0:
            raise ValueError(f"flush_period_s must be positive, got {self.flush_period_s!r}")
        if not isinstance(self.queue_depth, int) or self.queue_depth < 1:
            raise ValueError(f"queue_depth must be an int >= 1, got {self.queue_depth!r}")
        validate_name(self.status_topic)
        for name in (self.start_service, self.stop_service, self.split_service):
            validate_name(name, "service")

    @property
    def bag_prefix(self) -> str:
        return self.prefix if self.prefix is not None else self.mode


def next_bag_path(out_dir: str | Path, prefix: str) -> Path:
    """``out_dir/<prefix>_<NNN>`` with ``NNN`` one past the highest index there (000 when none)."""
    pattern = re.compile(rf"^{re.escape(prefix)}_(\d{{3,}})$")
    directory = Path(out_dir)
    taken = [int(m.group(1)) for p in directory.iterdir() if (m := pattern.match(p.name))] \
        if directory.is_dir() else []
    return directory / f"{prefix}_{max(taken, default=-1) + 1:03d}"


def _stamp_ns(msg: Any, default: int) -> int:
    """Header stamp of ``msg`` in ns, or ``default`` for a message without a header."""
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return default
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


class _Bag:
    """One open bag: its writer, connections by topic and message count."""

    def __init__(self, path: Path, topics: Mapping[str, str]) -> None:
        self.path = path
        self.writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        try:
            self.connections = {
                topic: self.writer.add_connection(
                    topic, msgtype, typestore=typestore_for(msgtype), offered_qos_profiles=[RECORD_QOS]
                )
                for topic, msgtype in topics.items()
            }
        except Exception:
            self.writer.abort()
            raise
        self.count = 0
        self.last_stamp_ns = -1
        """Latest header stamp written."""

    def write(self, topic: str, log_ns: int, data: bytes, stamp_ns: int) -> None:
        self.writer.write(self.connections[topic], log_ns, data)
        self.count += 1
        self.last_stamp_ns = max(self.last_stamp_ns, stamp_ns)

    def flush(self) -> None:
        """Write the open chunk and flush the file (no fsync: SIGKILL keeps the page cache).

        rosbags' MCAP writer (0.11.9) has no public flush; its storage closes a
        chunk only at 1 MiB, so this closes it through the storage object.
        """
        storage = self.writer.storage
        if storage is None:
            return
        if storage.chunk.msgs:
            storage.close_chunk()
        storage.bio.flush()

    def close(self) -> None:
        self.writer.close()


class Recorder:
    """Records the hand topics into bags; see the module docstring for behaviour."""

    def __init__(self, transport: Transport, params: RecorderParams) -> None:
        self.transport = transport
        self.params = params
        self.log = transport.logger
        self.bags: list[Path] = []
        """Every bag this recorder has closed, in order."""
        self.dropped = 0
        """Messages not written (undecodable bytes or a failed write)."""
        self._bag: _Bag | None = None
        self._split_after_ns: int | None = None
        """Episode mode: split before the first message stamped after this (a status's receive time)."""
        self._lock = threading.RLock()
        _, self._Response = service_classes(TRIGGER)
        Path(params.out_dir).mkdir(parents=True, exist_ok=True)
        if params.mode == "episode":  # first, so a spin sees a status before messages queued with it
            transport.subscribe(params.status_topic, STRING, qos.DEFAULT, self._on_status, raw=True)
        record_qos = qos.QoSProfile(depth=params.queue_depth)
        for topic, msgtype in params.topics.items():
            transport.subscribe(topic, msgtype, record_qos,
                                lambda data, t=topic, m=msgtype: self._on_message(t, m, data), raw=True)
        transport.service(params.start_service, TRIGGER, lambda req: self._answer(self.start))
        transport.service(params.stop_service, TRIGGER, lambda req: self._answer(self.stop))
        transport.service(params.split_service, TRIGGER, lambda req: self._answer(self.split))
        transport.timer(params.flush_period_s, self.flush)
        if params.start_immediately:
            ok, message = self.start()
            if not ok:
                self.log.error("could not start recording: %s", message)

    # ------------------------------------------------------------------ state
    @property
    def recording(self) -> bool:
        return self._bag is not None

    @property
    def current_bag(self) -> Path | None:
        """Path of the open bag, if any."""
        bag = self._bag
        return None if bag is None else bag.path

    @property
    def current_count(self) -> int:
        """Messages written to the open bag (0 when none is open)."""
        bag = self._bag
        return 0 if bag is None else bag.count

    def start(self) -> tuple[bool, str]:
        """Open a new bag unless one is open; (success, message)."""
        with self._lock:
            if self._bag is not None:
                return False, f"already recording to {self._bag.path}"
            try:
                path = self._open()
            except Exception as err:
                self.log.exception("could not open a bag in %s", self.params.out_dir)
                return False, f"could not open a bag in {self.params.out_dir}: {err}"
            return True, f"recording to {path}"

    def stop(self) -> tuple[bool, str]:
        """Close the open bag; (success, message)."""
        with self._lock:
            if self._bag is None:
                return False, "not recording"
            path, count, error = self._close()
            if error:
                return False, f"closing {path} failed: {error}"
            return True, f"closed {path} ({count} messages)"

    def split(self) -> tuple[bool, str]:
        """Close the open bag and open the next; (success, message)."""
        with self._lock:
            if self._bag is None:
                return False, "not recording; call start"
            old, count, error = self._close()
            try:
                path = self._open()
            except Exception as err:
                self.log.exception("could not open a bag in %s", self.params.out_dir)
                return False, f"closed {old} ({count} messages) but could not open the next: {err}"
            if error:
                return False, f"closing {old} failed: {error}; recording to {path}"
            return True, f"closed {old} ({count} messages); recording to {path}"

    def flush(self) -> None:
        """Write out what the open bag holds so far; failures are logged (it runs from a timer)."""
        with self._lock:
            if self._bag is None:
                return
            try:
                self._bag.flush()
            except Exception:
                self.log.exception("flushing %s failed", self._bag.path)

    def close(self) -> None:
        """Close any open bag (the transport's owner closes the transport)."""
        with self._lock:
            if self._bag is not None:
                self._close()

    # ------------------------------------------------------------------ bags
    def _open(self) -> Path:
        self._split_after_ns = None
        bag = _Bag(next_bag_path(self.params.out_dir, self.params.bag_prefix), self.params.topics)
        self._bag = bag
        self.log.info("recording to %s", bag.path)
        return bag.path

    def _close(self) -> tuple[Path, int, str]:
        """Close the open bag: (path, messages, error text or "")."""
        bag, self._bag = self._bag, None
        self._split_after_ns = None
        assert bag is not None
        try:
            bag.close()
        except Exception as err:
            self.log.exception("closing %s failed", bag.path)
            return bag.path, bag.count, f"{type(err).__name__}: {err}"
        self.bags.append(bag.path)
        self.log.info("closed %s (%d messages)", bag.path, bag.count)
        return bag.path, bag.count, ""

    # ------------------------------------------------------------------ callbacks
    def _answer(self, action: Any) -> Any:
        try:
            ok, message = action()
        except Exception as err:  # a service handler must answer, not raise
            self.log.exception("recorder service failed")
            ok, message = False, f"failed: {type(err).__name__}: {err}"
        return self._Response(success=ok, message=message)

    def _on_message(self, topic: str, msgtype: str, data: Any) -> None:
        try:
            now = self.transport.now_ns()
            data = bytes(data)
            try:
                msg = deserialize(msgtype, data)
            except Exception as err:  # the decoder raises whatever it trips over
                self.dropped += 1
                self.log.warning("dropped a message on %s: its %d bytes are not a %s (%s: %s)",
                                 topic, len(data), msgtype, type(err).__name__, err)
                return
            with self._lock:
                if self._bag is None:
                    return
                stamp = _stamp_ns(msg, now)
                if self._split_after_ns is not None and stamp > self._split_after_ns:
                    self._split_after_ns = None
                    if self._bag.count:
                        ok, message = self.split()
                        (self.log.info if ok else self.log.error)("episode status: %s", message)
                        if self._bag is None:
                            self.dropped += 1
                            return
                self._bag.write(topic, now, data, stamp)
        except Exception:  # never raise from a callback
            self.dropped += 1
            self.log.exception("could not record a message on %s", topic)

    def _on_status(self, data: Any) -> None:
        try:
            try:
                text = deserialize(STRING, bytes(data)).data
            except Exception as err:
                self.log.warning("ignored a message on %s: not a %s (%s: %s)",
                                 self.params.status_topic, STRING, type(err).__name__, err)
                return
            words = str(text).split()
            event = words[0].rstrip(":") if words else ""
            if event not in self.params.split_on:
                return
            with self._lock:
                if self._bag is None or (self._bag.count == 0 and self._split_after_ns is None):
                    return
                if event in END_EVENTS:
                    self._split_after_ns = self.transport.now_ns()
                elif self._split_after_ns is None:
                    self._split_after_ns = self._bag.last_stamp_ns
                self.log.info("status %r: the bag splits before the next message stamped later", event)
        except Exception:  # never raise from a callback
            self.log.exception("could not handle a message on %s", self.params.status_topic)
