"""``t42 lifecycle``, ``t42 call``, ``t42 param``, ``t42 reach`` as processes against stock nodes and servers on
the test's own graph: what a user of the pip-installed ROS (no ``ros2`` command) drives the suite with."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import pytest
import yaml
from rclpy.lifecycle import LifecycleNode
from std_srvs.srv import SetBool, Trigger

from t42_transfer.cli.graph import ASK_AGAIN_S
from t42_transfer.nodes.dynamixel_driver import DynamixelDriver


def t42(ros: Any, *argv: str, timeout_s: float = 60.0) -> tuple[int, str, str]:
    """Run ``t42 *argv`` while this process's nodes spin; (exit code, stdout, stderr)."""
    return t42_all(ros, list(argv), timeout_s=timeout_s)[0]


def t42_all(ros: Any, *argvs: list[str], timeout_s: float = 60.0) -> list[tuple[int, str, str]]:
    """Run every ``t42 *argv`` at once (their starts overlap on two cores) while this process's nodes spin."""
    procs = [subprocess.Popen([sys.executable, "-m", "t42_transfer.cli", *argv], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for argv in argvs]
    try:
        assert ros.spin_until(lambda: all(p.poll() is not None for p in procs), timeout_s), argvs
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
    return [(proc.returncode, *proc.communicate()) for proc in procs]


def test_lifecycle_gets_the_state_and_makes_transitions_by_name(ros: Any) -> None:
    ros.add(LifecycleNode, node_name="hand_like")
    ros.node("plain")  # a running node that is no lifecycle node: said so, without waiting out --wait
    plain = t42_started("lifecycle", "/plain", "--wait", "60")  # beside the transitions below
    assert t42(ros, "lifecycle", "hand_like")[:2] == (0, "/hand_like: unconfigured\n")
    assert t42(ros, "lifecycle", "/hand_like", "configure")[:2] == (0, "/hand_like: configure done; now inactive\n")
    assert t42(ros, "lifecycle", "/hand_like", "activate")[:2] == (0, "/hand_like: activate done; now active\n")
    code, _, err = t42(ros, "lifecycle", "/hand_like", "configure")  # not from active
    assert code == 2 and "cannot configure from its state now; it can: deactivate, shutdown" in err, err
    assert t42(ros, "lifecycle", "/hand_like", "shutdown")[:2] == (0, "/hand_like: shutdown done; now finalized\n")
    assert ros.spin_until(lambda: plain.poll() is not None, 60.0)
    out, err = plain.communicate()
    assert plain.returncode == 2 and out == "" and err == ("t42: error: /plain/get_state: /plain runs but has no "
                                                           "such service (a GetState service)\n"), err


def test_call_a_trigger_service_and_a_service_that_is_not_there(ros: Any) -> None:
    def answer(_: Any, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = True, "grasped"
        return response

    asked: list[bool] = []

    def switch(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        asked.append(request.data)
        response.success, response.message = request.data, f"torque {'on' if request.data else 'off'}"
        return response

    server = ros.node("server")
    server.create_service(Trigger, "/hand/reset", answer)
    server.create_service(SetBool, "/hand/torque", switch)
    assert t42(ros, "call", "/hand/reset")[:2] == (0, "/hand/reset: success: grasped\n")
    code, out, err = t42(ros, "call", "/t42/transfer_now", "--wait", "1")
    assert code == 2 and out == "", (out, err)
    assert "/t42/transfer_now: no such service on the graph after 1 s (ROS_DOMAIN_ID" in err, err
    # any service type, as ros2 service call: the request's fields as YAML, the type given or the graph's
    assert t42(ros, "call", "/hand/torque", "{data: true}")[:2] == (0, "/hand/torque: success: torque on\n")
    assert t42(ros, "call", "hand/torque", "std_srvs/srv/SetBool")[:2] == (1, "hand/torque: failure: torque off\n")
    assert asked == [True, False]
    code, out, _ = t42(ros, "call", "/server/list_parameters", "{depth: 0}")  # no success field: the answer as YAML
    assert code == 0 and "use_sim_time" in yaml.safe_load(out)["result"]["names"], out
    code, out, err = t42(ros, "call", "/hand/reset", "std_srvs/SetBool", "{data: true}")
    assert (code, out, err) == (2, "", "t42: error: /hand/reset: a std_srvs/srv/Trigger service, not a "
                                       "std_srvs/srv/SetBool\n")
    code, _, err = t42(ros, "call", "/hand/torque", "std_srvs/srv/SetBool", "{data: 1}")  # refused before the graph
    assert code == 2 and err == "t42: error: request.data: 1 is no boolean\n", err
    assert asked == [True, False]


def test_param_sets_and_gets_the_drivers_parameters_as_ros2_param_does(ros: Any) -> None:
    """A list of floats (as the README's max_angle_rad), a scalar, a refusal with the node's reason."""
    driver = ros.add(DynamixelDriver, {"port": "/dev/null/no_bus"})  # unconfigured: parameters only
    assert t42(ros, "param", "/dynamixel_driver", "max_angle_rad", "[2.5, 2.0]")[:2] == \
        (0, "/dynamixel_driver max_angle_rad: set\n")
    assert driver.params.max_angle_rad == (2.5, 2.0)
    assert t42(ros, "param", "dynamixel_driver", "load_limit", "250.0")[0] == 0 and driver.params.load_limit == 250.0
    # whole numbers for doubles, as a user types them (rclpy itself would refuse an integer for a double)
    assert t42(ros, "param", "/dynamixel_driver", "grasp_load", "90")[0] == 0 and driver.params.grasp_load == 90.0
    assert t42(ros, "param", "/dynamixel_driver", "max_angle_rad", "[2, 2.5]")[0] == 0
    assert driver.params.max_angle_rad == (2.0, 2.5)
    code, out, _ = t42(ros, "param", "/dynamixel_driver", "max_angle_rad", "[]")  # typed as declared, not bytes
    assert code == 1 and "refused" in out and "one per actuator" in out and "BYTE_ARRAY" not in out, out
    code, out, _ = t42(ros, "param", "/dynamixel_driver", "grasp_load", "true")  # no number: refused as before
    assert code == 1 and "refused" in out and driver.params.grasp_load == 90.0, out
    assert t42(ros, "param", "/dynamixel_driver", "load_limit")[:2] == (0, "/dynamixel_driver load_limit: 250.0\n")
    code, out, _ = t42(ros, "param", "/dynamixel_driver")  # every parameter, sorted, with its value
    listed = dict(line.split(": ", 1) for line in out.splitlines())
    assert code == 0 and list(listed) == sorted(listed) and listed["load_limit"] == "250.0", out
    assert {f.name for f in dataclasses.fields(driver.params)} <= set(listed) and "use_sim_time" in listed
    code, out, _ = t42(ros, "param", "/dynamixel_driver", "grasp_load", "400.0")
    assert code == 1 and "refused: grasp_load must be below load_limit" in out, out
    assert driver.params.grasp_load == 90.0


def test_a_read_whose_answer_is_lost_is_asked_again_and_a_call_is_not(ros: Any) -> None:
    """A server that never answers a first request, as rmw_fastrtps drops its reply to a client whose reply
    subscription it has not matched yet: ``t42 param`` and ``t42 lifecycle`` ask again and take the next answer;
    ``t42 call`` (a request that may act) sends it once."""
    from lifecycle_msgs.msg import State
    from lifecycle_msgs.srv import GetState
    from rcl_interfaces.msg import ParameterType, ParameterValue
    from rcl_interfaces.srv import GetParameters

    from t42_transfer.ros.deferred_service import DeferredService

    asked: dict[str, int] = {}

    def first_lost(kind: str, answer: Callable[[Any], Any]) -> Callable[[Any, Any], Any]:
        def callback(_: Any, response: Any) -> Any:
            asked[kind] = asked.get(kind, 0) + 1
            return services[kind].later() if asked[kind] == 1 else answer(response)  # the first: never answered
        return callback

    def values(response: Any) -> Any:
        response.values = [ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=2.5)]
        return response

    def state(response: Any) -> Any:
        response.current_state = State(id=State.PRIMARY_STATE_INACTIVE, label="inactive")
        return response

    def done(response: Any) -> Any:
        response.success, response.message = True, "done"
        return response

    node = ros.node("quiet", start_parameter_services=False)
    services = {kind: DeferredService(node, srv, f"/quiet/{kind}", first_lost(kind, answer))
                for kind, srv, answer in (("get_parameters", GetParameters, values), ("get_state", GetState, state),
                                          ("work", Trigger, done))}
    call = t42_started("call", "/quiet/work")  # beside the reads
    assert ros.spin_until(lambda: "work" in asked, 30.0)
    first_asked = time.monotonic()
    assert t42(ros, "param", "/quiet", "rate_factor")[:2] == (0, "/quiet rate_factor: 2.5\n")
    assert t42(ros, "lifecycle", "/quiet")[:2] == (0, "/quiet: inactive\n")
    ros.spin_until(lambda: call.poll() is not None, 3 * ASK_AGAIN_S - (time.monotonic() - first_asked))
    assert call.poll() is None, call.communicate()  # still waiting for its one request's answer
    call.kill()
    call.communicate()
    # (a busy machine may lose a second reply as well: each read is asked again until it is answered)
    assert asked["get_parameters"] >= 2 and asked["get_state"] >= 2 and asked["work"] == 1, asked


def test_ctrl_c_while_waiting_for_an_answer_is_one_line_and_exit_130(ros: Any) -> None:
    """A transfer answers after minutes: a user who stops waiting gets no traceback."""
    import signal

    from t42_transfer.ros.deferred_service import DeferredService

    called: list[Any] = []

    def later(_: Any, response: Any) -> Any:  # the answer held back, as a long transfer holds it
        called.append(service.later())
        return called[-1]

    service = DeferredService(ros.node("slow_server"), Trigger, "/t42/transfer_now", later)
    proc = subprocess.Popen([sys.executable, "-m", "t42_transfer.cli", "call", "/t42/transfer_now"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert ros.spin_until(lambda: called, 30.0)
    proc.send_signal(signal.SIGINT)
    assert ros.spin_until(lambda: proc.poll() is not None, 30.0)
    out, err = proc.communicate()
    assert proc.returncode == 130 and out == "", (out, err)
    assert err == "t42: interrupted: stopped waiting for the answer (the node still carries the request out)\n", err


def test_call_says_a_missing_service_and_a_server_that_leaves_mid_call_in_one_line(ros: Any) -> None:
    from t42_transfer.ros.deferred_service import DeferredService

    called: list[Any] = []

    def later(_: Any, response: Any) -> Any:  # never answered: the server leaves first
        called.append(service.later())
        return called[-1]

    node = ros.node("leaving_server")
    service = DeferredService(node, Trigger, "/leaving_server/work", later)
    missing = t42_started("call", "/leaving_server/nope", "--wait", "60")  # said after a few seconds, not 60
    proc = t42_started("call", "/leaving_server/work")
    assert ros.spin_until(lambda: called, 30.0)
    node.destroy_service(service.service)
    assert ros.spin_until(lambda: proc.poll() is not None and missing.poll() is not None, 30.0)
    out, err = proc.communicate()
    assert (proc.returncode, out) == (2, "") and err == ("t42: error: /leaving_server/work: the service left the "
                                                         "graph before it answered\n"), err
    assert (missing.returncode, missing.communicate()[1]) == (
        2, "t42: error: /leaving_server/nope: /leaving_server runs but has no such service\n")


@pytest.mark.parametrize(("typed", "said"), [
    (["std_srvs/srv/Trig-ger"], "std_srvs/srv/Trig-ger: no such service type"),  # a type, misspelt: no YAML
    (["t42_interfaces/action/Reach_SendGoal", "{}"], "an action's own service; t42 call takes services"),
])
def test_call_refuses_a_type_it_cannot_call_before_joining_the_graph(typed: list[str], said: str,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    from t42_transfer.cli import main

    assert main(["call", "/some/service", *typed, "--wait", "1"]) == 2
    assert said in capsys.readouterr().err


def reach_server(ros: Any, name: str, **callbacks: Any) -> Any:
    """A stock t42/reach ActionServer on its own node (a planner's stand-in for what a planner may do)."""
    from rclpy.action import ActionServer
    from t42_interfaces.action import Reach

    node = ros.node(name)
    return node, ActionServer(node, Reach, "/t42/reach", **callbacks)


def t42_started(*argv: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "t42_transfer.cli", *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def said_when_interrupted(proc: subprocess.Popen) -> tuple[str, str]:
    """What a command still running says once interrupted (where it waited), for a failure's message."""
    import signal

    proc.send_signal(signal.SIGINT)
    try:
        return proc.communicate(timeout=10.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.communicate()


def test_ctrl_c_while_the_planner_has_not_answered_the_goal_still_cancels_it(ros: Any) -> None:
    """The goal's answer comes after the Ctrl-C: the command waits for it, then cancels the goal."""
    import signal
    import time

    from rclpy.action import CancelResponse, GoalResponse

    proc: list[subprocess.Popen] = []
    held: list[Any] = []
    cancelled: list[Any] = []

    def slow_answer(_: Any) -> GoalResponse:  # the user presses Ctrl-C while the planner decides
        proc[0].send_signal(signal.SIGINT)
        time.sleep(1.0)
        return GoalResponse.ACCEPT

    reach_server(ros, "slow_planner", execute_callback=lambda handle: None, goal_callback=slow_answer,
                 handle_accepted_callback=held.append,  # accepted, never run: it runs until cancelled
                 cancel_callback=lambda handle: cancelled.append(handle) or CancelResponse.ACCEPT)
    proc.append(t42_started("reach", "0.0", "0.07"))
    assert ros.spin_until(lambda: proc[0].poll() is not None, 60.0)
    out, err = proc[0].communicate()
    assert proc[0].returncode == 130 and out == "", (out, err)
    assert err == "t42: interrupted: goal cancelled (the hand holds from its next step)\n", err
    assert len(held) == 1 and len(cancelled) == 1


def test_a_planner_that_leaves_mid_goal_or_fails_without_a_result_ends_the_wait_with_one_line(ros: Any) -> None:
    held: list[Any] = []
    node, server = reach_server(ros, "leaving_planner", execute_callback=lambda handle: None,
                                handle_accepted_callback=held.append)
    proc = t42_started("reach", "0.0", "0.07")
    assert ros.spin_until(lambda: held, 60.0), f"no goal came: {said_when_interrupted(proc)}"
    ros.spin_for(1.0)  # the goal's answer on its way to the command
    server.destroy()  # the planner's process ends with the goal under way
    ros.executor.remove_node(node)
    node.destroy_node()
    if not ros.spin_until(lambda: proc.poll() is not None, 30.0):
        looker = ros.node("looker")
        raise AssertionError(f"still waiting on a planner that is gone (nodes on the graph: {looker.get_node_names()}"
                             f"): {said_when_interrupted(proc)}")
    out, err = proc.communicate()
    assert proc.returncode == 2 and err.count("\n") == 1, (out, err)
    assert "/t42/reach: the action server left the graph before the goal's result" in err, err

    def fails(handle: Any) -> Any:
        raise RuntimeError("the model file vanished")  # rclpy aborts it and sends an empty result

    reach_server(ros, "failing_planner", execute_callback=fails)
    code, out, err = t42(ros, "reach", "0.0", "0.07")
    assert code == 1 and out == "/t42/reach: the goal ended aborted without a result (the planner's log says why)\n", \
        (out, err)


class _FirstLost:
    """rclpy's action server handle that loses the first of one kind of message, ``method``: a goal request
    (``take_goal_request``), its answer (``send_goal_response``) or a result request (``take_result_request``), as
    Fast DDS drops one between a client and a server not yet matched to it; everything else goes through."""

    def __init__(self, handle: Any, method: str) -> None:
        self._handle, self._method, self.lost = handle, method, 0

    def __getattr__(self, name: str) -> Any:
        real = getattr(self._handle, name)
        if name != self._method or self.lost:
            return real

        def lose(*args: Any) -> Any:
            self.lost += 1
            if name.startswith("take"):
                real(*args)  # taken off the wire, and dropped
                return None, None  # what rclpy's take gives when there was nothing
            return None

        return lose

    def __enter__(self) -> Any:
        return self._handle.__enter__()

    def __exit__(self, *exc: Any) -> Any:
        return self._handle.__exit__(*exc)


def executes_once(node: Any, runs: list[Any]) -> Callable[[Any], Any]:
    """A planner's execute callback: one feedback, then a hit; each goal it runs is added to ``runs``.  The feedback
    waits (up to 10 s) for the command's feedback subscription to show on the graph of ``node`` (of the server's
    process, whose graph the server's is): published
    before the server has matched it, it is lost (the README says so of an action client made just before its goal)."""
    import numpy as np

    from msg_adapters.reach import reach_feedback, reach_result

    def execute(handle: Any) -> Any:
        runs.append(handle)
        deadline = time.monotonic() + 10.0
        while not node.count_subscribers("/t42/reach/_action/feedback") and time.monotonic() < deadline:
            time.sleep(0.05)
        handle.publish_feedback(reach_feedback(1, 3.0, 1.0))
        handle.succeed()
        path = np.array([[0.0, 70.0], [0.5, 70.5]])
        return reach_result("hit", "hit", 1.0, path, 0, path, 0)

    return execute


@pytest.mark.parametrize("lost", ["send_goal_response", "take_goal_request", "take_result_request"])
def test_a_goal_whose_request_answer_or_result_request_is_lost_still_runs_once_to_its_result(ros: Any,
                                                                                           lost: str) -> None:
    """A lost answer: the goal's status stands for it; a lost goal: it goes again with its id; a lost result
    request: asked again once the status says the goal ended."""
    runs: list[Any] = []
    _, server = reach_server(ros, "quiet_planner", execute_callback=executes_once(ros.node("seer"), runs))
    server._handle = _FirstLost(server._handle, lost)
    code, out, err = t42(ros, "reach", "0.0", "0.07")
    assert server._handle.lost == 1 and code == 0 and len(runs) == 1, (out, err)
    assert out.splitlines()[0].startswith("step 1: 3.0 mm from the target") and "hit" in out.splitlines()[-1], out


def test_a_goal_whose_rejection_is_lost_is_not_taken_for_accepted(ros: Any) -> None:
    from rclpy.action import GoalResponse

    _, server = reach_server(ros, "refusing_planner", goal_callback=lambda request: GoalResponse.REJECT,
                             execute_callback=lambda handle: None)
    server._handle = _FirstLost(server._handle, "send_goal_response")
    for lost in (1, 0):  # its copy refused, and no goal on the server's status; then a plain no
        code, out, err = t42(ros, "reach", "0.0", "0.07", "--wait", "1")
        assert server._handle.lost == 1 and code == 1, (out, err)
        assert out.strip() == "/t42/reach: goal rejected (the planner logs why)", (lost, out, err)


def test_a_slow_no_then_a_yes_to_the_goal_sent_again_follows_the_goal_that_runs(ros: Any) -> None:
    """A server that says no after 4 s, then yes: the copy sent meanwhile is accepted and runs, so it is followed."""
    from rclpy.action import GoalResponse

    answers: list[GoalResponse] = []
    runs: list[Any] = []

    def slow_no_then_yes(_: Any) -> GoalResponse:
        if not answers:
            time.sleep(4.0)
        answers.append(GoalResponse.ACCEPT if answers else GoalResponse.REJECT)
        return answers[-1]

    reach_server(ros, "moody_planner", goal_callback=slow_no_then_yes,
                 execute_callback=executes_once(ros.node("seer"), runs))
    code, out, err = t42(ros, "reach", "0.0", "0.07")
    assert answers == [GoalResponse.REJECT, GoalResponse.ACCEPT] and len(runs) == 1, (answers, out, err)
    assert code == 0 and "hit" in out.splitlines()[-1], (out, err)


def test_a_goal_unanswered_within_the_wait_is_cancelled_by_its_id(ros: Any) -> None:
    """The server answers after the command gave up: the goal would run unwatched, so the command cancels it."""
    from rclpy.action import CancelResponse, GoalResponse

    held: list[Any] = []
    cancelled: list[Any] = []

    def slow_yes(_: Any) -> GoalResponse:  # past the command's wait: its 3 s for the server, 3 s more for the answer
        time.sleep(8.0)
        return GoalResponse.ACCEPT

    reach_server(ros, "slow_planner", goal_callback=slow_yes, execute_callback=lambda handle: None,
                 handle_accepted_callback=held.append,
                 cancel_callback=lambda handle: cancelled.append(handle) or CancelResponse.ACCEPT)
    code, out, err = t42(ros, "reach", "0.0", "0.07", "--wait", "3")
    assert code == 2 and out == "" and len(held) == 1 and len(cancelled) == 1, (out, err)
    assert err == ("t42: error: /t42/reach: no answer to the goal after 6 s, nor the goal among the server's (its "
                   "requests lost?); goal cancelled (the hand holds from its next step)\n"), err


@pytest.mark.parametrize("argv, bad", [
    (["call", "bad name", "std_srvs/srv/Trigger"], "bad name"),
    (["param", "bad node"], "bad node"),
    (["lifecycle", "bad node"], "bad node"),
    (["lifecycle", "/left/"], "/left/"),
    (["reach", "0.0", "0.07", "--action", "t42/1reach"], "t42/1reach"),
])
def test_a_name_ros_refuses_is_one_line_and_exit_2(argv: list[str], bad: str, ros_domain: int,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """rclpy raises its own exceptions, no ValueError, for such a name at the first client: a traceback before."""
    from t42_transfer.cli import main

    assert main([*argv, "--wait", "1"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.startswith(f"t42: error: {bad!r}: not a valid ROS name ("), captured
    assert captured.err.count("\n") == 1, captured.err
