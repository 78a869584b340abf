"""``t42 view --bag BAG``: a recorded bag over the Foxglove WebSocket protocol, with play, pause, speed and seek.

Each bag topic is a channel (``cdr``, the definition the bag stores, ``ros2msg`` or ``ros2idl``, else the one this
machine knows);
messages go out as the bag holds them, at their log times (the server's time follows them), paced by a
:class:`~t42_transfer.data.bag.playback.Timeline`.  The server advertises the bag's time range and the PlaybackControl
capability: the Foxglove app's play/pause button, speed and seek bar drive it.  ``/view/markers`` is added, drawn as
the live view draws it from the bag's hand topics (and its goals and planned paths, when it holds them), one
array at each step's joint state.  Playback starts paused at the bag's first message; at the end it reports Ended
and waits (a seek or play starts it again).  No ROS graph: the bag is read with rosbags (rclpy only serialises the
markers).
"""

from __future__ import annotations

import signal
import threading
import time
import warnings
from pathlib import Path
from typing import Any

import foxglove
from foxglove.websocket import (
    Capability,
    PlaybackCommand,
    PlaybackControlRequest,
    PlaybackState,
    PlaybackStatus,
)
from rclpy.serialization import serialize_message
from rosbags.interfaces import MessageDefinitionFormat

import msg_adapters as ma
from msg_adapters import names
from msg_adapters.markers import MARKER_ARRAY, scene_markers
from msg_adapters.schemas import message_definition
from t42_transfer.data.bag.playback import Timeline, open_bag
from t42_transfer.hand.params import variant
from t42_transfer.view.bag_scene import SceneInputs, input_reader
from t42_transfer.view.scene import DEFAULT_TOLERANCE_MM, build_scene
from t42_transfer.view.server import start_server

_IDLE_S = 0.05
"""Longest wait between looks at the controls while paused or ahead of time."""
_TIME_EVERY_NS = 50_000_000
"""The server's time is broadcast at most every 50 ms of bag time (and at each seek)."""


def _schema(conn: Any) -> foxglove.Schema | None:
    """The definition the bag stores, in its own encoding (``ros2idl`` for a type defined in IDL), else the one
    this machine knows (``ros2msg``); None when neither has one (a client could not decode the topic)."""
    text = conn.msgdef.data if hasattr(conn.msgdef, "data") else conn.msgdef
    idl = getattr(conn.msgdef, "format", None) == MessageDefinitionFormat.IDL
    if not text:
        try:
            text, idl = message_definition(conn.msgtype), False
        except KeyError:
            return None
    return foxglove.Schema(name=conn.msgtype, encoding="ros2idl" if idl else "ros2msg", data=str(text).encode())


def _channels(connections: Any, context: foxglove.Context, bag: Path) -> dict[int, foxglove.Channel]:
    """A channel per connection a client can decode; the others are left out with a warning, as ``t42 bag play``
    leaves out a topic whose message package is missing."""
    channels = {}
    for conn in connections:
        schema = _schema(conn)
        if schema is None:
            warnings.warn(f"{bag}: not serving {conn.topic} ({conn.msgtype}): neither the bag nor this machine "
                          "defines its type", stacklevel=2)
            continue
        channels[conn.id] = foxglove.Channel(conn.topic, schema=schema, message_encoding="cdr", context=context)
    return channels


class BagServer:
    """Serves one bag until :meth:`close`; ``port`` 0 picks a free port (:attr:`port`)."""

    def __init__(self, bag: str | Path, host: str = "127.0.0.1", port: int = 8765, hand: str = "target",
                 tolerance_mm: float = DEFAULT_TOLERANCE_MM) -> None:
        path = Path(bag)
        self._reader = open_bag(path, "served")
        self.path = path
        self.start_ns, self.end_ns = self._reader.start_time, max(self._reader.end_time - 1, self._reader.start_time)
        self.sent = 0
        """Messages sent so far."""
        self._context = foxglove.Context()
        self._channels = _channels(self._reader.connections, self._context, path)
        self._hand, self._tolerance_mm = variant(hand), float(tolerance_mm)
        self._inputs = SceneInputs()
        markers_schema = foxglove.Schema(name=MARKER_ARRAY, encoding="ros2msg",
                                         data=message_definition(MARKER_ARRAY).encode())
        self._markers = foxglove.Channel("/" + names.VIEW_MARKERS, schema=markers_schema, message_encoding="cdr",
                                         context=self._context)
        self._cond = threading.Condition()
        self._timeline = Timeline(self.start_ns, 1.0, paused=True)
        self._seek_to: int | None = self.start_ns
        self._ended = False
        self._stop = False
        try:
            self.server = start_server(f"t42 view {path.name}", host, port, capabilities=[Capability.Time],
                                       server_listener=_Controls(self), context=self._context,
                                       playback_time_range=(self.start_ns, self.end_ns))
        except ValueError:
            self._reader.close()
            raise
        self.port = self.server.port
        self._thread = threading.Thread(target=self._play, name="bag_server", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ controls (the server's threads)
    def state(self, request_id: str | None = None, did_seek: bool = False) -> PlaybackState:
        with self._cond:
            status = (PlaybackStatus.Ended if self._ended else
                      PlaybackStatus.Paused if self._timeline.paused else PlaybackStatus.Playing)
            return PlaybackState(status=status, current_time=self._timeline.bag_now(),
                                 playback_speed=self._timeline.rate, did_seek=did_seek, request_id=request_id)

    def control(self, request: PlaybackControlRequest) -> PlaybackState:
        """Apply a client's play/pause, speed and seek; the state after it."""
        with self._cond:
            if request.playback_speed and request.playback_speed > 0:
                self._timeline.set_rate(float(request.playback_speed))
            seek = request.seek_time
            if seek is not None:
                self._seek_to = min(max(int(seek), self.start_ns), self.end_ns)
            if request.playback_command == PlaybackCommand.Play:
                if self._ended and seek is None:
                    self._seek_to = self.start_ns  # play after the end: from the start
                self._timeline.resume()
            else:
                self._timeline.pause()
            self._cond.notify_all()
        return self.state(request.request_id, did_seek=seek is not None)

    # ------------------------------------------------------------------ playback (its own thread)
    def _play(self) -> None:
        messages, last_time = None, None
        while True:
            with self._cond:
                if self._stop:
                    return
                if self._seek_to is not None:
                    at, self._seek_to, self._ended = self._seek_to, None, False
                    self._timeline.restart(at, time.monotonic_ns())  # paused or playing, from ``at``
                    messages, last_time, self._inputs = self._reader.messages(start=at), None, SceneInputs()
                    self.server.broadcast_time(at)
                if self._ended or messages is None:
                    self._cond.wait(_IDLE_S)
                    continue
            item = next(messages, None)
            if item is None:
                with self._cond:
                    self._ended = True
                self.server.broadcast_playback_state(self.state())
                continue
            conn, log_ns, raw = item
            if not self._wait_until(log_ns):
                continue  # a seek (or stop) came first: handled above
            channel = self._channels.get(conn.id)
            if channel is None:  # a topic not served (see _channels)
                continue
            channel.log(bytes(raw), log_time=log_ns)
            self.sent += 1
            self._draw(conn, log_ns, raw)
            if last_time is None or log_ns - last_time >= _TIME_EVERY_NS:
                self.server.broadcast_time(log_ns)
                last_time = log_ns

    def _draw(self, conn: Any, log_ns: int, raw: bytes) -> None:
        """Take in a message that feeds the scene; at each step's joint state, log the scene's markers."""
        reading = input_reader(conn.topic)
        if reading is None:
            return
        field, read = reading
        try:
            setattr(self._inputs, field, read(self._reader.deserialize(raw, conn.msgtype)))
            if field != "actuator_angles":
                return
            i = self._inputs
            scene = build_scene(self._hand, actuator_angles=i.actuator_angles, object_xy_mm=i.object_xy_mm,
                                goal_xy_mm=i.goal_xy_mm, tolerance_mm=self._tolerance_mm, path_xy_mm=i.path_xy_mm,
                                candidates=i.candidates or ())
        except ValueError:  # a message the scene cannot use (another frame, NaN): the picture waits for the next
            return
        self._markers.log(serialize_message(scene_markers(scene, log_ns, ma.RCLPY)), log_time=log_ns)

    def _wait_until(self, log_ns: int) -> bool:
        """Wait until ``log_ns`` is due; False when a seek or stop came first (the message is not sent)."""
        with self._cond:
            while True:
                if self._stop or self._seek_to is not None:
                    return False
                delay_s = (self._timeline.due_ns(log_ns) - time.monotonic_ns()) / 1e9
                if delay_s <= 0:
                    return True
                self._cond.wait(min(delay_s, _IDLE_S))

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(5.0)
        self.server.stop()
        self._reader.close()


class _Controls(foxglove.websocket.ServerListener):
    def __init__(self, bag: BagServer) -> None:
        self.bag = bag

    def on_playback_control_request(self, playback_control_request: PlaybackControlRequest) -> PlaybackState:
        return self.bag.control(playback_control_request)


def serve_bag(bag: str | Path, host: str = "127.0.0.1", port: int = 8765, hand: str = "target",
              tolerance_mm: float = DEFAULT_TOLERANCE_MM) -> int:
    """``t42 view --bag``: serve ``bag`` until Ctrl-C (or SIGTERM); exit code 0."""
    stop = threading.Event()
    server = BagServer(bag, host=host, port=port, hand=hand, tolerance_mm=tolerance_mm)
    # After the server opened: a bag that does not open raised before, with no handler left installed behind it.
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        span = (server.end_ns - server.start_ns) / 1e9
        print(f"serving {server.path} ({len(server._channels)} topics, {span:.1f} s) on ws://{host}:{server.port}; "
              "open it in Foxglove (Open connection -> Foxglove WebSocket); Ctrl-C stops", flush=True)
        stop.wait()
    finally:
        server.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
