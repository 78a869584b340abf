"""The in-process transport: CDR round trips, queues, QoS matching, services, timers."""

import logging

import numpy as np
import pytest

from msg_adapters import JOINT_STATE, POSE_STAMPED, TYPESTORE, joint_state_msg, object_pose_msg
from t42_transfer.ros import qos
from t42_transfer.ros.inprocess import FakeClock, InProcessBus, InProcessTransport, TopicTypeError
from t42_transfer.ros.transport import Transport, deserialize, serialize, service_classes

STRING = "std_msgs/msg/String"
TRIGGER = "std_srvs/srv/Trigger"
String = TYPESTORE.types[STRING]


@pytest.fixture
def nodes():
    bus = InProcessBus(clock=FakeClock(1_000_000_000))
    a, b = InProcessTransport(bus, "talker"), InProcessTransport(bus, "listener")
    yield bus, a, b
    a.close()
    b.close()


def test_is_a_transport(nodes):
    _, a, _ = nodes
    assert isinstance(a, Transport)
    assert a.logger.name.endswith("talker")


def _pose():
    return object_pose_msg(np.array([12.5, -3.25], np.float32), 1_234_567_890)


def _joint_state():
    return joint_state_msg(np.array([0.1, -0.2], np.float32), np.array([3.0, 4.0], np.float32), 42)


@pytest.mark.parametrize("msgtype,make", [(POSE_STAMPED, _pose), (JOINT_STATE, _joint_state)])
def test_round_trip_bytes_equal_rosbags(nodes, msgtype, make):
    _, a, b = nodes
    got, raw = [], []
    b.subscribe("/hand/x", msgtype, qos.DEFAULT, got.append)
    b.subscribe("/hand/x", msgtype, qos.DEFAULT, raw.append, raw=True)
    msg = make()
    a.publisher("/hand/x", msgtype).publish(msg)
    assert got == [] and raw == []  # delivery happens in spin_once
    assert b.spin_once() == 2
    expected = bytes(TYPESTORE.serialize_cdr(msg, msgtype))
    assert expected[:4] == b"\x00\x01\x00\x00"
    assert raw == [expected] and isinstance(raw[0], bytes)
    assert bytes(TYPESTORE.serialize_cdr(got[0], msgtype)) == expected
    assert got[0].__msgtype__ == msgtype


def test_publish_raw_exact_bytes(nodes):
    _, a, b = nodes
    raw = []
    b.subscribe("/chatter", STRING, qos.DEFAULT, raw.append, raw=True)
    data = serialize(STRING, String(data="hello"))
    a.publisher("/chatter", STRING).publish_raw(data)
    b.spin_once()
    assert raw == [data]
    assert deserialize(STRING, raw[0]).data == "hello"


def test_keep_last_depth_per_subscriber(nodes):
    _, a, b = nodes
    shallow, deep = [], []
    b.subscribe("/chatter", STRING, qos.QoSProfile(depth=2), lambda m: shallow.append(m.data))
    b.subscribe("/chatter", STRING, qos.DEFAULT, lambda m: deep.append(m.data))
    pub = a.publisher("/chatter", STRING)
    for i in range(12):
        pub.publish(String(data=str(i)))
    assert b.spin_once() == 12
    assert shallow == ["10", "11"]
    assert deep == [str(i) for i in range(2, 12)]
    assert b.spin_once() == 0


def test_keep_all(nodes):
    _, a, b = nodes
    got = []
    b.subscribe("/chatter", STRING, qos.QoSProfile(history=qos.History.KEEP_ALL), got.append)
    pub = a.publisher("/chatter", STRING)
    for i in range(50):
        pub.publish(String(data=str(i)))
    b.spin_once()
    assert len(got) == 50


def test_type_mismatch(nodes):
    _, a, b = nodes
    a.publisher("/hand/object_pose", POSE_STAMPED)
    with pytest.raises(TopicTypeError, match="carries geometry_msgs/msg/PoseStamped"):
        b.subscribe("/hand/object_pose", JOINT_STATE, qos.DEFAULT, print)
    with pytest.raises(TopicTypeError):
        b.publisher("/hand/object_pose", STRING)
    pub = a.publisher("/hand/object_pose", POSE_STAMPED)
    with pytest.raises(TypeError, match="expected a geometry_msgs/msg/PoseStamped"):
        pub.publish(String(data="x"))


def test_bad_names_and_types(nodes):
    _, a, _ = nodes
    with pytest.raises(ValueError):
        a.publisher("chatter", STRING)
    with pytest.raises(KeyError):
        a.publisher("/chatter", "nope_msgs/msg/Nope")
    with pytest.raises(ValueError):
        InProcessTransport(InProcessBus(), "bad-name")


def test_qos_matching_and_latching(nodes, caplog):
    bus, a, b = nodes
    got = []
    with caplog.at_level(logging.WARNING):
        b.subscribe("/chatter", STRING, qos.DEFAULT, got.append)
        a.publisher("/chatter", STRING, qos.SENSOR_DATA).publish(String(data="lost"))
    assert "incompatible QoS" in caplog.text
    b.spin_once()
    assert got == []

    latched = a.publisher("/status", STRING, qos.TRANSIENT_LOCAL)
    latched.publish(String(data="old"))
    latched.publish(String(data="new"))
    late = []
    c = InProcessTransport(bus, "late")
    c.subscribe("/status", STRING, qos.TRANSIENT_LOCAL, lambda m: late.append(m.data))
    c.spin_once()
    assert late == ["new"]


def test_trigger_service(nodes):
    _, a, b = nodes
    Request, Response = service_classes(TRIGGER)
    calls = []

    def handler(request):
        calls.append(request)
        return Response(success=True, message="reset done")

    a.service("/hand/reset", TRIGGER, handler)
    client = b.client("/hand/reset", TRIGGER)
    assert client.service_is_ready()
    response = client.call(Request(structure_needs_at_least_one_member=0), timeout_s=1.0)
    assert (response.success, response.message) == (True, "reset done")
    assert response.__msgtype__ == "std_srvs/srv/Trigger_Response"
    assert len(calls) == 1
    with pytest.raises(ValueError, match="already has a server"):
        b.service("/hand/reset", TRIGGER, handler)


def test_service_missing_times_out(nodes):
    _, _, b = nodes
    Request, _ = service_classes(TRIGGER)
    client = b.client("/nobody", TRIGGER)
    assert not client.service_is_ready()
    with pytest.raises(TimeoutError):
        client.call(Request(structure_needs_at_least_one_member=0), timeout_s=0.01)


def test_timer_with_fake_clock():
    clock = FakeClock()
    node = InProcessTransport(InProcessBus(clock=clock), "ticker")
    ticks = []
    timer = node.timer(0.1, lambda: ticks.append(node.now_ns()))
    assert node.spin_once() == 0
    clock.advance(0.099)
    assert node.spin_once() == 0
    clock.advance(0.001)
    assert node.spin_once() == 1 and ticks == [100_000_000]
    clock.advance(0.35)  # missed periods are skipped, one call per spin
    node.spin_once()
    node.spin_once()
    assert ticks == [100_000_000, 450_000_000]
    clock.advance(0.05)
    node.spin_once()
    assert ticks[-1] == 500_000_000
    timer.cancel()
    clock.advance(1.0)
    assert node.spin_once() == 0


def test_wall_clock_timer_and_spin_until():
    node = InProcessTransport(InProcessBus(), "wall")
    ticks = []
    node.timer(0.01, lambda: ticks.append(1))
    assert node.spin(until=lambda: len(ticks) >= 3, timeout_s=2.0)
    node.close()
    assert node.closed
    with pytest.raises(RuntimeError):
        node.spin_once()


def test_close_unregisters(nodes):
    bus, a, b = nodes
    a.publisher("/chatter", STRING)
    a.service("/svc", TRIGGER, lambda r: None)
    a.close()
    assert bus.topic_type("/chatter") is None and "/svc" not in bus.services
    b.publisher("/chatter", POSE_STAMPED)  # the topic is free again


def test_spin_once_wakes_on_message_from_another_thread():
    import threading

    bus = InProcessBus()
    a, b = InProcessTransport(bus, "a"), InProcessTransport(bus, "b")
    got = []
    b.subscribe("/chatter", STRING, qos.DEFAULT, got.append)
    pub = a.publisher("/chatter", STRING)
    threading.Timer(0.02, lambda: pub.publish(String(data="hi"))).start()
    assert b.spin_once(timeout_s=5.0) == 1
    assert got[0].data == "hi"


def test_use_sim_time_takes_ros_time_from_clock_while_timers_keep_the_bus_clock() -> None:
    from msg_adapters import TYPESTORE, ns_to_stamp
    from t42_transfer.ros import qos as ros_qos

    clock = FakeClock(5_000_000_000)
    bus = InProcessBus(clock=clock)
    sim, node = InProcessTransport(bus, "simulator"), InProcessTransport(bus, "listener")
    assert node.now_ns() == 5_000_000_000
    node.use_sim_time()
    assert node.now_ns() == 0  # no /clock yet, as in ROS
    ticks: list[int] = []
    node.timer(1.0, lambda: ticks.append(node.now_ns()))
    pub = sim.publisher("/clock", "rosgraph_msgs/msg/Clock", ros_qos.CLOCK)
    Clock = TYPESTORE.types["rosgraph_msgs/msg/Clock"]
    pub.publish(Clock(clock=ns_to_stamp(42_000_000_123)))
    clock.advance(1.0)
    node.spin_once()
    assert node.now_ns() == 42_000_000_123 and node.clock_ns() == 6_000_000_000
    assert ticks == [42_000_000_123]  # the timer fired on the bus clock and read ROS time
    pub.publish(Clock(clock=ns_to_stamp(41_000_000_000)))  # an old clock message does not turn time back
    node.spin_once()
    assert node.now_ns() == 42_000_000_123
