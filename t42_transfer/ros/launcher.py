"""``t42 up``: run the nodes of one params file as separate processes, like a small ``ros2 launch``.

Each node with its own section in the params file runs as
``python -m t42_transfer.cli node <name> --ros-args --params-file <file>`` (plus
:func:`namespace_args` when a namespace is given), in its
own session (so a terminal's Ctrl-C reaches only this supervisor, which then
stops the children in order).  Their output is forwarded line by line, prefixed
``[<name>]``.  On SIGINT, SIGTERM or SIGHUP (the terminal or ssh session closed)
every child gets SIGINT, then SIGTERM after ``stop_timeout_s``, then SIGKILL.
Should the supervisor itself die (SIGKILL, a crash), each child gets SIGTERM
from the kernel and stops cleanly (:func:`~t42_transfer.ros.runner.stop_with_supervisor`).
A child that exits on its own after running a
while is restarted alone, as launch's ``respawn`` does: after 1 s, then 2, 4, 8 s
for each further restart, at most ``max_respawns`` times; the others keep running
(a restarted recorder begins a new bag, a restarted driver grasps on the next reset,
a restarted planner reads its model again).  A child that exits within
``MIN_UPTIME_S`` of its start failed to start, and one past its restarts, or any
with ``respawn=False`` (``--no-respawn``), is a failure: the others are stopped the
same way and the exit code is 1.  Discovery stays on this machine
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) unless the user set a range.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import IO, Any, TextIO, TypeVar

from msg_adapters import names
from t42_transfer.config import show
from t42_transfer.nodes.registry import NODES
from t42_transfer.ros.runner import RUNNING, STOP_SIGNALS, SUPERVISOR_ENV, keep_discovery_local
from t42_transfer.yaml_files import read_yaml

PACKAGE = "t42_transfer"
"""The ROS package whose executables (setup.py's console scripts, one per node) a launch file starts."""
WILDCARDS = ("/**", "**")
PARAMS_KEY = "ros__parameters"

POLL_S = 0.1
MIN_UPTIME_S = 5.0
"""A child that exits sooner than this after its start failed to start: restarting it would fail again."""
MAX_RESPAWNS = 5
MAX_BACKOFF_S = 8.0


@dataclass
class Child:
    name: str
    proc: subprocess.Popen[str]
    forwarder: threading.Thread
    overrides: tuple[str, ...] = ()
    started: float = 0.0
    """time.monotonic() at its start."""
    running: bool = False
    """It said it runs (:data:`~t42_transfer.ros.runner.RUNNING`): before that, a stop only cuts its start short
    (a signal during the interpreter's own start-up can end no process cleanly)."""


def namespace_args(namespace: str) -> list[str]:
    """ROS arguments that put a node into ``namespace`` with that namespace's own ``/clock``.

    Every name the nodes use is relative except ``/clock``; a suite per hand (each driver may be
    its graph's clock) therefore also remaps ``/clock`` into its namespace, so two simulated hands
    on one graph do not share a clock.
    """
    namespace = _absolute(namespace)
    if not namespace:
        return []
    return ["-r", f"__ns:={namespace}", "-r", f"{names.CLOCK}:={namespace}{names.CLOCK}"]


def _absolute(namespace: str) -> str:
    """``left``, ``/left/`` -> ``/left``; the root namespace -> ``""``."""
    return "/" + namespace.strip("/") if namespace.strip("/") else ""


def read_params_file(path: str | Path) -> dict[str, Any]:
    """A ROS params file's node sections, checked as rcl's parser checks them; ValueError naming the file.

    Every node process parses the file again (rcl); a file rcl would refuse is refused here
    first, in one line, instead of by every child in turn.  Each section is ``node: {ros__parameters:
    {...}}`` (or namespaces around that); parameters are scalars, lists of one scalar type, or
    mappings of them (dotted names); YAML aliases are refused, as rcl refuses them.
    """
    doc = read_yaml(path, "params file", aliases=False)
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: a params file is a mapping of node sections, got {type(doc).__name__}")
    for key, section in doc.items():
        _check_section(path, key, section, "")
    return doc


_SCALARS = (bool, int, float, str)


def _check_section(path: str | Path, key: Any, section: Any, outer: str) -> None:
    where = outer + _where(key)
    if not isinstance(key, str) or not key or key[0].isdigit():
        raise ValueError(f"{path}: node section {where}: a name is a string not starting with a digit")
    if not isinstance(section, dict):
        raise ValueError(f"{path}: node section {where}: expected a mapping with {PARAMS_KEY}, "
                         f"got {type(section).__name__}")
    if PARAMS_KEY in section:
        if len(section) > 1:
            others = sorted(_where(k) for k in section if k != PARAMS_KEY)
            raise ValueError(f"{path}: node section {where}: {', '.join(others)} beside {PARAMS_KEY}")
        _check_params(path, f"{where}.{PARAMS_KEY}", section[PARAMS_KEY])
        return
    for inner, value in section.items():  # a namespace around node sections
        _check_section(path, inner, value, f"{where}.")


def _check_params(path: str | Path, where: str, params: Any) -> None:
    if not isinstance(params, dict):
        raise ValueError(f"{path}: {where}: expected a mapping of parameters, got {type(params).__name__}")
    for name, value in params.items():
        at = f"{where}.{_where(name)}"
        if not isinstance(name, str):
            raise ValueError(f"{path}: {at}: a parameter name is a string")
        if isinstance(value, dict):
            _check_params(path, at, value)
        elif isinstance(value, list):
            kinds = {type(v) for v in value}
            if len(kinds) > 1 or not kinds <= set(_SCALARS):
                raise ValueError(f"{path}: {at}: a list parameter holds values of one type (bool, int, float "
                                 f"or string), got {', '.join(sorted(k.__name__ for k in kinds))}")
        elif value is not None and not isinstance(value, _SCALARS):
            raise ValueError(f"{path}: {at}: a parameter is a bool, int, float, string or list, "
                             f"got {type(value).__name__}")


def _where(key: Any) -> str:
    """A key for a one-line message: as written when it is a short printable name, else its cut-short repr."""
    return key if isinstance(key, str) and key.isprintable() and 0 < len(key) <= 60 else show(key)


def node_sections(path: str | Path) -> list[str]:
    """Names of the nodes a ROS params file has its own section for (wildcards excluded), in file order.

    Write sections as ``/**/name`` to match the node under any namespace (``t42 up --namespace``);
    a plain ``name`` section matches it only at the root namespace, as in rcl.
    """
    names: list[str] = []
    for key in read_params_file(path):
        if key in WILDCARDS:
            continue
        name = key.rsplit("/", 1)[-1]  # "/**/recorder", "/left/recorder" and "recorder" name the recorder
        if name not in names:
            names.append(name)
    return names


P = TypeVar("P")


def params_from_file(params_cls: type[P], params_file: str | Path, node_name: str) -> tuple[P, list[str]]:
    """The ``params_cls`` a node named ``node_name`` (``/left/object_tracker``; no namespace: the root) would
    declare from ``params_file``, and the names the file gives it that it has none of (a typo): without running
    it, for a tool that must use exactly what the node would (rcl resolves the file's sections, wildcards and
    namespaces for the name; :func:`declare_params` checks the values).  ValueError, one line, when the values
    are refused or the file gives that node no parameter at all."""
    import rclpy

    from t42_transfer.ros.params import declare_params, parameter_overrides, undeclared_overrides

    read_params_file(params_file)  # a file rcl would refuse: one line here, not rcl's error
    namespace, _, name = ("/" + node_name.strip("/")).rpartition("/")
    keep_discovery_local()
    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", "--params-file", str(params_file)])
    try:
        node = rclpy.create_node(name, namespace=namespace or "/", context=context, enable_rosout=False,
                                 start_parameter_services=False)
    except Exception as err:  # a bad node name
        rclpy.shutdown(context=context)
        raise ValueError(f"{node_name}: not a node name ({err})") from None
    try:
        if not parameter_overrides(node):
            raise ValueError(f"{params_file}: no parameters for {node.get_fully_qualified_name()} (a section "
                             f"/**/{name}, or {node.get_fully_qualified_name()})")
        try:
            return declare_params(node, params_cls), undeclared_overrides(node)
        except ValueError as err:  # the node's words, with the file they came from
            raise ValueError(f"{params_file}: {err}") from None
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)


def plan_nodes(config: str | Path, only: Sequence[str] | None = None) -> list[str]:
    """The registered nodes ``config`` has sections for (filtered by ``only``); ValueError for unknown names."""
    sections = node_sections(config)
    unknown = [n for n in sections if n not in NODES]
    if unknown:
        raise ValueError(f"{config}: no registered node named {', '.join(unknown)}; available: {', '.join(NODES)}")
    if only is not None:
        missing = [n for n in only if n not in sections]
        if missing:
            raise ValueError(f"--only {','.join(missing)}: not in {config} (it has {', '.join(sections)})")
        sections = [n for n in sections if n in only]
    if not sections:
        raise ValueError(f"{config}: no node sections to run")
    return sections


def launch_nodes(params_file: str | Path, namespace: str = "") -> list[dict[str, Any]]:
    """The launch_ros ``Node`` arguments ``launch/t42_suite.launch.py`` starts for ``params_file``: the nodes
    :func:`plan_nodes` names, as ``t42 up`` starts them (one process each, the file as their parameters, and in a
    namespace its own ``/clock``, :func:`namespace_args`): one node list for both ways of starting a suite."""
    namespace = _absolute(namespace)
    clock = [(names.CLOCK, namespace + names.CLOCK)] if namespace else []
    return [{"package": PACKAGE, "executable": name, "name": name, "namespace": namespace,
             "parameters": [str(params_file)], "remappings": clock, "output": "screen", "emulate_tty": True}
            for name in plan_nodes(params_file)]


def _forward(child: Child, stream: IO[str], out: TextIO, lock: threading.Lock) -> None:
    for line in stream:
        if not child.running and RUNNING in line:
            child.running = True
        with lock:
            out.write(f"[{child.name}] {line}" if line.endswith("\n") else f"[{child.name}] {line}\n")
            out.flush()


def _stop(children: list[Child], timeout_s: float, say: Callable[[str], None]) -> None:
    """SIGINT every live child, then SIGTERM and SIGKILL to those still running after ``timeout_s`` each."""
    for sig, wait_s in ((signal.SIGINT, timeout_s), (signal.SIGTERM, timeout_s), (signal.SIGKILL, timeout_s)):
        alive = [c for c in children if c.proc.poll() is None]
        if not alive:
            return
        if sig is not signal.SIGINT:
            say(f"{', '.join(c.name for c in alive)} still running: sending {sig.name}")
        for child in alive:
            child.proc.send_signal(sig)
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline and any(c.proc.poll() is None for c in alive):
            time.sleep(POLL_S / 2)


class Supervisor:
    """Node processes started from one params file; stops them all on exit (``with Supervisor(...)``).

    ``t42 up`` and ``t42 demo`` both run the suite through this class.
    """

    def __init__(self, config: str | Path, out: TextIO | None = None, stop_timeout_s: float = 5.0,
                 env: dict[str, str] | None = None, namespace: str = "") -> None:
        self.config = Path(config).resolve()
        self.namespace = namespace
        self.out = out if out is not None else sys.stdout
        self.stop_timeout_s = stop_timeout_s
        self.env = env
        self.children: list[Child] = []
        self._lock = threading.Lock()

    def say(self, message: str) -> None:
        with self._lock:
            self.out.write(f"[t42 up] {message}\n")
            self.out.flush()

    def start(self, name: str, *overrides: str) -> Child:
        """Start node ``name`` with its section of the params file (and ``-p`` ``overrides``, ``key:=value``)."""
        cmd = [sys.executable, "-u", "-m", "t42_transfer.cli", "node", name, "--ros-args",
               "--params-file", str(self.config)]
        cmd += namespace_args(self.namespace)
        for override in overrides:
            cmd += ["-p", override]
        env = dict(os.environ if self.env is None else self.env, **{SUPERVISOR_ENV: str(os.getpid())})
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                bufsize=1, start_new_session=True, env=env)
        child = Child(name, proc, threading.Thread(), overrides, time.monotonic())
        child.forwarder = threading.Thread(target=_forward, args=(child, proc.stdout, self.out, self._lock),
                                           daemon=True)
        child.forwarder.start()
        self.children.append(child)
        self.say(f"started {name} (pid {proc.pid})")
        return child

    def dead(self) -> list[Child]:
        """The children no longer running."""
        return [c for c in self.children if c.proc.poll() is not None]

    def forget(self, child: Child) -> None:
        """Drop an exited child (its output forwarded to the end) before it is started again."""
        self.children.remove(child)
        child.forwarder.join(timeout=1.0)
        if child.proc.stdout is not None and not child.forwarder.is_alive():
            child.proc.stdout.close()

    def stop(self) -> dict[str, int]:
        """Stop every child (SIGINT, then SIGTERM, then SIGKILL); their exit codes."""
        _stop(self.children, self.stop_timeout_s, self.say)
        for child in self.children:
            child.forwarder.join(timeout=1.0)
            if child.proc.stdout is not None and not child.forwarder.is_alive():
                child.proc.stdout.close()
        return {c.name: c.proc.returncode for c in self.children}

    def starting(self) -> list[str]:
        """Children that had not said they run yet."""
        return [c.name for c in self.children if not c.running]

    def __enter__(self) -> Supervisor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def up(config: str | Path, only: Sequence[str] | None = None, stop_timeout_s: float = 5.0,
       out: TextIO | None = None, namespace: str = "", respawn: bool = True, max_respawns: int = MAX_RESPAWNS) -> int:
    """Run the nodes of params file ``config`` until SIGINT, SIGTERM or SIGHUP, or a child fails (see the module
    docstring); the exit code."""
    names = plan_nodes(config, only)
    supervisor = Supervisor(config, out, stop_timeout_s, namespace=namespace)
    supervisor.say(f"discovery range {keep_discovery_local()}, ROS_DOMAIN_ID {os.environ.get('ROS_DOMAIN_ID', '0')}")
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in STOP_SIGNALS}
    failed: list[str] = []
    respawner = _Respawner(supervisor, max_respawns if respawn else 0)
    try:
        for name in names:
            supervisor.start(name)
        while not stop.is_set():
            failed = respawner.tend()
            if failed:
                supervisor.say(f"{'; '.join(failed)}: stopping the others")
                break
            stop.wait(POLL_S)
        else:
            supervisor.say("stopping")
    finally:
        starting = supervisor.starting()
        codes = supervisor.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if starting:
        supervisor.say(f"stopped while starting: {', '.join(starting)}")
    unclean = {n: rc for n, rc in codes.items() if rc != 0 and n not in starting}
    if unclean and not failed:
        supervisor.say("not stopped cleanly: " + ", ".join(f"{n} exited with code {rc}" for n, rc in unclean.items()))
    return 1 if failed or unclean else 0


class _Respawner:
    """Restarts the supervisor's children that exit after running a while, with backoff, up to a limit."""

    def __init__(self, supervisor: Supervisor, max_respawns: int) -> None:
        self.supervisor, self.max_respawns = supervisor, max_respawns
        self.respawns: dict[str, int] = {}
        self.due: dict[str, tuple[float, tuple[str, ...]]] = {}
        """Children waiting to be started again: when, and with which overrides."""

    def tend(self) -> list[str]:
        """Schedule restarts of children that died, start those due; what failed for good (empty: all is well)."""
        now, failed = time.monotonic(), []
        for child in self.supervisor.dead():
            code, ran_s, count = child.proc.returncode, now - child.started, self.respawns.get(child.name, 0)
            if ran_s < MIN_UPTIME_S or count >= self.max_respawns:
                why = ("it failed to start" if ran_s < MIN_UPTIME_S else f"restarted {count} time(s) already") \
                    if self.max_respawns else "no respawn"
                failed.append(f"{child.name} exited with code {code} unexpectedly ({why})")
                continue
            delay = min(MAX_BACKOFF_S, 2.0 ** count)
            self.supervisor.say(f"{child.name} exited with code {code} after {ran_s:.0f} s: restarting it in "
                                f"{delay:g} s ({count + 1} of {self.max_respawns})")
            self.supervisor.forget(child)
            self.respawns[child.name] = count + 1
            self.due[child.name] = (now + delay, child.overrides)
        for name, (when, overrides) in list(self.due.items()):
            if now >= when and not failed:
                del self.due[name]
                self.supervisor.start(name, *overrides)
        return failed
