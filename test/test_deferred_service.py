"""A service answered after its callback returned, on each executor a node of the suite spins on."""

from __future__ import annotations

import pytest
from ros_rig import RosRig
from std_srvs.srv import Trigger

from t42_transfer.ros.deferred_service import DeferredService, Pending


class Server:
    """Answers "now" requests at once and the others when :meth:`finish` runs (later work, elsewhere)."""

    def __init__(self, ros: RosRig) -> None:
        self.node = ros.node("server")
        self.pending: list[Pending] = []
        self.service = DeferredService(self.node, Trigger, "work", self._on_request)

    def _on_request(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response | Pending:
        if len(self.pending) >= 2:
            response.success, response.message = False, "busy"
            return response
        answer = self.service.later()
        self.pending.append(answer)
        return answer

    def finish(self, message: str) -> None:
        for answer in self.pending:
            answer.answer(Trigger.Response(success=True, message=message))
            answer.answer(Trigger.Response(success=False, message="a second answer"))  # ignored
        self.pending.clear()


@pytest.mark.parametrize("events", [False, True], ids=["single_threaded", "events"])
def test_answers_come_when_the_work_is_done_not_when_the_callback_returns(ros_domain: int, events: bool) -> None:
    ros = RosRig(ros_domain, events=events)
    try:
        server = Server(ros)
        client = ros.node("client").create_client(Trigger, "work")
        assert client.wait_for_service(timeout_sec=10.0)
        first, second = client.call_async(Trigger.Request()), client.call_async(Trigger.Request())
        assert ros.spin_until(lambda: len(server.pending) == 2)
        assert ros.call(client, Trigger.Request()).message == "busy"  # answered at once, while two wait
        ros.spin_for(0.3)
        assert not first.done() and not second.done()
        server.finish("done")
        assert ros.spin_until(lambda: first.done() and second.done())
        assert [(f.result().success, f.result().message) for f in (first, second)] == [(True, "done")] * 2
        ros.spin_for(0.3)  # the ignored second answers sent nothing a later call could receive
        third = client.call_async(Trigger.Request())
        assert ros.spin_until(lambda: len(server.pending) == 1)
        server.finish("again")
        assert ros.spin_until(third.done) and third.result().message == "again"
    finally:
        ros.shutdown()
