"""A service whose answer is sent later than its callback returns, on any rclpy executor.

rclpy answers a request with what the service callback returns.  An answer that waits on later work (the
driver's ``hand/reset`` answers once the grasp, run by the next control steps, closed) takes a coroutine
callback on the Python executors, and rclpy 7.1.6's EventsExecutor does not await one: the coroutine is never
run and its ``send_response`` raises TypeError out of the spin.  So here the callback returns at once, either
the response or a :class:`Pending` answer; the executor hands the request's header to the service's
``send_response``, which this service's own routing keeps with the pending answer, and :meth:`Pending.answer`
sends the response with that header when the work is done (rclpy's public ``Service.send_response``).
Callbacks and answers are expected on the executor's thread (the driver's single thread).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


class Pending:
    """An answer to come: :meth:`answer` sends it, once (later calls are ignored)."""

    def __init__(self, send: Callable[[Any, Any], None]) -> None:
        self._send = send
        self._header: Any = None
        self._response: Any = None
        self.answered = False

    def answer(self, response: Any) -> None:
        if self.answered:
            return
        self.answered = True
        self._response = response
        self._flush()

    def _set_header(self, header: Any) -> None:
        self._header = header
        self._flush()

    def _flush(self) -> None:
        if self._header is not None and self._response is not None:
            response, header, self._response, self._header = self._response, self._header, None, None
            self._send(response, header)


class DeferredService:
    """``node.create_service`` whose ``callback(request, response)`` returns the response, or :meth:`later`'s
    :class:`Pending` to answer it afterwards."""

    def __init__(self, node: Any, srv_type: Any, name: str, callback: Callable[[Any, Any], Any],
                 **kwargs: Any) -> None:
        self.service = node.create_service(srv_type, name, callback, **kwargs)
        self._send = self.service.send_response
        self.service.send_response = self._route  # the executor sends what the callback returned through here

    def later(self) -> Pending:
        return Pending(self._send)

    def _route(self, response: Any, header: Any) -> None:
        if isinstance(response, Pending):
            response._set_header(header)
        else:
            self._send(response, header)
