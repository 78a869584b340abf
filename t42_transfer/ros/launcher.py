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
A child that exits 0 finished (the explorer after its episodes) and is
not started again, as in ``ros2 launch``; the others keep running, and ``t42 up`` ends (0) once none is left.
A child that exits otherwise after running a
while is restarted alone, as launch's ``respawn`` does: after 1 s, then 2, 4, 8 s
for each further restart, at most ``max_respawns`` times; the others keep running
(a restarted recorder begins a new bag, a restarted driver grasps on the next reset,
a restarted planner reads its model again).  A child that exits within
``MIN_UPTIME_S`` of its start failed to start, and one past its restarts, or any
with ``respawn=False`` (``--no-respawn``), is a failure: the others are stopped the
same way and the exit code is 1.  A second ``t42 up`` of nodes of the same names (the same file and namespace)
on the same ROS domain is refused (:func:`hold_node_names`).  Discovery stays on this machine
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) unless the user set a range.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import IO, Any, Literal, TextIO, TypeVar

from msg_adapters import names
from t42_transfer.config import show
from t42_transfer.nodes.registry import NODES
from t42_transfer.ros.runner import RUNNING, STOP_SIGNALS, SUPERVISOR_ENV, keep_discovery_local
from t42_transfer.yaml_files import read_yaml

PACKAGE = "t42_transfer"
"""The ROS package whose executables (setup.py's console scripts, one per node) a launch file starts."""
WILDCARDS = ("*", "**")
"""rcl's wildcard tokens of a section's name: one token, any number of tokens."""
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
    return _node_names(read_params_file(path))


def _node_names(doc: dict[str, Any]) -> list[str]:
    names: list[str] = []
    for tokens in _section_names(doc):
        if tokens and tokens[-1] not in WILDCARDS and tokens[-1] not in names:
            names.append(tokens[-1])
    return names


def _section_names(doc: dict[str, Any], outer: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """The node name of each section of a checked params file, as rcl reads it: the keys from the outermost in,
    split at ``/`` (``left: {mock_driver: ...}`` and ``/left/mock_driver`` are both ``("left", "mock_driver")``)."""
    found: list[tuple[str, ...]] = []
    for key, section in doc.items():
        path = (*outer, *(t for t in key.split("/") if t))
        found += [path] if PARAMS_KEY in section else _section_names(section, path)
    return found


def _matches(tokens: Sequence[str], fqn: str) -> bool:
    """Whether rcl gives the section named ``tokens`` to the node ``fqn``: ``*`` is one token, ``**`` any number."""
    parts = {"*": "/[^/]+", "**": "(?:/[^/]+)*"}
    return re.fullmatch("".join(parts.get(t, "/" + re.escape(t)) for t in tokens), fqn) is not None


def _check_namespaces(config: str | Path, doc: dict[str, Any], run: Sequence[str], namespace: str) -> None:
    """ValueError, one line, for a section of a node in ``run`` that rcl would not give that node under
    ``namespace``: the node would start on the file's other values or its defaults, silently."""
    for tokens in _section_names(doc):
        fqn = f"{namespace}/{tokens[-1]}" if tokens else ""
        if tokens and tokens[-1] in run and not _matches(tokens, fqn):
            key = "/" + "/".join(tokens)
            raise ValueError(f"{config}: section {key} does not match the node {fqn} it would start (under "
                             f"{namespace or 'no namespace'}): run under --namespace /{'/'.join(tokens[:-1])}, "
                             f"or name the section /**/{tokens[-1]} (any namespace)")


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


def plan_nodes(config: str | Path, only: Sequence[str] | None = None, namespace: str = "") -> list[str]:
    """The registered nodes ``config`` has sections for (filtered by ``only``), to run under ``namespace``;
    ValueError for unknown names and for a section of one of them that rcl would not give it there."""
    doc = read_params_file(config)
    sections = _node_names(doc)
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
    _check_namespaces(config, doc, sections, _absolute(namespace))
    return sections


RESPAWN_DELAY_S = 1.0
"""The first restart's delay (then 2, 4, 8 s): the launch file's ``respawn_delay``."""


def launch_nodes(params_file: str | Path, namespace: str = "") -> list[dict[str, Any]]:
    """The launch_ros ``Node`` arguments ``launch/t42_suite.launch.py`` starts for ``params_file``: the nodes
    :func:`plan_nodes` names, as ``t42 up`` starts them (one process each, the file as their parameters, and in a
    namespace its own ``/clock``, :func:`namespace_args`): one node list for both ways of starting a suite.

    Restarted as ``t42 up`` restarts them (``respawn``, at most :data:`MAX_RESPAWNS` times), but after a fixed
    :data:`RESPAWN_DELAY_S` (launch has no backoff); launch restarts a process whatever its exit code, so a node
    that can finish (the explorer, a camera at a video's end) is not respawned: its exit 0 is its end."""
    namespace = _absolute(namespace)
    clock = [(names.CLOCK, namespace + names.CLOCK)] if namespace else []
    nodes = []
    for name in plan_nodes(params_file, namespace=namespace):
        respawn = not NODES[name].finishes  # the registry says so: no node module (torch, mujoco) is imported
        nodes.append({"package": PACKAGE, "executable": name, "name": name, "namespace": namespace,
                      "parameters": [str(params_file)], "remappings": clock, "output": "screen", "emulate_tty": True,
                      "respawn": respawn, "respawn_delay": RESPAWN_DELAY_S,
                      "respawn_max_retries": MAX_RESPAWNS if respawn else 0})
    return nodes


def _forward(child: Child, stream: IO[str], emit: Callable[[str], None]) -> None:
    for line in stream:
        if not child.running and RUNNING in line:
            child.running = True
        emit(f"[{child.name}] {line}" if line.endswith("\n") else f"[{child.name}] {line}\n")


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
        self._broken = False

    def say(self, message: str) -> None:
        self.emit(f"[t42 up] {message}\n")

    def emit(self, text: str) -> None:
        """Write ``text`` whole; once the reader is gone (``t42 up | head``), drop it: the children's output is
        still read to the end (a child blocks on a full pipe) and the suite runs on until stopped."""
        with self._lock:
            if self._broken:
                return
            try:
                self.out.write(text)
                self.out.flush()
            except (BrokenPipeError, ValueError):  # (ValueError: the stream was closed)
                self._broken = True
                try:  # nothing more reaches the pipe, the interpreter's last flush included
                    devnull = os.open(os.devnull, os.O_WRONLY)
                    os.dup2(devnull, self.out.fileno())
                    os.close(devnull)
                except (OSError, ValueError, AttributeError):
                    pass

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
        child.forwarder = threading.Thread(target=_forward, args=(child, proc.stdout, self.emit),
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


def hold_node_names(fqns: Sequence[str], config: str | Path, domain: str | None = None,
                    where: Path | None = None) -> list[IO[str]]:
    """Lock files, one per fully qualified node name on the ROS domain, held while this ``t42 up`` runs (close
    them to let go); ValueError naming the ``t42 up`` that holds one.

    rcl lets two nodes of one name run side by side: two suites of one params file and namespace would run two
    drivers on the hand's topics, and each recorder would record both.  An ``flock`` is let go by the kernel
    however its holder ends (no stale lock after a SIGKILL); the file names the holder for the message."""
    import fcntl
    import tempfile

    domain = os.environ.get("ROS_DOMAIN_ID", "0") if domain is None else domain
    where = Path(tempfile.gettempdir()) / f"t42_up_{os.getuid()}" if where is None else where
    where.mkdir(parents=True, exist_ok=True)
    held: list[IO[str]] = []
    try:
        for fqn in fqns:
            handle = open(where / f"domain{domain}{fqn.replace('/', '%')}.lock", "a+")
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                handle.seek(0)
                owner = handle.read().strip() or "another t42 up"
                handle.close()
                raise ValueError(f"{fqn} already runs in {owner} on ROS_DOMAIN_ID {domain}: stop that suite first, "
                                 "or start this one under another --namespace") from None
            handle.seek(0)
            handle.truncate()
            handle.write(f"t42 up (pid {os.getpid()}) of {Path(config).absolute()}\n")
            handle.flush()
            held.append(handle)
    except BaseException:
        for handle in held:
            handle.close()
        raise
    return held


def up(config: str | Path, only: Sequence[str] | None = None, stop_timeout_s: float = 5.0,
       out: TextIO | None = None, namespace: str = "", respawn: bool = True, max_respawns: int = MAX_RESPAWNS) -> int:
    """Run the nodes of params file ``config`` until SIGINT, SIGTERM or SIGHUP, or a child fails (see the module
    docstring); the exit code."""
    names = plan_nodes(config, only, namespace)
    held = hold_node_names([f"{_absolute(namespace)}/{name}" for name in names], config)
    try:
        return _run_suite(config, names, stop_timeout_s, out, namespace, max_respawns if respawn else 0)
    finally:
        for handle in held:
            handle.close()


def _run_suite(config: str | Path, names: list[str], stop_timeout_s: float, out: TextIO | None, namespace: str,
               max_respawns: int) -> int:
    supervisor = Supervisor(config, out, stop_timeout_s, namespace=namespace)
    supervisor.say(f"discovery range {keep_discovery_local()}, ROS_DOMAIN_ID {os.environ.get('ROS_DOMAIN_ID', '0')}")
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in STOP_SIGNALS}
    failed: list[str] = []
    respawner = _Respawner(supervisor, max_respawns)
    try:
        for name in names:
            supervisor.start(name)
        while not stop.is_set():
            failed = respawner.tend()
            if failed:
                supervisor.say(f"{'; '.join(failed)}: stopping the others")
                break
            if respawner.idle():
                supervisor.say("every node finished")
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


@dataclass(frozen=True)
class AfterExit:
    """What ``t42 up`` does about a node that exited (:func:`after_exit`), a field for each kind of answer."""

    action: Literal["done", "restart", "fail"]
    delay_s: float = 0.0
    """How long to wait before starting it again (``restart`` only)."""
    why: str = ""
    """Why its exit is a failure (``fail`` only), for the message that stops the suite."""


def after_exit(code: int, ran_s: float, restarts: int, max_respawns: int) -> AfterExit:
    """What ``t42 up`` does about a node that exited with ``code`` after ``ran_s`` s, restarted ``restarts`` times
    so far: ``done`` for exit 0 (a node that finished, the explorer after its episodes: as in launch, its end is no
    failure and starting it again would redo its work), ``restart`` after a backoff, or ``fail``."""
    if code == 0:
        return AfterExit("done")
    if max_respawns <= 0:
        return AfterExit("fail", why="no respawn")
    if ran_s < MIN_UPTIME_S:
        return AfterExit("fail", why="it failed to start")
    if restarts >= max_respawns:
        return AfterExit("fail", why=f"restarted {restarts} time(s) already")
    return AfterExit("restart", delay_s=min(MAX_BACKOFF_S, RESPAWN_DELAY_S * 2.0 ** restarts))


class _Respawner:
    """Restarts the supervisor's children that exit after running a while, with backoff, up to a limit."""

    def __init__(self, supervisor: Supervisor, max_respawns: int) -> None:
        self.supervisor, self.max_respawns = supervisor, max_respawns
        self.respawns: dict[str, int] = {}
        self.due: dict[str, tuple[float, tuple[str, ...]]] = {}
        """Children waiting to be started again: when, and with which overrides."""

    def tend(self) -> list[str]:
        """Schedule restarts of children that died, start those due; what failed for good (empty: all is well).
        A child that finished (exit 0) is dropped: the others keep running."""
        now, failed = time.monotonic(), []
        for child in self.supervisor.dead():
            code, ran_s, count = child.proc.returncode, now - child.started, self.respawns.get(child.name, 0)
            verdict = after_exit(code, ran_s, count, self.max_respawns)
            if verdict.action == "fail":
                failed.append(f"{child.name} exited with code {code} unexpectedly ({verdict.why})")
                continue
            self.supervisor.forget(child)
            if verdict.action == "done":
                self.supervisor.say(f"{child.name} finished (exit 0 after {ran_s:.0f} s)")
                continue
            self.supervisor.say(f"{child.name} exited with code {code} after {ran_s:.0f} s: restarting it in "
                                f"{verdict.delay_s:g} s ({count + 1} of {self.max_respawns})")
            self.respawns[child.name] = count + 1
            self.due[child.name] = (now + verdict.delay_s, child.overrides)
        for name, (when, overrides) in list(self.due.items()):
            if now >= when and not failed:
                del self.due[name]
                self.supervisor.start(name, *overrides)
        return failed

    def idle(self) -> bool:
        """Every child finished and none waits for its restart: the suite is done."""
        return not self.supervisor.children and not self.due
