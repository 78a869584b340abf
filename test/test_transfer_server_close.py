"""Closing the transfer server (``t42 node`` stopping it) with a Transfer goal accepted whose execution has not
started: its client still gets a result, and nothing is written."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient
from t42_interfaces.action import Transfer
from test_transfer_server import Rig, add_target_bag

from msg_adapters import names

# One executor thread: the test decides when the server's executor runs the goal's execute callback that rclpy
# queues on accepting it (the transfer server spins on several, where that moment is the executor's).
pytestmark = [pytest.mark.usefixtures("one_torch_thread"), pytest.mark.executor_threads(1)]


def _client(rig: Rig) -> tuple[Any, list[Any]]:
    """An action client of the server's, and where the result futures of its goals go: it asks for a goal's
    result once the goal is accepted, as rclpy clients do."""
    client = ActionClient(rig.tester, Transfer, names.TRANSFER)
    assert rig.ros.spin_until(client.server_is_ready, 10.0)
    return client, []


def _send_and_spin_until_accepted(rig: Rig, client: Any, results: list[Any]) -> Any:
    """Send a goal and spin until the server accepted it: that spin queued the goal's execution, which the next
    spin would start (rclpy keeps its goals private).  The goal's future."""
    sent = client.send_goal_async(Transfer.Goal())
    sent.add_done_callback(lambda accepted: results.append(accepted.result().get_result_async()))
    assert rig.ros.spin_until(lambda: rig.server._action._goal_handles, 10.0), "the goal never reached the server"
    assert not sent.done() and not rig.server.busy
    return sent


def _client_got_aborted(rig: Rig, results: list[Any]) -> None:
    """The client's one goal ended ABORTED as a goal a stopping node never started does, and nothing was written."""
    assert rig.ros.spin_until(lambda: bool(results) and results[0].done(), 5.0), \
        "the client of a goal accepted before the node stopped got no result"
    got = results[0].result()
    assert got.status == GoalStatus.STATUS_ABORTED and not got.result.success
    assert got.result.message == "the node is shutting down; send it when it runs"
    assert rig.model_files() == [] and sorted(p.name for p in rig.bag_dir.iterdir()) == ["episode_000"]


def test_a_goal_accepted_but_not_started_when_the_node_stops_is_aborted_and_its_client_gets_the_result(
        ros: Any, tmp_path: Path, source_model: Path) -> None:
    """As ``t42 node`` stops the node: close() from the thread that spins it, then the node is destroyed (nothing
    spins it after close()).  The client asks for the result once the goal is accepted: here while the node
    closes, after the goal has ended."""
    rig = Rig(ros, tmp_path, source_model)
    add_target_bag(rig.bag_dir)
    client, results = _client(rig)
    _send_and_spin_until_accepted(rig, client, results)
    rig.server.close()
    rig.server.destroy_node()  # (t42 node shuts its executor down first; the test's spins on for the client)
    ros.nodes.remove(rig.server)
    _client_got_aborted(rig, results)


def test_a_goal_a_closed_node_accepted_is_answered_before_the_node_is_destroyed(
        ros: Any, tmp_path: Path, source_model: Path) -> None:
    """A closed node that is still spun takes goals (and ends them at once); destroying it answers one accepted
    since close() before the action server goes: its client's result request arrives after close()."""
    rig = Rig(ros, tmp_path, source_model)
    add_target_bag(rig.bag_dir)
    client, results = _client(rig)
    rig.server.close()
    _send_and_spin_until_accepted(rig, client, results)
    rig.server.destroy_node()
    ros.nodes.remove(rig.server)
    _client_got_aborted(rig, results)
