"""A node whose construction failed leaves the graph at once, and takes nothing from a later node of its name."""

from __future__ import annotations

import dataclasses
import gc
from typing import Any

import pytest
from rclpy.parameter import Parameter
from ros_rig import Rosout

from t42_transfer.nodes.registry import NODES


def first_parameter(node_cls: type) -> str:
    return dataclasses.fields(node_cls.params_class)[0].name


@pytest.mark.parametrize("name", sorted(NODES))
def test_a_node_refused_at_construction_is_gone_from_the_graph_at_once(ros: Any, name: str) -> None:
    node_cls = NODES[name].node_class()
    tester = ros.node("tester")
    with pytest.raises(Exception):  # noqa: B017,PT011 (each node refuses in its own words)
        ros.add(node_cls, {first_parameter(node_cls): ["not", "a", "setting"]})
    assert name not in tester.get_node_names(), tester.get_node_names()


def test_a_bag_player_refused_for_a_missing_bag_is_gone_from_the_graph_at_once(ros: Any, tmp_path: Any) -> None:
    from t42_transfer.nodes.player import BagPlayer

    tester = ros.node("tester")
    with pytest.raises(Exception, match="does not exist"):  # noqa: PT011 (the bag reader's own error)
        ros.add(BagPlayer, {"bag": str(tmp_path / "missing")})
    assert "bag_player" not in tester.get_node_names() and len(tester.get_node_names()) == 1


def test_a_node_of_the_same_name_keeps_its_rosout_lines_after_the_refused_one_is_collected(ros: Any) -> None:
    """The camera is a lifecycle node: its state machine refers back to it, so only the garbage collector
    finalizes a refused one, at a moment of its own (here: at once, when asked)."""
    from t42_transfer.nodes.camera import Camera

    with pytest.raises(ValueError, match="fps"):
        ros.add(Camera, {"fps": -1.0, "autostart": False})
    camera = ros.add(Camera, {"autostart": False})
    log = Rosout(ros, "camera")
    ros.spin_for(0.5)
    gc.collect()
    camera.get_logger().warning("said after the collection")
    assert log.wait_warnings(1) == ["said after the collection"]


@pytest.mark.parametrize("node_name", ["camera", "dynamixel_driver"])
def test_a_destroyed_lifecycle_node_leaves_the_graph_and_a_later_one_keeps_its_rosout_lines(ros: Any,
                                                                                         node_name: str) -> None:
    """rclpy's own LifecycleNode stayed on the graph after ``destroy_node`` until the garbage collector ran, and
    then silenced the next node of its name on /rosout: two tests lost a driver's and a camera's lines so."""
    node_cls = NODES[node_name].node_class()
    params = {"autostart": False} if node_name == "camera" else {"port": "/dev/null/no_bus"}
    tester = ros.node("tester")
    first = node_cls(context=ros.context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    first.destroy_node()
    assert node_name not in tester.get_node_names()
    second = ros.add(node_cls, params)
    log = Rosout(ros, node_name)
    ros.spin_for(0.5)
    del first
    gc.collect()
    second.get_logger().warning("said after the collection")
    assert log.wait_warnings(1) == ["said after the collection"]


@pytest.mark.parametrize("node_name", ["camera", "dynamixel_driver"])
def test_a_transition_not_valid_in_the_state_is_answered_false_and_the_node_goes_on(ros: Any, node_name: str) -> None:
    """rclpy raised rcl's "Transition is not registered" out of ``change_state`` for, say, activate while
    unconfigured (configure while active); the runner takes that for a bug and ended the process (a driver then
    dropped the object).  Now: ``success: false``, a warning naming the valid transitions, the state unchanged."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState

    params = {"autostart": False} if node_name == "camera" else {"port": "/dev/null/no_bus"}
    ros.add(NODES[node_name].node_class(), params)
    log = Rosout(ros, node_name)
    tester = ros.node("tester")
    change = tester.create_client(ChangeState, f"{node_name}/change_state")
    get = tester.create_client(GetState, f"{node_name}/get_state")
    for transition in (Transition(id=Transition.TRANSITION_ACTIVATE), Transition(id=99),
                       Transition(label="activate")):
        assert ros.call(change, ChangeState.Request(transition=transition)).success is False
        assert ros.call(get, GetState.Request()).current_state.label == "unconfigured"
    said = log.wait_warnings(2)
    assert any("not valid in state 'unconfigured'" in line and "configure (id 1)" in line for line in said), said
