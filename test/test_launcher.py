"""`t42 up`'s and the launch file's planning, in milliseconds: which nodes a params file starts and where, what
the supervisor does about an exit, the lock against a second suite of the same names, and the transfer server's
claim of its namespace's model directory.  The processes themselves: test_node_runner.py."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from t42_transfer.cli import main
from t42_transfer.ros.launcher import (
    MAX_RESPAWNS,
    MIN_UPTIME_S,
    RESPAWN_DELAY_S,
    AfterExit,
    _Respawner,
    after_exit,
    hold_node_names,
    launch_nodes,
    node_sections,
    plan_nodes,
)

SECTION = {"ros__parameters": {"rate_factor": 3.0}}


def _params(tmp_path: Path, doc: dict[str, Any]) -> Path:
    import json

    import yaml

    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(json.loads(json.dumps(doc)), sort_keys=False))  # (no aliases: rcl refuses them)
    return path


# ------------------------------------------------------------------ exits
def test_a_node_that_exits_0_finished_and_is_not_restarted() -> None:
    """The explorer ends 0 after its episodes: `t42 up` restarted it (the same seed, the same episodes recorded
    again) or, ended within 5 s or under --no-respawn, stopped the suite with exit 1."""
    for ran_s in (1.0, MIN_UPTIME_S + 5):
        for max_respawns in (0, MAX_RESPAWNS):
            assert after_exit(0, ran_s, 0, max_respawns) == AfterExit("done")
    assert after_exit(-9, MIN_UPTIME_S + 1, 0, MAX_RESPAWNS) == AfterExit("restart", delay_s=RESPAWN_DELAY_S)
    assert after_exit(1, MIN_UPTIME_S + 1, 3, MAX_RESPAWNS) == AfterExit("restart", delay_s=8.0)
    assert after_exit(1, 1.0, 0, MAX_RESPAWNS) == AfterExit("fail", why="it failed to start")
    assert after_exit(1, MIN_UPTIME_S + 1, MAX_RESPAWNS, MAX_RESPAWNS) == AfterExit(
        "fail", why="restarted 5 time(s) already")
    assert after_exit(-9, MIN_UPTIME_S + 1, 0, 0) == AfterExit("fail", why="no respawn")

    class Supervisor:  # the part of launcher.Supervisor the respawner uses
        def __init__(self) -> None:
            done = SimpleNamespace(returncode=0, poll=lambda: 0)
            running = SimpleNamespace(returncode=None, poll=lambda: None)
            started = time.monotonic() - 2.0
            self.children = [SimpleNamespace(name="explorer", proc=done, started=started, overrides=()),
                             SimpleNamespace(name="mock_driver", proc=running, started=started, overrides=())]
            self.said: list[str] = []
            self.started: list[str] = []

        def dead(self) -> list[Any]:
            return [c for c in self.children if c.proc.poll() is not None]

        def forget(self, child: Any) -> None:
            self.children.remove(child)

        def say(self, message: str) -> None:
            self.said.append(message)

        def start(self, name: str, *overrides: str) -> None:
            self.started.append(name)

    supervisor = Supervisor()
    respawner = _Respawner(supervisor, MAX_RESPAWNS)  # type: ignore[arg-type]
    assert respawner.tend() == [] and respawner.tend() == []
    assert [c.name for c in supervisor.children] == ["mock_driver"] and not respawner.due and not supervisor.started
    assert supervisor.said == ["explorer finished (exit 0 after 2 s)"]
    assert not respawner.idle()
    supervisor.children.clear()
    assert respawner.idle()  # every node finished: `t42 up` ends, 0


# ------------------------------------------------------------------ params files as rcl reads them
def test_every_section_form_rcl_accepts_is_read(tmp_path: Path) -> None:
    """A nested namespace (`left: {mock_driver: ...}`) was taken for a node named left, `/**/*` for one named *."""
    nested = _params(tmp_path, {"left": {"mock_driver": SECTION}, "/**/*": SECTION, "*": SECTION,
                                "/left/*": SECTION, "/**": {"recorder": SECTION}, "/**/left/**/planner": SECTION})
    assert node_sections(nested) == ["mock_driver", "recorder", "planner"]
    assert plan_nodes(nested, namespace="/left") == ["mock_driver", "recorder", "planner"]
    assert plan_nodes(nested, namespace="left/") == ["mock_driver", "recorder", "planner"]
    assert plan_nodes(nested, ["recorder"]) == ["recorder"]  # (the /left sections are not those of a node run)
    only_wildcards = _params(tmp_path, {"/**/*": SECTION, "/**": SECTION})
    with pytest.raises(ValueError, match="no node sections to run"):
        plan_nodes(only_wildcards)


@pytest.mark.parametrize("doc, namespace", [
    ({"/left/mock_driver": SECTION}, ""),
    ({"left": {"mock_driver": SECTION}}, "/right"),
    ({"/**/recorder": SECTION, "mock_driver": SECTION}, "/left"),
    ({"/*/mock_driver": SECTION}, ""),
], ids=["absolute-at-root", "nested-elsewhere", "root-only-under-ns", "one-token-at-root"])
def test_a_section_that_cannot_reach_its_node_is_refused(tmp_path: Path, doc: dict[str, Any], namespace: str,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """`/left/mock_driver` under no --namespace started /mock_driver on its defaults, silently."""
    params = _params(tmp_path, doc)
    with pytest.raises(ValueError, match=r"section /\S*mock_driver does not match the node \S*/mock_driver"):
        plan_nodes(params, namespace=namespace)
    with pytest.raises(ValueError, match="does not match"):
        launch_nodes(params, namespace)
    args = ["up", str(params)] + (["--namespace", namespace] if namespace else [])
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "does not match the node" in err, err


# ------------------------------------------------------------------ one suite of those names at a time
def test_a_second_suite_of_the_same_node_names_is_refused(tmp_path: Path, ros_domain: int,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Two `t42 up` of one file and namespace ran side by side, each recorder recording both hands."""
    held = hold_node_names(["/left/mock_driver", "/left/recorder"], "a.yaml", "7", tmp_path)
    with pytest.raises(ValueError, match=r"^/left/recorder already runs in t42 up \(pid \d+\) of \S*a.yaml on "
                                         r"ROS_DOMAIN_ID 7: stop that suite first"):
        hold_node_names(["/left/recorder"], "b.yaml", "7", tmp_path)
    others = [hold_node_names(["/right/recorder"], "b.yaml", "7", tmp_path),
              hold_node_names(["/left/recorder"], "b.yaml", "8", tmp_path)]  # another namespace or domain
    with pytest.raises(ValueError, match="/left/mock_driver already runs"):  # none of its names kept
        hold_node_names(["/left/planner", "/left/mock_driver"], "b.yaml", "7", tmp_path)
    for handle in held + [h for hs in others for h in hs]:
        handle.close()
    again = hold_node_names(["/left/planner", "/left/mock_driver", "/left/recorder"], "b.yaml", "7", tmp_path)
    for handle in again:
        handle.close()

    # `t42 up` holds them: a suite of the same names on this domain is refused before it starts a node.  (The node
    # is given a bad parameter: should it be started after all, it fails at once instead of running on.)
    params = _params(tmp_path, {"/**/mock_driver": {"ros__parameters": {"rate_factor": -1.0}}})
    held = hold_node_names(["/left/mock_driver"], "first.yaml")
    try:
        assert main(["up", str(params), "--namespace", "/left"]) == 2
    finally:
        for handle in held:
            handle.close()
    captured = capsys.readouterr()
    assert "/left/mock_driver already runs in t42 up" in captured.err and "started" not in captured.out, captured


# ------------------------------------------------------------------ the launch file
def test_the_launch_file_respawns_as_t42_up_does_but_not_a_node_that_finishes(tmp_path: Path) -> None:
    """Its docstring and the README said it starts the nodes as `t42 up` does; it gave them no respawn."""
    params = _params(tmp_path, {f"/**/{n}": SECTION for n in ("mock_driver", "recorder", "explorer", "camera")})
    nodes = {n["name"]: n for n in launch_nodes(params, "/left")}
    for name in ("mock_driver", "recorder"):
        assert nodes[name]["respawn"] is True, name
        assert nodes[name]["respawn_delay"] == RESPAWN_DELAY_S == after_exit(1, MIN_UPTIME_S, 0, 1).delay_s
        assert nodes[name]["respawn_max_retries"] == MAX_RESPAWNS
    for name in ("explorer", "camera"):  # launch restarts whatever the exit code: its exit 0 would start it again
        assert nodes[name]["respawn"] is False and nodes[name]["respawn_max_retries"] == 0, name


def test_output_is_drained_after_the_reader_went_away() -> None:
    """`t42 up | head -3`: the forwarders died of BrokenPipeError, the children's pipes then filled up."""
    import sys
    import threading

    from t42_transfer.ros.launcher import Child, Supervisor, _forward

    class Gone:
        def write(self, text: str) -> int:
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self) -> None:
            raise BrokenPipeError(32, "Broken pipe")

    supervisor = Supervisor(__file__, out=Gone())  # type: ignore[arg-type]
    proc = subprocess.Popen([sys.executable, "-c", "print('x' * 1000 + '\\n', end='' ) or [print(i) for i in "
                             "range(200_000)]"], stdout=subprocess.PIPE, text=True)
    child = Child("talker", proc, threading.Thread())
    forwarder = threading.Thread(target=_forward, args=(child, proc.stdout, supervisor.emit), daemon=True)
    forwarder.start()
    supervisor.say("still running")  # no error either
    assert proc.wait(timeout=20) == 0  # (200,000 lines: far past a pipe's 64 KiB, read to the end)
    forwarder.join(timeout=5)
    assert not forwarder.is_alive()
    proc.stdout.close()
