"""The transfer server's status on ``diagnostics``: the stage of the running (or last) transfer and what is known.

One status named :data:`STATUS_NAME`, level OK while running and when done, WARN for a refusal, ERROR for a
failure; key-values ``stage``, ``elapsed_s``, ``method`` and what the transfer reported so far (the server's
docstring lists them).  The worker thread publishes at each stage change and epoch, the waiting callback every
``progress_period_s``, and a timer each second once a transfer has ended.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node

from msg_adapters import RCLPY, diagnostic_array, names

STATUS_NAME = "t42_transfer: transfer"
"""Name of the transfer server's status in ``diagnostics``."""

_MESSAGES = {
    "loading": "loading the source model and the new bags",
    "training": "training",
    "evaluating": "scoring on held-out target episodes",
    "saving": "saving the model",
}


class TransferStatus:
    """The status of ``node``'s transfers, published one at a time from any thread: read under the lock, so a
    periodic publish cannot send an older epoch after the worker has published a newer one."""

    def __init__(self, node: Node, method: str) -> None:
        self._node = node
        self._publisher = node.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 10)
        self._lock = threading.Lock()
        self._status: dict[str, Any] = {"stage": "idle", "level": "OK", "message": "idle", "values": {}}
        self.method = method
        """The method of the running (or last) transfer."""
        self.started = time.monotonic()
        self.closed = False
        """Set when the node closes: nothing is published from then."""

    @property
    def stage(self) -> str:
        return self._status["stage"]

    def begin(self, method: str) -> None:
        """A new transfer with ``method`` starts (its values start empty)."""
        self.started, self.method = time.monotonic(), method
        self._status = {"stage": "loading", "level": "OK", "message": "starting", "values": {}}

    def busy(self, again: str) -> str:
        """What a caller refused while a transfer runs is told (``again``: what to do when it is done)."""
        return (f"busy: a {self.method} transfer is {self.stage} ({time.monotonic() - self.started:.0f} s in); "
                f"{again} when it is done")

    def report(self, stage: str, info: Mapping[str, object]) -> None:
        """Progress callback of :func:`~t42_transfer.transfer.online.run_transfer` (worker thread); an epoch report
        says which in the message."""
        message = _MESSAGES.get(stage, stage)
        if stage == "training" and "phase" in info:
            message = f"training {info['phase']}: epoch {info['epoch']}/{info['epochs']}"
        self.set(stage, "OK", message, info)

    def set(self, stage: str, level: str, message: str, info: Mapping[str, object]) -> None:
        """Move to ``stage`` with ``level`` and ``message``, ``info`` added to the values known; publish it."""
        values = {**self._status["values"], **info}
        self._status = {"stage": stage, "level": level, "message": message, "values": values}
        self.publish()

    def publish_ended(self, running: bool) -> None:
        """The status once a transfer has ended (before: nothing to say; while one runs, its worker publishes)."""
        if self.stage != "idle" and not running:
            self.publish()

    def publish(self) -> None:
        """Publish the current status; failures are logged (it runs from worker and callback threads)."""
        try:
            with self._lock:
                if self.closed:
                    return
                status = self._status
                values = {"stage": status["stage"], "elapsed_s": f"{time.monotonic() - self.started:.1f}",
                          "method": self.method, **status["values"]}
                self._publisher.publish(diagnostic_array(STATUS_NAME, status["level"], status["message"], values,
                                                         self._node.get_clock().now().nanoseconds, kit=RCLPY))
        except Exception as err:
            self._node.get_logger().error(f"could not publish the transfer status: {err!r}")
