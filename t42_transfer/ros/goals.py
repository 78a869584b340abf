"""An rclpy ActionServer that knows which of its accepted goals still owe a client their result.

rclpy's ActionServer sends a goal's result only in answer to a result request, and only while its node is spun: a
node that stops spinning right after its goals ended leaves a client that asks a moment later waiting for ever
(rclpy's ActionClient never gives up on a result).  A node that closes spins until :meth:`~AnsweringActionServer.\
unanswered` is 0.  A goal counts from its acceptance (its execute callback may not have started yet: rclpy queues
it on the executor) until its result has been sent once, or, once it has ended, until ``ask_wait_s`` passed
without a client asking for it (its client left).  Clients ask for the result as soon as the goal is accepted, so
the wait is short unless a client is gone.

Built on two private parts of rclpy 7.1's ActionServer: ``_result_futures`` (a goal's result future, made when
it is accepted, dropped when it expires) and ``_send_result_response`` (called for every result sent).
"""

from __future__ import annotations

import threading
import time
from typing import Any

from rclpy.action import ActionServer


class AnsweringActionServer(ActionServer):
    """An :class:`~rclpy.action.ActionServer` (same arguments, but ``handle_accepted_callback``, which it uses to
    time the goals' ends) that counts the goals whose result has not been sent yet."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._answer_lock = threading.Lock()
        self._sent: set[bytes] = set()
        """Goals whose result has been sent (to the first client that asked)."""
        self._ended: dict[bytes, float] = {}
        """When each ended goal's result was set (monotonic s)."""
        super().__init__(*args, handle_accepted_callback=self._accepted, **kwargs)

    def _accepted(self, handle: Any) -> None:
        uuid = bytes(handle.goal_id.uuid)
        future = self._result_futures.get(uuid)
        if future is not None:
            future.add_done_callback(lambda _: self._note_end(uuid))
        handle.execute()  # rclpy's default: the execute callback is queued on the executor

    def _note_end(self, uuid: bytes) -> None:
        with self._answer_lock:
            self._ended.setdefault(uuid, time.monotonic())

    def _send_result_response(self, request_header: Any, future: Any) -> None:
        super()._send_result_response(request_header, future)
        with self._answer_lock:
            self._sent.update(uuid for uuid, f in list(self._result_futures.items()) if f is future)

    def unanswered(self, ask_wait_s: float) -> int:
        """The accepted goals that still owe a client their result: running or queued, or ended less than
        ``ask_wait_s`` ago with no result request answered."""
        now = time.monotonic()
        futures = dict(self._result_futures)
        with self._answer_lock:
            self._sent &= futures.keys()  # expired goals are forgotten
            self._ended = {uuid: t for uuid, t in self._ended.items() if uuid in futures}
            count = 0
            for uuid, future in futures.items():
                if uuid in self._sent:
                    continue
                if future.done() and now - self._ended.setdefault(uuid, now) > ask_wait_s:
                    continue  # nobody asked for it in time: its client is gone
                count += 1
            return count
