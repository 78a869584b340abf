"""Cyclone DDS services: rmw_cyclonedds_cpp wire layout, correlation, readiness, failures, across processes."""

from __future__ import annotations

import logging
import os
import random
import struct
import subprocess
import sys
import textwrap
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import pytest

pytest.importorskip("cyclonedds", reason="cyclonedds (cyclonedds-python) is not installed")

from cyclonedds.core import InstanceState, Policy, SampleState, ViewState  # noqa: E402
from cyclonedds.domain import DomainParticipant  # noqa: E402
from cyclonedds.pub import DataWriter  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402

from cyclonedds._clayer import ddspy_take, ddspy_write  # noqa: E402

from t42_transfer.ros import dds_types  # noqa: E402
from t42_transfer.ros.cyclone import (  # noqa: E402
    CycloneTransport,
    dds_qos,
    pack_service_sample,
    unpack_service_sample,
)
from t42_transfer.ros.naming import SRV_TYPESTORE, type_hash  # noqa: E402
from t42_transfer.ros.qos import SERVICES_DEFAULT  # noqa: E402
from t42_transfer.ros.transport import TransportClosed, message_class, serialize  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TRIGGER = "std_srvs/srv/Trigger"
REQ, RESP = "std_srvs/srv/Trigger_Request", "std_srvs/srv/Trigger_Response"
Request, Response = SRV_TYPESTORE.types[REQ], SRV_TYPESTORE.types[RESP]


@pytest.fixture
def domain_id(monkeypatch: pytest.MonkeyPatch) -> int:
    """A random domain per test, localhost discovery, so concurrent runs do not meet."""
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    monkeypatch.delenv("CYCLONEDDS_URI", raising=False)
    return random.randint(100, 200)


@contextmanager
def spinning(node: CycloneTransport) -> Iterator[None]:
    """Spin ``node`` in a background thread (a ROS executor stand-in) until the block ends."""
    stop = threading.Event()
    thread = threading.Thread(target=lambda: node.spin(until=stop.is_set), daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(5)


def _echo(request: Any) -> Any:
    """Answers with the request's one byte, so a client can tell its replies from others'."""
    return Response(success=True, message=f"got {request.structure_needs_at_least_one_member}")


def test_sample_layout_is_header_then_body() -> None:
    response = Response(success=True, message="ok, reset")
    body = serialize(RESP, response)
    guid, seq = 0xFEDCBA9876543210, 42
    wire = pack_service_sample(guid, seq, body)
    assert wire[:4] == b"\x00\x01\x00\x00"
    assert struct.unpack("<Qq", wire[4:20]) == (guid, seq)
    assert wire[20:] == body[4:]
    # The registered wire type serialises to exactly these bytes: the body's alignment survives.
    cls = dds_types.dds_service_class(RESP)
    assert cls.__idl_typename__ == "std_srvs::srv::dds_::Trigger_Response_"
    assert cls(request_header_guid=guid, request_header_seq=seq, success=True, message="ok, reset").serialize() == wire
    assert unpack_service_sample(wire) == (guid, seq, body)
    assert SRV_TYPESTORE.deserialize_cdr(wire[:4] + wire[20:], RESP) == response
    big_endian = b"\x00\x00\x00\x00" + struct.pack(">Qq", guid, seq) + b"\x01"
    assert unpack_service_sample(big_endian)[:2] == (guid, seq)
    with pytest.raises(ValueError):
        unpack_service_sample(wire[:12])


def test_service_type_names() -> None:
    assert dds_types.dds_service_class(REQ).__idl_typename__ == "std_srvs::srv::dds_::Trigger_Request_"
    assert dds_types.dds_class(REQ).__idl_typename__ == "std_srvs::srv::dds_::Trigger_Request_"
    request = Request(structure_needs_at_least_one_member=7)
    wire = pack_service_sample(1, 2, serialize(REQ, request))
    obj = dds_types.dds_service_class(REQ).deserialize(wire)
    assert (obj.request_header_guid, obj.request_header_seq, obj.structure_needs_at_least_one_member) == (1, 2, 7)
    with pytest.raises(ValueError):
        dds_types.dds_service_class("std_msgs/msg/String")


def _take_raw(reader: DataReader) -> list[bytes]:
    return [bytes(d) for d, i in ddspy_take(reader._ref, SampleState.Any | ViewState.Any | InstanceState.Any, 64)
            if i.valid_data]


def test_trigger_round_trip_and_wire(domain_id: int) -> None:
    with CycloneTransport("server", domain_id) as server, CycloneTransport("caller", domain_id) as caller:
        got: list[Any] = []
        server.service("/reset", TRIGGER, lambda req: (got.append(req), _echo(req))[1])
        client = caller.client("/reset", TRIGGER)
        # A third participant listens to both topics as plain DDS, to see the bytes on the wire.
        spy = DomainParticipant(domain_id)
        try:
            rq = DataReader(spy, Topic(spy, "rq/resetRequest", dds_types.dds_service_class(REQ)),
                            qos=dds_qos(SERVICES_DEFAULT))
            rr = DataReader(spy, Topic(spy, "rr/resetReply", dds_types.dds_service_class(RESP)),
                            qos=dds_qos(SERVICES_DEFAULT))
            deadline = time.monotonic() + 5
            while not (rq.get_matched_publications() and rr.get_matched_publications()) \
                    and time.monotonic() < deadline:
                time.sleep(0.01)
            with spinning(server):
                response = client.call(Request(structure_needs_at_least_one_member=9), timeout_s=5)
            requests, replies = _take_raw(rq), _take_raw(rr)
            while not replies and time.monotonic() < deadline:
                time.sleep(0.01)
                requests, replies = requests + _take_raw(rq), replies + _take_raw(rr)
        finally:
            spy.__del__()

        assert response == Response(success=True, message="got 9")
        assert [r.structure_needs_at_least_one_member for r in got] == [9]
        assert len(requests) == 1 and len(replies) == 1
        guid, seq, body = unpack_service_sample(requests[0])
        assert guid == client.guid
        assert body == serialize(REQ, Request(structure_needs_at_least_one_member=9))
        assert unpack_service_sample(replies[0]) == (guid, seq, serialize(RESP, response))

        # Names, types and USER_DATA as rmw_cyclonedds_cpp sets them.
        service = server._services[0]
        assert service.reader.topic.name == "rq/resetRequest"
        assert service.writer.topic.name == "rr/resetReply"
        assert service.writer.topic.typename == "std_srvs::srv::dds_::Trigger_Response_"
        assert client.writer.topic.typename == "std_srvs::srv::dds_::Trigger_Request_"
        server_ud = service.reader.get_qos()[Policy.Userdata].data.decode()
        client_ud = client.reader.get_qos()[Policy.Userdata].data.decode()
        assert server_ud == f"serviceid={service.csid};typehash={type_hash(REQ)};"
        assert client_ud == f"clientid={client.csid};typehash={type_hash(RESP)};"
        assert client.writer.get_qos()[Policy.Userdata].data.decode().startswith(f"clientid={client.csid};")
        assert Policy.Reliability.Reliable(max_blocking_time=100_000_000) in service.reader.get_qos()
        assert Policy.History.KeepLast(10) in client.writer.get_qos()


def test_call_needs_no_spin_of_the_client_node_and_works_from_any_thread(domain_id: int) -> None:
    with CycloneTransport("server", domain_id) as server, CycloneTransport("caller", domain_id) as caller:
        server.service("/reset", TRIGGER, _echo)
        with spinning(server):
            client = caller.client("/reset", TRIGGER)
            # Same thread, nobody spins `caller`.
            assert client.call(Request(structure_needs_at_least_one_member=1), 5).message == "got 1"
            # From another thread while the main thread spins the caller's node.
            out: list[Any] = []
            request = Request(structure_needs_at_least_one_member=2)
            worker = threading.Thread(target=lambda: out.append(client.call(request, 5)))
            worker.start()
            caller.spin(until=lambda: not worker.is_alive(), timeout_s=6)
            worker.join()
            assert [r.message for r in out] == ["got 2"]


def test_concurrent_clients_each_get_their_own_replies(domain_id: int) -> None:
    def slow_echo(request: Any) -> Any:
        time.sleep(0.002)
        return _echo(request)

    with CycloneTransport("server", domain_id) as server, \
            CycloneTransport("a", domain_id) as a, CycloneTransport("b", domain_id) as b:
        server.service("/reset", TRIGGER, slow_echo)
        with spinning(server):
            clients = [a.client("/reset", TRIGGER), b.client("/reset", TRIGGER)]
            shared = clients[0]  # two threads on one client too: replies must reach the right caller
            callers = [(clients[0], 1), (clients[1], 2), (shared, 3)]
            results: dict[int, list[str]] = {tag: [] for _, tag in callers}
            errors: list[BaseException] = []

            def run(client: Any, tag: int) -> None:
                try:
                    for _ in range(15):
                        reply = client.call(Request(structure_needs_at_least_one_member=tag), 5)
                        results[tag].append(reply.message)
                except BaseException as exc:  # reported below
                    errors.append(exc)

            threads = [threading.Thread(target=run, args=c) for c in callers]
            for t in threads:
                t.start()
            for t in threads:
                t.join(30)
            assert not errors
            for tag, messages in results.items():
                assert messages == [f"got {tag}"] * 15
            assert clients[0].guid != clients[1].guid


def test_client_keeps_only_its_own_guid_and_seq(domain_id: int) -> None:
    """A raw DDS server answers each request with a foreign guid, a foreign seq, then the real reply."""
    with CycloneTransport("caller", domain_id) as caller:
        client = caller.client("/reset", TRIGGER)
        fake = DomainParticipant(domain_id)
        tag = b"serviceid=fake;"
        requests = DataReader(fake, Topic(fake, "rq/resetRequest", dds_types.dds_service_class(REQ)),
                              qos=dds_qos(SERVICES_DEFAULT, tag))
        replies = DataWriter(fake, Topic(fake, "rr/resetReply", dds_types.dds_service_class(RESP)),
                             qos=dds_qos(SERVICES_DEFAULT, tag))
        stop = threading.Event()

        def serve() -> None:
            while not stop.is_set():
                for data in _take_raw(requests):
                    guid, seq, _ = unpack_service_sample(data)
                    for g, q, text in ((guid ^ 1, seq, "other guid"), (guid, seq + 1000, "other seq"),
                                       (guid, seq, "mine")):
                        reply = serialize(RESP, Response(success=True, message=text))
                        ddspy_write(replies._ref, pack_service_sample(g, q, reply))
                        time.sleep(0.05)  # the client sees each one on its own
                time.sleep(0.005)

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        try:
            assert client.call(Request(structure_needs_at_least_one_member=0), timeout_s=5).message == "mine"
            assert client.call(Request(structure_needs_at_least_one_member=0), timeout_s=5).message == "mine"
            assert client._replies == {}  # nothing left behind for calls that never come
        finally:
            stop.set()
            thread.join(5)
            fake.__del__()


def test_timeout_and_not_ready_without_server(domain_id: int) -> None:
    with CycloneTransport("lonely", domain_id) as node:
        client = node.client("/nobody_home", TRIGGER)
        assert not client.service_is_ready()
        start = time.monotonic()
        with pytest.raises(TimeoutError):
            client.call(Request(structure_needs_at_least_one_member=0), timeout_s=0.3)
        assert 0.25 < time.monotonic() - start < 2.0


def test_service_is_ready_once_the_server_exists(domain_id: int) -> None:
    with CycloneTransport("caller", domain_id) as caller, CycloneTransport("server", domain_id) as server:
        client = caller.client("/reset", TRIGGER)
        other = caller.client("/other", TRIGGER)
        assert not client.service_is_ready()
        server.service("/reset", TRIGGER, _echo)
        deadline = time.monotonic() + 5
        while not client.service_is_ready() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert client.service_is_ready()
        assert not other.service_is_ready()


def test_handler_exception_is_logged_and_unanswered(domain_id: int,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    calls: list[int] = []

    def flaky(request: Any) -> Any:
        calls.append(request.structure_needs_at_least_one_member)
        if len(calls) == 1:
            raise RuntimeError("boom")
        return _echo(request)

    with CycloneTransport("server", domain_id) as server, CycloneTransport("caller", domain_id) as caller:
        server.service("/flaky", TRIGGER, flaky)
        with spinning(server):
            client = caller.client("/flaky", TRIGGER)
            with caplog.at_level(logging.ERROR, logger="t42_transfer.ros.server"):
                with pytest.raises(TimeoutError):
                    client.call(Request(structure_needs_at_least_one_member=1), timeout_s=1.0)
            assert any("handler failed" in r.getMessage() and r.exc_info for r in caplog.records)
            assert client.call(Request(structure_needs_at_least_one_member=2), timeout_s=5).message == "got 2"
            assert calls == [1, 2]


STRING = "std_msgs/msg/String"


def _wait_until(condition: Any, timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)
    return bool(condition())


def _call_in_thread(client: Any, tag: int, out: list[Any], timeout_s: float = 10.0) -> threading.Thread:
    """Call ``client`` from a new thread; the response, or the exception, lands in ``out``."""
    def run() -> None:
        try:
            out.append(client.call(Request(structure_needs_at_least_one_member=tag), timeout_s))
        except BaseException as exc:  # checked by the test
            out.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


class Blocking:
    """A handler that blocks each request until :attr:`release` is set, counting the ones inside."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.inside = 0
        self.entered = 0
        self._lock = threading.Lock()

    def __call__(self, request: Any) -> Any:
        with self._lock:
            self.inside += 1
            self.entered += 1
        try:
            assert self.release.wait(10.0)
            return _echo(request)
        finally:
            with self._lock:
                self.inside -= 1


def test_concurrent_service_keeps_the_node_serving(domain_id: int) -> None:
    slow = Blocking()
    with CycloneTransport("server", domain_id) as server, CycloneTransport("caller", domain_id) as caller:
        server.service("/slow", TRIGGER, slow, concurrent=True)
        server.service("/quick", TRIGGER, _echo)
        heard: list[str] = []
        server.subscribe("/chatter", STRING, SERVICES_DEFAULT, lambda m: heard.append(m.data))
        chatter = caller.publisher("/chatter", STRING, SERVICES_DEFAULT)
        slow_client = caller.client("/slow", TRIGGER)
        first: list[Any] = []
        second: list[Any] = []
        with spinning(server):
            threads = [_call_in_thread(slow_client, 1, first)]
            assert _wait_until(lambda: slow.inside == 1)
            start = time.monotonic()
            assert caller.client("/quick", TRIGGER).call(Request(structure_needs_at_least_one_member=3), 5).message \
                == "got 3"
            assert time.monotonic() - start < 1.5
            threads.append(_call_in_thread(slow_client, 2, second))
            assert _wait_until(lambda: slow.inside == 2), "a second request runs beside the first"
            # Published until heard: the first message may go out before the writer is matched.
            assert _wait_until(lambda: chatter.publish(message_class(STRING)(data="hi")) or heard, 5.0)
            assert first == [] and second == []
            slow.release.set()
            for thread in threads:
                thread.join(10)
        assert [r.message for r in first] == ["got 1"] and [r.message for r in second] == ["got 2"]


def test_plain_service_is_served_in_the_spin_loop_one_at_a_time(domain_id: int) -> None:
    slow = Blocking()
    served: list[str] = []
    with CycloneTransport("server", domain_id) as server, CycloneTransport("caller", domain_id) as caller:
        server.service("/slow", TRIGGER, slow)
        server.service("/quick", TRIGGER, lambda request: (served.append("quick"), _echo(request))[1])
        heard: list[str] = []
        server.subscribe("/chatter", STRING, SERVICES_DEFAULT, lambda m: heard.append(m.data))
        chatter = caller.publisher("/chatter", STRING, SERVICES_DEFAULT)
        quick = caller.client("/quick", TRIGGER)
        assert _wait_until(lambda: bool(chatter.writer.get_matched_subscriptions()) and quick.service_is_ready())
        first: list[Any] = []
        with spinning(server):
            thread = _call_in_thread(caller.client("/slow", TRIGGER), 1, first)
            assert _wait_until(lambda: slow.inside == 1)
            chatter.publish(message_class(STRING)(data="hi"))
            with pytest.raises(TimeoutError):
                quick.call(Request(structure_needs_at_least_one_member=2), timeout_s=0.5)
            assert heard == [] and served == [], "nothing else runs while the handler blocks the spin loop"
            slow.release.set()
            thread.join(10)
            assert _wait_until(lambda: heard == ["hi"] and served == ["quick"])
        assert [r.message for r in first] == ["got 1"] and slow.entered == 1


def test_closing_while_a_concurrent_handler_runs(domain_id: int, caplog: pytest.LogCaptureFixture) -> None:
    """close() does not wait for the handler; its late reply is dropped with a log line, no traceback."""
    slow = Blocking()
    with CycloneTransport("caller", domain_id) as caller:
        server = CycloneTransport("server", domain_id)
        server.service("/slow", TRIGGER, slow, concurrent=True)
        out: list[Any] = []
        with caplog.at_level(logging.INFO, logger="t42_transfer.ros.server"), spinning(server):
            thread = _call_in_thread(caller.client("/slow", TRIGGER), 1, out, timeout_s=2.0)
            assert _wait_until(lambda: slow.inside == 1)
            start = time.monotonic()
            server.close()  # from the test thread while spinning() spins it in another
            assert time.monotonic() - start < 1.0
            slow.release.set()
            assert _wait_until(lambda: slow.inside == 0)
            thread.join(5)
        assert len(out) == 1 and isinstance(out[0], TimeoutError)
        assert _wait_until(lambda: any("no reply" in r.getMessage() for r in caplog.records), 2.0)
        assert not [r for r in caplog.records if r.exc_info or r.levelno >= logging.WARNING]


def test_closing_the_node_ends_a_call_in_another_thread(domain_id: int) -> None:
    slow = Blocking()
    with CycloneTransport("server", domain_id) as server:
        server.service("/slow", TRIGGER, slow, concurrent=True)
        caller = CycloneTransport("caller", domain_id)
        waiting: list[Any] = []
        answering: list[Any] = []
        with spinning(server):
            threads = [_call_in_thread(caller.client("/nobody_home", TRIGGER), 1, waiting),
                       _call_in_thread(caller.client("/slow", TRIGGER), 2, answering)]
            assert _wait_until(lambda: slow.inside == 1)
            caller.close()
            for thread in threads:
                thread.join(2.0)
            slow.release.set()
        for out in (waiting, answering):
            assert len(out) == 1 and isinstance(out[0], TransportClosed), out
            assert str(out[0]) == "node caller is closed"


SERVER_SCRIPT = textwrap.dedent(
    """
    import sys, time
    from t42_transfer.ros.cyclone import CycloneTransport
    from t42_transfer.ros.naming import SRV_TYPESTORE
    Response = SRV_TYPESTORE.types["std_srvs/srv/Trigger_Response"]
    served = []
    def handle(request):
        served.append(request)
        return Response(success=True, message=f"remote {request.structure_needs_at_least_one_member}")
    with CycloneTransport("remote_server") as node:
        node.service("/remote_reset", "std_srvs/srv/Trigger", handle)
        print("up", flush=True)
        node.spin(until=lambda: len(served) >= 2, timeout_s=20)
        node.spin_once(0.2)
    """
)


def test_call_across_processes(domain_id: int) -> None:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONPATH=str(REPO))
    env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
    env.pop("CYCLONEDDS_URI", None)
    proc = subprocess.Popen([sys.executable, "-c", SERVER_SCRIPT], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        with CycloneTransport("local_caller", domain_id) as node:
            client = node.client("/remote_reset", TRIGGER)
            try:
                first = client.call(Request(structure_needs_at_least_one_member=4), timeout_s=20)
                second = client.call(Request(structure_needs_at_least_one_member=5), timeout_s=5)
            except TimeoutError:
                proc.kill()
                raise AssertionError(f"no reply; server stderr: {proc.communicate()[1].decode()[-2000:]}")
        assert (first.success, first.message) == (True, "remote 4")
        assert second.message == "remote 5"
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()
