"""The view node (``t42 view``) seen by an independent Foxglove client: channels with ros2msg schemas, the graph's
CDR unchanged, /clock as time, the scene's markers, and a goal published by the client reaching the graph."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np
import pytest
from foxglove_probe import finish_probe, running, start_probe
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path as PathMsg
from rclpy.parameter_client import AsyncParameterClient
from rclpy.serialization import deserialize_message, serialize_message
from ros_rig import REPO, Rosout, RosRig, Tester, stop
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from visualization_msgs.msg import MarkerArray

import msg_adapters as ma
from msg_adapters import names
from msg_adapters.wire import CONTROL_PERIOD_NS
from t42_transfer.nodes.view import View
from t42_transfer.ros.qos import profile

POSE_MM = np.array([4.0, 92.0], np.float32)
GOAL_MM = (12.0, 104.0)
CLIENT_GOAL_MM = (-6.0, 98.0)
T0_NS = 1_000_000_000


def _feed(tester: Tester) -> Any:
    """Publishers of the hand's topics, /clock, a goal and a path; returns a function that publishes step k."""
    node = tester.tester
    pubs = {name: node.create_publisher(cls, name, 10) for name, cls in (
        (names.OBJECT_POSE, PoseStamped), (names.JOINT_STATES, JointState), (names.CLOCK, Clock),
        (names.GOAL, PointStamped), (names.PLANNED_PATH, PathMsg))}
    path = np.column_stack([np.linspace(4, 12, 9), np.linspace(92, 104, 9)]).astype(np.float32)

    def step(k: int) -> None:
        stamp = T0_NS + k * CONTROL_PERIOD_NS
        pubs[names.CLOCK].publish(Clock(clock=ma.ns_to_stamp(stamp, ma.RCLPY)))
        pubs[names.OBJECT_POSE].publish(ma.object_pose_msg(POSE_MM, stamp, ma.RCLPY))
        pubs[names.JOINT_STATES].publish(ma.joint_state_msg(np.array([100.0, 100.0], np.float32),
                                                            np.array([0.36, 0.4], np.float32), stamp, ma.RCLPY))
        if k % 5 == 0:
            pubs[names.GOAL].publish(ma.goal_msg(GOAL_MM, stamp, ma.RCLPY))
            pubs[names.PLANNED_PATH].publish(ma.path_msg(path, stamp, kit=ma.RCLPY))

    return step


def _run_probe(ros: RosRig, step: Any, port: int, **kwargs: Any) -> Any:
    handle = start_probe(f"ws://127.0.0.1:{port}", **kwargs)
    k, deadline = 0, time.monotonic() + 40
    while running(handle) and time.monotonic() < deadline:
        step(k)
        k += 1
        ros.spin_for(0.1)
    return finish_probe(handle)


@pytest.fixture
def view(ros: RosRig) -> View:
    return ros.add(View, {"port": 0, "discovery_period_s": 0.2, "marker_rate_hz": 20.0})


@pytest.mark.parametrize("impl", [None, "python"], ids=["reference_client", "python_websockets"])
def test_a_foxglove_client_gets_the_graph_as_cdr_with_schemas_and_the_markers(ros, view, impl):
    tester = Tester(ros)
    wire_bytes: list[bytes] = []  # the poses' CDR as a raw reader on the graph gets it
    tester.tester.create_subscription(PoseStamped, names.OBJECT_POSE, wire_bytes.append, 100, raw=True)
    step = _feed(tester)
    assert ros.spin_until(lambda: {"/hand/object_pose", "/view/markers"} <= set(view.offered) or step(0), 15)
    assert view.reading == []  # nothing is read for no one
    result = _run_probe(ros, step, view.port, topics=["/hand/object_pose", "/view/markers", "/clock"], count=3,
                        impl=impl)
    assert ros.spin_until(lambda: view.reading == [], 5), view.reading  # the client gone, the readers are too
    print(f"client: {result.impl}")  # which independent client ran (node's @foxglove/ws-protocol, or websockets)
    assert impl is None or result.impl == impl
    assert result.server is not None and {"clientPublish", "time"} <= set(result.server["capabilities"])
    assert "cdr" in result.server.get("supportedEncodings", [])

    pose_channel = result.channel("/hand/object_pose")
    assert pose_channel["encoding"] == "cdr" and pose_channel["schemaEncoding"] == "ros2msg"
    assert pose_channel["schemaName"] == "geometry_msgs/msg/PoseStamped"
    schema = pose_channel["schema"]
    assert schema.startswith("std_msgs/Header header") and "MSG: geometry_msgs/Point" in schema
    assert result.channel("/view/markers")["schemaName"] == "visualization_msgs/msg/MarkerArray"
    assert "MSG: visualization_msgs/Marker" in result.channel("/view/markers")["schema"]

    poses = result.messages["/hand/object_pose"]
    assert len(poses) == 3
    for _, data in poses:
        msg = deserialize_message(data, PoseStamped)
        assert ma.object_xy_mm(msg).tolist() == POSE_MM.tolist()
        assert data in wire_bytes  # the CDR as on the graph, unchanged (padding bytes included)
    markers = deserialize_message(result.messages["/view/markers"][-1][1], MarkerArray)
    drawn = {(m.ns, m.id): m for m in markers.markers[1:]}
    assert {"hand", "object", "goal", "path"} <= {ns for ns, _ in drawn}
    obj, goal = drawn["object", 0].pose.position, drawn["goal", 0].pose.position  # goal 0: its dot
    assert (obj.x, obj.y) == pytest.approx(POSE_MM / 1000)
    assert (goal.x, goal.y) == pytest.approx(np.array(GOAL_MM) / 1000)
    # /clock is the server's time, and messages are logged at it.
    assert result.times and all(t >= T0_NS for t in result.times)
    assert all(T0_NS <= log_time < T0_NS + 10**12 for log_time, _ in poses)


def test_a_client_publishes_a_goal_onto_the_graph_and_nothing_else(ros, view):
    tester = Tester(ros)
    goals = tester.listen(PointStamped, names.GOAL)
    commands = tester.listen(JointState, names.HAND_COMMAND)
    step = _feed(tester)
    goal = ma.goal_msg(CLIENT_GOAL_MM, T0_NS, ma.RCLPY)
    publish = {"topic": "/t42/goal", "schemaName": "geometry_msgs/msg/PointStamped", "data": serialize_message(goal),
               "repeat": 5}
    garbage = dict(publish, data=b"\x00\x01\x00\x00" + (10**9).to_bytes(4, "little") + b"t42_base")
    _run_probe(ros, lambda k: None, view.port, topics=[], count=0, publish=garbage, timeout_s=10)
    ros.spin_for(0.5)
    assert goals == []  # a message that is no PointStamped is not published
    result = _run_probe(ros, lambda k: None, view.port, topics=[], count=0, publish=publish, timeout_s=15)
    assert result.server is not None
    assert ros.spin_until(lambda: any(ma.goal_xy_mm(g).tolist() == list(CLIENT_GOAL_MM) for g in goals), 10)
    # A topic outside client_topics is refused: a viewer may not drive the servos.
    command = ma.joint_state_msg(np.zeros(2, np.float32), np.zeros(2, np.float32), T0_NS, ma.RCLPY)
    refused = {"topic": "/hand/command", "schemaName": "sensor_msgs/msg/JointState",
               "data": serialize_message(command), "repeat": 5}
    _run_probe(ros, step, view.port, topics=[], count=0, publish=refused, timeout_s=10)
    ros.spin_for(0.5)
    assert commands == []
    # An allowed topic in another type: refused with the node's warning (rcl's error bypassed /rosout).
    from std_msgs.msg import String

    log = Rosout(ros, "view")
    retyped = {"topic": "/t42/goal", "schemaName": "std_msgs/msg/String",
               "data": serialize_message(String(data="go")), "repeat": 2}
    _run_probe(ros, step, view.port, topics=[], count=0, publish=retyped, timeout_s=10)
    assert any("as std_msgs/msg/String; the graph's type is geometry_msgs/msg/PointStamped" in w
               for w in log.wait_warnings()), log.warnings()


def test_t42_view_runs_the_node_until_ctrl_c(ros, tmp_path):
    """``--namespace`` as ``t42 up``'s: the view's names and its /clock are the namespace's (a suite per hand keeps
    its own clock there); ``--tolerance`` in mm reaches the node's ``tolerance_m``."""
    log = tmp_path / "view.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-u", "-m", "t42_transfer.cli", "view", "--port", "0",
                                 "--tolerance", "3", "--namespace", "/left"], cwd=REPO, stdout=out,
                                stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 30
        while "Foxglove WebSocket server on ws://127.0.0.1:" not in log.read_text() and time.monotonic() < deadline:
            assert proc.poll() is None, log.read_text()
            time.sleep(0.2)
        assert "[left.view]: Foxglove WebSocket server on ws://127.0.0.1:" in log.read_text()  # its namespace
        graph = ros.node("graph")
        assert ros.spin_until(lambda: graph.count_subscribers("/left/clock") == 1, 10)
        assert graph.count_subscribers("/clock") == 0
        client = AsyncParameterClient(graph, "/left/view")
        assert client.wait_for_services(10)
        future = client.get_parameters(["tolerance_m"])
        assert ros.spin_until(future.done, 10)
        assert future.result().values[0].double_value == pytest.approx(0.003)
    finally:
        codes = stop([proc])
    assert codes == [0], log.read_text()


@pytest.mark.usefixtures("one_torch_thread")
def test_a_goal_published_by_a_client_starts_a_plan_the_client_then_sees(ros, tmp_path):
    from test_planner_node import SMALL, START_XY, Rig, toy_file

    rig = Rig(ros, toy_file(tmp_path / "toy.safetensors"), **SMALL)
    view = ros.add(View, {"port": 0, "discovery_period_s": 0.2})
    rig.tick()
    assert ros.spin_until(lambda: "/t42/planned_path" in view.offered, 10)
    goal = ma.goal_msg(START_XY + np.array([4.0, 4.0], np.float32), 0, ma.RCLPY)  # stamp 0: now
    publish = {"topic": "/t42/goal", "schemaName": "geometry_msgs/msg/PointStamped", "data": serialize_message(goal),
               "repeat": 3, "period_ms": 1000}  # the first a second in: the view's new reader of the path matched
    result = _run_probe(ros, lambda k: None, view.port, topics=["/t42/planned_path"], count=1, publish=publish)
    assert "/t42/planned_path" in result.messages, f"the client saw no plan; the view offered {view.offered}"
    assert ros.spin_until(lambda: rig.trajectories, 10), "the planner sent no trajectory for the client's goal"
    path = deserialize_message(result.messages["/t42/planned_path"][0][1], PathMsg)
    assert any(len(path.poses) == len(t.points) + 1 for t in rig.trajectories)  # a plan's path, start included
    assert ma.path_xy_mm(path)[0] == pytest.approx(START_XY, abs=1e-3)


def _ask(port: int, requests: list[dict], answers: int, timeout_s: float = 20.0) -> list[dict]:
    """Send JSON ``requests`` over the protocol; the first ``answers`` parameterValues replies."""
    from foxglove_probe import SUBPROTOCOLS
    from websockets.sync.client import connect

    got: list[dict] = []
    with connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, max_size=None) as ws:
        deadline = time.monotonic() + timeout_s
        pending = list(requests)
        while len(got) < answers and time.monotonic() < deadline:
            if pending and len(got) == len(requests) - len(pending):
                ws.send(json.dumps(pending.pop(0)))
            try:
                frame = ws.recv(timeout=0.05)
            except TimeoutError:
                continue
            if isinstance(frame, str) and json.loads(frame)["op"] == "parameterValues":
                got.append(json.loads(frame))
    return got


def test_a_client_reads_and_sets_the_nodes_parameters(ros, view):
    other = ros.node("hand_tool", namespace="/left")
    other.declare_parameter("gain", 2.5)
    box: dict[str, Any] = {}
    requests = [{"op": "getParameters", "parameterNames": [], "id": "all"},
                {"op": "setParameters", "parameters": [{"name": "/view.tolerance_m", "value": 1}], "id": "set"},
                {"op": "setParameters", "parameters": [{"name": "/view.tolerance_m", "value": -1.0}], "id": "bad"},
                {"op": "getParameters", "parameterNames": ["/left/hand_tool.gain"], "id": "one"}]
    thread = threading.Thread(target=lambda: box.update(answers=_ask(view.port, requests, 4)), daemon=True)
    thread.start()
    assert ros.spin_until(lambda: not thread.is_alive(), 30)
    every, set_ok, set_bad, one = box["answers"]
    values = {p["name"]: p["value"] for p in every["parameters"]}
    assert values["/view.hand"] == "target" and values["/view.tolerance_m"] == 0.002
    assert values["/left/hand_tool.gain"] == 2.5
    assert view.params.tolerance_m == 1.0  # the whole number 1 taken as the double it is
    assert {p["name"]: p["value"] for p in set_bad["parameters"]} == {"/view.tolerance_m": 1.0}  # refused, kept
    assert one["id"] == "one"
    assert [(p["name"], p["value"]) for p in one["parameters"]] == [("/left/hand_tool.gain", 2.5)]


def _scene_inputs(ros: RosRig, **types: Any) -> tuple[Tester, list, dict[str, Any]]:
    """The test's node, the view's markers as they come, and a publisher per topic (``names`` attribute: type),
    once the view reads them all."""
    tester = Tester(ros)
    markers = tester.listen(MarkerArray, names.VIEW_MARKERS)
    pubs = {name: tester.tester.create_publisher(kind, getattr(names, name), 10) for name, kind in types.items()}
    assert tester.wait_graph(subscribers={getattr(names, name): 1 for name in types},
                             publishers={names.VIEW_MARKERS: 1})
    return tester, markers, pubs


def test_the_planners_refusal_of_the_goal_drawn_turns_it_red(ros, view):
    from t42_interfaces.msg import PlanResult as PlanResultMsg

    from msg_adapters.markers import COLORS
    from msg_adapters.plan_result import PlanResult, plan_result_msg

    tester, markers, pubs = _scene_inputs(ros, GOAL=PointStamped, PLAN_RESULT=PlanResultMsg)
    goal_pub, result_pub = pubs["GOAL"], pubs["PLAN_RESULT"]

    def goal_markers() -> dict[int, Any]:
        return {m.id: m for m in markers[-1].markers if m.ns == "goal"} if markers else {}

    def refusal(goal_mm, status):
        return plan_result_msg(PlanResult(False, status, "why", list(goal_mm), T0_NS), T0_NS, ma.RCLPY)

    goal_pub.publish(ma.goal_msg(GOAL_MM, T0_NS, ma.RCLPY))
    assert ros.spin_until(lambda: 1 in goal_markers(), 5)
    result_pub.publish(refusal((1.0, 2.0), "unreachable"))  # another goal's: not this one
    result_pub.publish(refusal(GOAL_MM, "superseded"))  # replaced, not refused
    ros.spin_for(0.5)
    assert 2 not in goal_markers() and goal_markers()[1].color.r == pytest.approx(COLORS["goal"][0])
    result_pub.publish(refusal(GOAL_MM, "goal_outside_workspace"))
    assert ros.spin_until(lambda: 2 in goal_markers(), 5)
    assert goal_markers()[2].text == "refused: goal_outside_workspace"
    assert goal_markers()[1].color.r == pytest.approx(COLORS["refused"][0])
    goal_pub.publish(ma.goal_msg(CLIENT_GOAL_MM, T0_NS, ma.RCLPY))  # a new goal: not refused (yet)
    assert ros.spin_until(lambda: 2 not in goal_markers() and goal_markers()[0].pose.position.x < 0, 5)
    late = tester.listen(MarkerArray, names.VIEW_MARKERS, profile(names.LATCHED))  # RViz opened now
    assert ros.spin_until(lambda: late, 5), "a viewer that joins late gets the scene (latched)"
    assert late[0] == markers[-1]


def test_a_goal_that_cannot_be_drawn_keeps_the_last_one_and_the_rest_of_the_scene(ros, view):
    """A goal in another frame (the planner refuses it too) once blanked every marker until a good goal came."""
    _, markers, pubs = _scene_inputs(ros, GOAL=PointStamped, OBJECT_POSE=PoseStamped)
    goal_pub, pose_pub = pubs["GOAL"], pubs["OBJECT_POSE"]

    def drawn(ns: str) -> Any:
        return next((m.pose.position for m in markers[-1].markers if (m.ns, m.id) == (ns, 0)), None) \
            if markers else None

    goal_pub.publish(ma.goal_msg(GOAL_MM, T0_NS, ma.RCLPY))
    assert ros.spin_until(lambda: drawn("goal") is not None, 5)
    bad = ma.goal_msg(CLIENT_GOAL_MM, T0_NS, ma.RCLPY)
    bad.header.frame_id = "camera"
    goal_pub.publish(bad)
    ros.spin_for(0.3)
    pose_pub.publish(ma.object_pose_msg([5.0, 90.0], T0_NS, ma.RCLPY))
    assert ros.spin_until(lambda: drawn("object") is not None and drawn("object").x == pytest.approx(0.005), 5)
    assert drawn("goal").x == pytest.approx(GOAL_MM[0] / 1000)  # the last good goal


def test_a_port_in_use_or_a_bad_hand_is_one_line_and_exit_2(ros_domain, tmp_path, small_set):
    import socket

    from ros_rig import assert_one_line_errors

    from t42_transfer.data.bag import write_bag
    from t42_transfer.view.bag_server import BagServer

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert_one_line_errors([(["view", "--ros-args", "-p", f"port:={port}"], f"cannot serve on 127.0.0.1:{port}"),
                                (["view", "--ros-args", "-p", "hand:=no_such_hand"], "no_such_hand")])
        with pytest.raises(ValueError, match=f"cannot serve on 127.0.0.1:{port}"):
            BagServer(write_bag(tmp_path / "bag", small_set), port=port)


def test_the_planners_candidates_are_drawn_when_it_publishes_them(ros, view):
    from t42_interfaces.msg import PlanCandidates

    from msg_adapters.planning import candidates_msg

    tester = Tester(ros)
    markers = tester.listen(MarkerArray, names.VIEW_MARKERS)
    pub = tester.tester.create_publisher(PlanCandidates, names.PLAN_CANDIDATES, 10)
    goal_pub = tester.tester.create_publisher(PointStamped, names.GOAL, 10)
    assert tester.wait_graph(subscribers={names.PLAN_CANDIDATES: 1, names.GOAL: 1},
                             publishers={names.VIEW_MARKERS: 1})

    def drawn() -> list[Any]:
        return [m for m in markers[-1].markers if m.ns == "candidates"] if markers else []

    goal_pub.publish(ma.goal_msg(GOAL_MM, T0_NS, ma.RCLPY))
    assert ros.spin_until(lambda: markers and any(m.ns == "goal" for m in markers[-1].markers), 5)
    assert drawn() == []  # none published: none drawn
    paths = [np.array([[0.0, 80.0], [1.0 + k, 81.0], [2.0 + k, 83.0]], np.float32) for k in range(3)]
    pub.publish(candidates_msg(paths, T0_NS, ma.RCLPY))
    assert ros.spin_until(lambda: len(drawn()) == 3, 5), "the candidates were not drawn"
    for marker, path in zip(sorted(drawn(), key=lambda m: m.id), paths, strict=True):
        assert np.allclose([(p.x, p.y) for p in marker.points], path / 1000)


def test_clients_coming_and_going_on_the_servers_threads_never_stop_the_spin(ros, view):
    """The Foxglove server calls the node on threads of its own: a graph reader destroyed there while the executor
    put its wait set together stopped the spin with InvalidHandle (seen once in a fast-suite run)."""
    step = _feed(Tester(ros))
    topic = "/hand/object_pose"
    assert ros.spin_until(lambda: topic in view.offered or step(0), 15)
    churned, failed = threading.Event(), []

    def churn() -> None:
        try:
            for _ in range(400):
                view.client_subscribed(7, topic)
                view.client_unsubscribed(7, topic)
        except Exception as err:  # said below, not left to hang the loop
            failed.append(err)
        finally:
            churned.set()

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # the threads interleave as on a busy machine
    try:
        threading.Thread(target=churn, daemon=True).start()
        k, deadline = 0, time.monotonic() + 60.0
        while not churned.is_set() and time.monotonic() < deadline:
            step(k)
            k += 1
            ros.spin_for(0.002)
    finally:
        sys.setswitchinterval(switch)
    assert churned.is_set() and not failed, failed
    readers = lambda: [s for s in view.subscriptions if s.topic_name == topic]  # noqa: E731
    assert ros.spin_until(lambda: len(readers()) == 1, 5), readers()  # the markers' own: no reader left behind
    assert view.reading == [] and k > 10


def test_a_client_back_before_its_reader_was_destroyed_reads_on_with_it(ros, view):
    """Unsubscribed and subscribed again before the executor's turn: one graph reader, not a second beside the
    first (each message would reach the channel twice)."""
    step = _feed(Tester(ros))
    topic = "/hand/object_pose"
    assert ros.spin_until(lambda: topic in view.offered or step(0), 15)
    readers = lambda: [s for s in view.subscriptions if s.topic_name == topic]  # noqa: E731
    view.client_subscribed(7, topic)
    view.client_unsubscribed(7, topic)
    view.client_subscribed(8, topic)
    assert len(readers()) == 2, readers()  # the markers' own and the client's
    ros.spin_for(0.3)
    assert len(readers()) == 2 and view.reading == [topic], readers()
    view.client_unsubscribed(8, topic)
    assert ros.spin_until(lambda: len(readers()) == 1, 5), readers()
