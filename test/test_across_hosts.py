"""Across machines: driver and recorder on one host, transfer server and planner on another.

The two hosts are network namespaces made by the test (``ip netns``, as root) and
joined by a veth pair whose /30 addresses exist only between them; each namespace
has nothing else but its loopback, so no traffic can reach any other address.  Discovery
is SUBNET (ROS's default range) on both sides, and data goes over UDP only.  A plain rclpy script on the second
host drives the story: it sees all four nodes, sets parameters, reads /rosout and the
hand state, resets the hand, then (after the explorer on the first host recorded its
episodes) calls the transfer and sends a goal whose trajectory the driver executes.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from ros_rig import REPO, stop, unbuffered_env
from test_stock_graph import STOCK_USER, T42, suite_file

ADDRESSES = ("10.242.77.1/30", "10.242.77.2/30")


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=30)


def _can_make_namespaces() -> str | None:
    """None when this machine lets the test make network namespaces, else why not."""
    if shutil.which("ip") is None:
        return "the ip command (iproute2) is not installed"
    if os.geteuid() != 0:
        return "making network namespaces needs root"
    probe = f"t42probe{uuid.uuid4().hex[:6]}"
    try:
        _ip("netns", "add", probe)
    except (subprocess.CalledProcessError, OSError) as err:
        return f"ip netns add failed: {getattr(err, 'stderr', err)}".strip()
    _ip("netns", "del", probe)
    return None


@pytest.fixture
def two_hosts(ros_domain: int) -> Iterator[tuple[str, str]]:
    """Two network namespaces joined by a veth pair (and nothing else), removed afterwards."""
    why = _can_make_namespaces()
    if why is not None:
        pytest.skip(why)
    tag = uuid.uuid4().hex[:6]
    hosts = (f"t42a{tag}", f"t42b{tag}")
    links = (f"t42a{tag}0", f"t42b{tag}0")
    made: list[str] = []
    try:
        for host in hosts:
            _ip("netns", "add", host)
            made.append(host)
        _ip("link", "add", links[0], "type", "veth", "peer", "name", links[1])
        for host, link, address in zip(hosts, links, ADDRESSES, strict=True):
            _ip("link", "set", link, "netns", host)
            _ip("-n", host, "addr", "add", address, "dev", link)
            _ip("-n", host, "link", "set", "lo", "up")
            _ip("-n", host, "link", "set", link, "up", "multicast", "on")
            _ip("-n", host, "route", "add", "224.0.0.0/4", "dev", link)  # discovery multicast over the link
        yield hosts
    finally:
        for host in made:
            subprocess.run(["ip", "netns", "del", host], capture_output=True, timeout=30)


def _env() -> dict[str, str]:
    # UDP only: Fast DDS would otherwise move data between the "hosts" through shared memory (/dev/shm is
    # common to both namespaces); this way every byte crosses the veth link, as between two machines.
    return unbuffered_env(ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET", FASTDDS_BUILTIN_TRANSPORTS="UDPv4")


def _on(host: str, cmd: list[str], log: Path) -> subprocess.Popen:
    with log.open("w") as out:
        return subprocess.Popen(["ip", "netns", "exec", host, *cmd], cwd=REPO, env=_env(), stdout=out,
                                stderr=subprocess.STDOUT)


def _stock_user(host: str, mode: str, log: Path) -> dict:
    import json

    proc = subprocess.run(["ip", "netns", "exec", host, sys.executable, str(STOCK_USER), mode],
                          cwd=STOCK_USER.parent, env=dict(_env(), PYTHONPATH=""), capture_output=True, text=True,
                          timeout=600)
    log.write_text(proc.stdout + proc.stderr)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    assert lines and proc.returncode == 0, proc.stdout + proc.stderr
    return json.loads(lines[-1])


# Slow suite (CI runs it): 16 s on a quiet 2-core machine, the default suite's largest check after the demos; the
# same nodes and the same stock script on one host are in the default suite (test_stock_graph).
@pytest.mark.slow
def test_the_story_across_two_hosts(two_hosts: tuple[str, str], tmp_path: Path, source_model: Path) -> None:
    robot, server = two_hosts
    params = suite_file(tmp_path, source_model)
    hand = _on(robot, [*T42, "up", str(params), "--only", "mock_driver,recorder", "--stop-timeout", "10"],
               tmp_path / "robot.log")
    brain = _on(server, [*T42, "up", str(params), "--only", "transfer_server,planner", "--stop-timeout", "10"],
                tmp_path / "server.log")
    logs = lambda: (tmp_path / "robot.log").read_text()[-3000:] + (tmp_path / "server.log").read_text()[-3000:]  # noqa: E731
    try:
        seen = _stock_user(server, "graph", tmp_path / "user_graph.log")
        assert {"/mock_driver", "/recorder", "/transfer_server", "/planner"} <= set(seen["nodes"]), logs()
        assert seen["reset"][0] and not seen["bad_set"][0] and seen["good_set"][0]
        assert set(seen["rosout"]) == {"mock_driver", "recorder", "transfer_server", "planner"}

        explorer = _on(robot, [*T42, "node", "explorer", "--ros-args", "--params-file", str(params)],
                       tmp_path / "explorer.log")
        try:
            assert explorer.wait(timeout=300) == 0, (tmp_path / "explorer.log").read_text()
        finally:
            stop([explorer], 60.0)[0]
        assert len(list((tmp_path / "bags").glob("episode_*"))) >= 3

        seen = _stock_user(server, "transfer", tmp_path / "user_transfer.log")
        assert seen["transfer"][0], (seen, logs())
        assert seen["trajectory"]["points"] >= 1 and seen["path"]["poses"] == seen["trajectory"]["points"] + 1
        assert any(s.startswith("trajectory_done") for s in seen["driver_status"])  # executed on the other host
    finally:
        codes = [stop([brain], 60.0)[0], stop([hand], 60.0)[0]]
    assert codes == [0, 0], logs()
