"""Emulated T42 hardware: two XM430 servos on a pseudo-terminal with the simulated hand behind them, and a tracker.

What a driver meets where a real hand would be (``t42 hw emulate``):

* the servo bus on a pty (``link`` makes a stable symlink to it): Dynamixel protocol 2.0, the servos'
  control tables, :mod:`t42_transfer.hardware.emulator`; Goal Position drives the simulated hand's tendons,
  Present Position and Present Current come from its physics, stepped once per control period;
* ``tracker/object_pose`` (geometry_msgs/PoseStamped): the object as the real hands' camera saw it, at
  ``pose_rate_hz`` (the public test paths show 34-53 % of 10 Hz steps with no new pose), stamped at capture,
  ``pose_latency_s`` late, each frame lost with probability ``pose_dropout``;
* ``sim/object_pose``: the true object position every step, for checks only;
* with ``camera_rate_hz`` above 0, a rendered camera instead of the emulated tracker
  (:mod:`t42_transfer.ros.sim_camera`): ``camera/image_raw`` + ``camera/camera_info`` of the hand as it is after
  each tick, stamped with the tick, for an ``object_tracker`` to publish ``tracker/object_pose`` from;
* with ``sim_time``, ``/clock``: one control period per tick, ``rate_factor`` times faster than real time at
  most: in ``lockstep`` (the default) a tick waits until the driver has written its goals for the last one
  (or ``lockstep_wait_s`` passed), so a driver slowed by a busy machine slows the clock instead of missing
  periods (a real hand cannot wait: on wall time there is no lockstep).

Faults are parameters, so they are injected at start (``-p drop_replies:=5``) or at run time
(``ros2 param set``): ``drop_replies``, ``corrupt_replies`` and ``slow_replies`` (each answer
``reply_delay_s`` late) count down as replies go, and the parameter with them (at 0 again, the same count may
be set again), ``dead_servos`` never answer, ``error_bits`` sets a Hardware Error Status on the servos in id
order when it changes (e.g. ``[0, 32]``: overload on the second; a reboot clears it, and ``[0, 0]`` before the
same bits again raises them again), ``port_closed`` takes the terminal away (and back when set false: a new pty at
the same link).
"""

from __future__ import annotations

import math
import random
import time
from dataclasses import dataclass
from typing import Any

from geometry_msgs.msg import PoseStamped
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock

from msg_adapters import RCLPY, names, ns_to_stamp, object_pose_msg
from t42_transfer.conventions import CONTROL_PERIOD_NS, CONTROL_PERIOD_S
from t42_transfer.hand.params import NAMED_VARIANTS
from t42_transfer.hand.sim import SimulatedHand
from t42_transfer.hardware.emulator import PtyBus, t42_bus
from t42_transfer.hardware.hand_plant import HandPlant
from t42_transfer.ros.node_lifetime import destroyed_if_init_fails
from t42_transfer.ros.params import LiveParams, param
from t42_transfer.ros.sim_camera import SimCamera, SimCameraParams

SPENT_FAULTS = ("drop_replies", "corrupt_replies", "slow_replies")
"""Faults given as a count of replies, which the bus counts down as it answers."""


@dataclass(frozen=True)
class HwEmulatorParams(SimCameraParams):
    """The emulator's ROS parameters (and its rendered camera's)."""

    link: str = param("", "symlink to the servo bus's pty (empty: none; the log names the pty); replaces only "
                          "an earlier emulator's link into /dev/pts/", read_only=True)
    hand: str = param("target", f"simulated hand behind the servos: {', '.join(NAMED_VARIANTS)} or family-<seed>",
                      read_only=True)
    seed: int = param(0, "seed of the first object placement; each placement after uses the next", min=0,
                      read_only=True)
    rate_factor: float = param(1.0, "physics runs this many times faster than real time", min=1e-3, max=100.0)
    sim_time: bool = param(False, "be the graph's clock: /clock advances one control period per tick",
                           read_only=True)
    lockstep: bool = param(True, "with sim_time: the next tick waits (up to lockstep_wait_s) for the driver's "
                                 "goals of this one, so a late driver misses no period")
    lockstep_wait_s: float = param(0.5, "wall seconds a tick waits for the driver's goals in lockstep",
                                   min=0.0, max=60.0)
    pose_rate_hz: float = param(6.0, "tracker frames per second of (sim) time", min=0.1, max=100.0)
    pose_latency_s: float = param(0.03, "a frame goes out this long after it was captured", min=0.0, max=1.0)
    pose_dropout: float = param(0.0, "probability that a frame is lost", min=0.0, max=1.0)
    drop_replies: int = param(0, "replies still to drop", min=0, max=1_000_000)
    corrupt_replies: int = param(0, "replies still to corrupt (one byte flipped)", min=0, max=1_000_000)
    slow_replies: int = param(0, "answers still to send reply_delay_s late (a busy host, a buffering adapter)",
                              min=0, max=1_000_000)
    reply_delay_s: float = param(0.05, "how late a slow answer comes", min=0.0, max=1.0)
    dead_servos: tuple[int, ...] = param((0,), "ids of servos that no longer answer (0: none)")
    error_bits: tuple[int, ...] = param((0, 0), "Hardware Error Status to raise on the servos, in id order")
    port_closed: bool = param(False, "the adapter unplugged: the pty goes away until set false")

    def __post_init__(self) -> None:
        self.check_camera()
        if any(not 0 <= b <= 255 for b in self.error_bits):
            raise ValueError(f"error_bits must be bytes (0-255), got {list(self.error_bits)}")


class HwEmulator(Node):
    """The emulated hand on its bus, and its tracker; see the module docstring."""

    params_class = HwEmulatorParams  # the one its LiveParams declares; t42 node NAME --help lists it

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("hw_emulator", **node_kwargs)
        self._params = LiveParams(self, self.params_class, self._on_params)
        p = self.params
        self.log = self.get_logger()
        self.plant = HandPlant(SimulatedHand(p.hand), seed=p.seed)
        self.bus = t42_bus(plant=self.plant)
        # The camera first: a renderer that cannot start fails the node before a pty is opened.
        self.camera = SimCamera(self, self.plant.hand.params, p) if p.camera_rate_hz > 0 else None
        self.pty: PtyBus | None = None
        """The servo bus's port: opened last (by the faults' first application), so that a driver that finds it
        at once finds the servos with their faults, and none with ``port_closed``."""
        self._rng = random.Random(p.seed)
        self._sim_ns = time.time_ns()  # the wall time: with use_sim_time on itself, ROS time is 0 until its /clock
        self._next_frame_ns = self._sim_ns
        self._writes_at_tick, self._tick_wall_s = 0, 0.0
        """Lockstep: the bus's goal writes and the wall time at the last tick."""
        self._pending: list[tuple[int, int, Any]] = []
        """Frames captured and not yet out: (due, capture stamp, xy)."""
        self._tracker = self.create_publisher(PoseStamped, names.TRACKER_POSE, 10)
        self._truth = self.create_publisher(PoseStamped, names.SIM_POSE, 10)
        self._clock_pub = self.create_publisher(Clock, names.CLOCK, 10) if p.sim_time else None
        # The graph's clock ticks on the machine's: on ROS time (use_sim_time) it would wait for itself.
        self._timer = self.create_timer(CONTROL_PERIOD_S / p.rate_factor, self._on_timer,
                                       clock=RosClock(clock_type=ClockType.STEADY_TIME) if p.sim_time else None)
        self._apply_faults(p)
        where = "closed (port_closed)" if self.pty is None else f"on {self.port}"
        self.log.info(f"servo bus {where} (servos 1 and 2, XM430-W350), hand {p.hand!r}")

    @property
    def params(self) -> HwEmulatorParams:
        return self._params.value

    @property
    def port(self) -> str:
        return "" if self.pty is None else self.pty.port

    def now_ns(self) -> int:
        return self._sim_ns if self._clock_pub is not None else self.get_clock().now().nanoseconds

    def close(self) -> None:
        self._timer.cancel()
        if self.camera is not None:
            self.camera.close()
        if self.pty is not None:
            self.pty.close_port()
            self.pty = None

    # ------------------------------------------------------------------ faults
    def _on_params(self, old: HwEmulatorParams, new: HwEmulatorParams) -> None:
        if new.rate_factor != old.rate_factor:
            self._timer.timer_period_ns = round(CONTROL_PERIOD_S / new.rate_factor * 1e9)
        self._apply_faults(new, old)

    def _apply_faults(self, p: HwEmulatorParams, old: HwEmulatorParams | None = None) -> None:
        """Inject the faults whose parameters changed (all at start): a change of another parameter must not
        inject again a fault already spent or cleared."""
        def changed(name: str) -> bool:
            return old is None or getattr(p, name) != getattr(old, name)

        faults = self.bus.faults
        with self.bus.lock:
            for name in (*SPENT_FAULTS, "reply_delay_s"):
                if changed(name):
                    setattr(faults, name, getattr(p, name))
            if changed("dead_servos"):
                faults.dead = {i for i in p.dead_servos if i}
            if changed("error_bits"):
                for servo, bits in zip(sorted(self.bus.servos), p.error_bits, strict=False):
                    if bits:
                        self.bus.servos[servo].raise_error(bits)
        if p.port_closed and self.pty is not None:
            self.log.warning(f"port {self.pty.port} closed (the adapter unplugged)")
            self.pty.close_port()
            self.pty = None
        elif not p.port_closed and self.pty is None:
            self.pty = PtyBus(self.bus, link=p.link or None)
            if old is not None:
                self.log.info(f"port back on {self.pty.port}")

    # ------------------------------------------------------------------ one tick
    def _waits_for_the_driver(self) -> bool:
        """In lockstep, whether this tick waits: the driver has not written its goals since the last one yet."""
        p = self.params
        if self._clock_pub is None or not p.lockstep:
            return False
        now = time.monotonic()
        if self.bus.sync_writes == self._writes_at_tick and now - self._tick_wall_s < p.lockstep_wait_s:
            return True
        self._writes_at_tick, self._tick_wall_s = self.bus.sync_writes, now
        return False

    def _on_timer(self) -> None:
        if self._waits_for_the_driver():
            return
        try:
            if self._clock_pub is not None:
                self._sim_ns += CONTROL_PERIOD_NS
                self._clock_pub.publish(Clock(clock=ns_to_stamp(self._sim_ns, RCLPY)))
            self.plant.tick()
            self._count_spent_faults()
            now = self.now_ns()
            if self.camera is None:
                self._truth.publish(object_pose_msg(self.plant.hand.object_xy, now, RCLPY))
                self._emulated_tracker(now)
            elif not self.camera.capture(self.plant.hand, now):  # a frame publishes the truth with its stamp
                self._truth.publish(object_pose_msg(self.plant.hand.object_xy, now, RCLPY))
        except Exception as err:  # never raise from a callback
            self.log.error(f"emulator tick failed: {err!r}", throttle_duration_sec=1.0)

    def _count_spent_faults(self) -> None:
        """Fault counts the bus used up go back to 0 in the parameters too: ``ros2 param get`` says what is left,
        and setting the same count again injects it again."""
        with self.bus.lock:
            spent = [name for name in SPENT_FAULTS if getattr(self.params, name) and not getattr(self.bus.faults, name)]
        if spent:
            self.set_parameters([Parameter(name, value=0) for name in spent])

    def _emulated_tracker(self, now: int) -> None:
        """Frames at the tracker's rate, with a little jitter: each captured now, sent after the latency."""
        p = self.params
        period_ns = round(1e9 / p.pose_rate_hz)
        while self._next_frame_ns <= now:
            jitter = self._rng.uniform(-0.1, 0.1) * period_ns
            self._next_frame_ns += max(1, round(period_ns + jitter))
            if self._rng.random() >= p.pose_dropout:
                xy = self.plant.hand.state[:2]
                self._pending.append((now + round(p.pose_latency_s * 1e9), now, xy))
        due, self._pending = self._pending, []
        for frame in due:
            if frame[0] > now + CONTROL_PERIOD_NS // 2:  # not yet: its latency runs past this tick
                self._pending.append(frame)
                continue
            _, stamp, xy = frame
            if math.isfinite(float(xy[0])):
                self._tracker.publish(object_pose_msg(xy, stamp, RCLPY))
