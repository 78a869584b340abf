"""``t42 lifecycle``, ``t42 call``, ``t42 param`` as processes against nodes on the test's own graph: what a user of
the pip-installed ROS (no ``ros2`` command) drives the suite with."""

from __future__ import annotations

import subprocess
import sys
from typing import Any

from rclpy.lifecycle import LifecycleNode
from std_srvs.srv import Trigger

from t42_transfer.nodes.dynamixel_driver import DynamixelDriver


def t42(ros: Any, *argv: str, timeout_s: float = 60.0) -> tuple[int, str, str]:
    """Run ``t42 *argv`` while this process's nodes spin; (exit code, stdout, stderr)."""
    proc = subprocess.Popen([sys.executable, "-m", "t42_transfer.cli", *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    assert ros.spin_until(lambda: proc.poll() is not None, timeout_s), argv
    out, err = proc.communicate()
    return proc.returncode, out, err


def test_lifecycle_gets_the_state_and_makes_transitions_by_name(ros: Any) -> None:
    ros.add(LifecycleNode, node_name="hand_like")
    assert t42(ros, "lifecycle", "hand_like")[:2] == (0, "/hand_like: unconfigured\n")
    assert t42(ros, "lifecycle", "/hand_like", "configure")[:2] == (0, "/hand_like: configure done; now inactive\n")
    assert t42(ros, "lifecycle", "/hand_like", "activate")[:2] == (0, "/hand_like: activate done; now active\n")
    code, _, err = t42(ros, "lifecycle", "/hand_like", "configure")  # not from active
    assert code == 2 and "cannot configure from its state now; it can: deactivate, shutdown" in err, err
    assert t42(ros, "lifecycle", "/hand_like", "shutdown")[:2] == (0, "/hand_like: shutdown done; now finalized\n")


def test_call_a_trigger_service_and_a_service_that_is_not_there(ros: Any) -> None:
    def answer(_: Any, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = True, "grasped"
        return response

    ros.node("server").create_service(Trigger, "/hand/reset", answer)
    assert t42(ros, "call", "/hand/reset")[:2] == (0, "/hand/reset: success: grasped\n")
    code, out, err = t42(ros, "call", "/t42/transfer_now", "--wait", "1")
    assert code == 2 and out == "", (out, err)
    assert "/t42/transfer_now: no such service on the graph after 1 s (a Trigger service" in err, err


def test_param_sets_and_gets_the_drivers_parameters_as_ros2_param_does(ros: Any) -> None:
    """A list of floats (as the README's max_angle_rad), a scalar, a refusal with the node's reason."""
    driver = ros.add(DynamixelDriver, {"port": "/dev/null/no_bus"})  # unconfigured: parameters only
    assert t42(ros, "param", "/dynamixel_driver", "max_angle_rad", "[2.5, 2.0]")[:2] == \
        (0, "/dynamixel_driver max_angle_rad: set\n")
    assert driver.params.max_angle_rad == (2.5, 2.0)
    assert t42(ros, "param", "dynamixel_driver", "load_limit", "250.0")[0] == 0 and driver.params.load_limit == 250.0
    assert t42(ros, "param", "/dynamixel_driver", "load_limit")[:2] == (0, "/dynamixel_driver load_limit: 250.0\n")
    code, out, _ = t42(ros, "param", "/dynamixel_driver", "grasp_load", "400.0")
    assert code == 1 and "refused: grasp_load must be below load_limit" in out, out
    assert driver.params.grasp_load == 100.0


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
