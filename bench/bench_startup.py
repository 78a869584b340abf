"""Start-up time of the node suite: ``t42 up configs/suite.yaml`` until every node is on the graph with its services.

    .venv/bin/python bench/bench_startup.py [--runs 5] [--config configs/suite.yaml] [--out bench/results/startup.json]

``suite_up_s``: seconds from starting ``t42 up CONFIG`` (a subprocess in a fresh temporary working directory,
so the config's relative paths are empty folders: no source model, no recordings, no model for the planner)
until an observer rclpy node in this process sees every node of the config on the graph and every service of
:data:`SERVICES` ready (the node's own services and its parameter service ``/<node>/get_parameters``, so a node
without services of its own, the planner, counts once its parameter services are up).  Without their files
the nodes still start as they do from a clean checkout: the transfer server reads its source model only when
a transfer is called, the planner logs that it waits for ``t42/model_updated``.  ``bare_node_s``: the same
measure for ``python -c`` running a bare rclpy node (rclpy, and std_srvs for the suite's Trigger service type)
with one service, spun as ``t42 node`` spins a node.  ``bare_node_late_init_s``: the same bare node sleeping
:data:`LATE_INIT_S` before it imports rclpy, as a suite node's context starts late (after the supervisor's
and its own imports): with the observer already up, such a late participant was found only after a wait of
about 3 s (a Fast DDS announcement period), which ``late_init_wait_s`` (its time less the sleep) shows.
Medians of ``--runs`` runs each, suite and bare runs taken in turn in the same run, each with a fresh
observer (created, and the graph clear of the nodes, before the clock starts, as a test's rig node is).

Where the time goes, per node (medians): ``started_s`` (``t42 up`` says it started the process: the
supervisor's own start-up), ``running_s`` (the node's "running on ..." log line: interpreter, imports and
the node's construction), ``discovered_s`` (its name on the observer's graph), ``services_ready_s`` and the
CPU seconds its process had used by then.  Beside them the seconds of ``python -c "import X"`` (medians of
``--runs``) for the heavy imports each node process pays, and one ``python -X importtime`` tree per node
process (``import rclpy, t42_transfer.cli, <node module>``, as ``t42 node`` imports them) with the
cumulative milliseconds of each heavy package in it.

Everything runs on its own ROS_DOMAIN_ID (random in 150-230 unless set) with LOCALHOST discovery.  Every
process started is stopped with SIGINT and waited for (``t42 up`` stops its nodes); should one not stop,
SIGTERM then SIGKILL, and the node processes ``t42 up`` reported are stopped by their pids too, also on error.
The machine's load is recorded before and after: on a shared machine, repeat on a quiet one before quoting.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from types import FrameType

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from bench.machine import machine_info  # noqa: E402
from msg_adapters import names  # noqa: E402
from t42_transfer.nodes.registry import NODES  # noqa: E402
from t42_transfer.ros.launcher import plan_nodes  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "startup.json"
CONFIG = REPO / "configs" / "suite.yaml"
TICK_S = os.sysconf("SC_CLK_TCK")
POLL_S = 0.01
REFERENCE = {"date": "2026-12-02", "suite_up_s": 4.3, "bare_node_s": 0.65}

SERVICES = {
    "mock_driver": ["/" + names.HAND_RESET],
    "recorder": ["/" + names.private_of("recorder", s) for s in (names.RECORDER_START, names.RECORDER_STOP,
                                                                   names.RECORDER_SPLIT)],
    "transfer_server": ["/" + names.TRANSFER_NOW],
    "planner": [],
    "bare_node": ["/bare_node/trigger"],
}
"""Each node's own services (std_srvs/Trigger); its ``/<node>/get_parameters`` is waited for too."""

BARE_NODE = """
import signal
import sys
import time
time.sleep(float(sys.argv[1]) if len(sys.argv) > 1 else 0.0)  # bare_node_late_init_s: rclpy.init that late
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger
stop = []
for sig in (signal.SIGINT, signal.SIGTERM):
    signal.signal(sig, lambda *_: stop.append(True))
context = rclpy.Context()
rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
node = Node("bare_node", context=context)
node.create_service(Trigger, "~/trigger", lambda request, response: response)
executor = SingleThreadedExecutor(context=context)
executor.add_node(node)
while not stop:
    executor.spin_once(timeout_sec=0.1)
executor.shutdown(timeout_sec=5.0)
node.destroy_node()
rclpy.shutdown(context=context)
"""

HEAVY = ("torch", "mujoco", "rclpy", "numpy", "scipy", "cv2", "safetensors", "mcap", "rosbags", "yaml",
         "msg_adapters", "t42_transfer")
LATE_INIT_S = 1.0
"""The bare node of ``bare_node_late_init_s`` sleeps this long before it imports rclpy (as a suite node, whose
context starts after the supervisor's and its own imports: 0.4-2 s)."""

"""Packages whose cumulative import time each node's -X importtime tree reports (where they appear)."""

STARTED = re.compile(r"^\[t42 up\] started (\w+) \(pid (\d+)\)")
RUNNING = re.compile(r"^\[(\w+)\] .*SIGINT or SIGTERM stops")


def cpu_s(pid: int) -> float | None:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / TICK_S  # utime + stime


def is_node_process(pid: int) -> bool:
    """``pid`` is still one of our node processes (not a reused pid)."""
    try:
        return b"t42_transfer.cli" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def stop_process(proc: subprocess.Popen, timeout_s: float = 30.0) -> float:
    """SIGINT, wait; SIGTERM, SIGKILL if it does not end. Seconds until it ended."""
    start = time.monotonic()
    for sig, wait_s in ((signal.SIGINT, timeout_s), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        if proc.poll() is not None:
            break
        proc.send_signal(sig)
        try:
            proc.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            continue
    return time.monotonic() - start


def stop_pids(pids: list[int], timeout_s: float = 10.0) -> list[int]:
    """Stop node processes left behind (SIGINT, then SIGKILL after ``timeout_s``); the pids that needed it."""
    left = [pid for pid in pids if is_node_process(pid)]
    for pid in left:
        os.kill(pid, signal.SIGINT)
    deadline = time.monotonic() + timeout_s
    while any(is_node_process(pid) for pid in left) and time.monotonic() < deadline:
        time.sleep(0.1)
    for pid in left:
        if is_node_process(pid):
            os.kill(pid, signal.SIGKILL)
    return left


class Observer:
    """An rclpy node in this process that watches the graph for nodes and services, with its own context."""

    def __init__(self, nodes: dict[str, list[str]]) -> None:
        import rclpy
        from rcl_interfaces.srv import GetParameters
        from rclpy.node import Node
        from std_srvs.srv import Trigger

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node(f"startup_observer_{os.getpid()}", context=self.context)
        self.nodes = nodes
        self.clients = {}
        for name, services in nodes.items():
            for service in services:
                self.clients[service] = self.node.create_client(Trigger, service)
            self.clients[f"/{name}/get_parameters"] = self.node.create_client(GetParameters,
                                                                              f"/{name}/get_parameters")

    def visible(self) -> set[str]:
        return {name for name, ns in self.node.get_node_names_and_namespaces() if ns == "/"} & set(self.nodes)

    def ready(self) -> set[str]:
        return {service for service, client in self.clients.items() if client.service_is_ready()}

    def wait_clear(self, timeout_s: float = 15.0) -> bool:
        """Wait until none of the nodes is on the graph (a previous run's gone); whether it cleared."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if not self.visible() and not self.ready():
                return True
            time.sleep(0.1)
        return False

    def close(self) -> None:
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


def node_services(name: str) -> list[str]:
    return [*SERVICES.get(name, []), f"/{name}/get_parameters"]


def one_run(cmd: list[str], nodes: list[str], cwd: Path, env: dict[str, str], timeout_s: float) -> dict:
    """Start ``cmd``; seconds until each of ``nodes`` is on the graph with its services ready; stop it."""
    observer = Observer({n: SERVICES.get(n, []) for n in nodes})
    proc = None
    pids: list[int] = []
    lines: list[tuple[float, str]] = []
    try:
        clear = observer.wait_clear()
        time.sleep(0.2)
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                bufsize=1, start_new_session=True)

        def read(stream) -> None:  # noqa: ANN001
            for line in stream:
                lines.append((time.monotonic() - t0, line.rstrip("\n")))
                started = STARTED.match(line)
                if started:
                    pids.append(int(started.group(2)))

        reader = threading.Thread(target=read, args=(proc.stdout,), daemon=True)
        reader.start()
        seen: dict[str, float] = {}
        ready: dict[str, float] = {}
        wanted = {s for n in nodes for s in node_services(n)}
        while True:
            now = time.monotonic() - t0
            for name in observer.visible() - set(seen):
                seen[name] = now
            for service in observer.ready() - set(ready):
                ready[service] = now
            if set(seen) == set(nodes) and set(ready) >= wanted:
                break
            if proc.poll() is not None or now > timeout_s:
                tail = "\n".join(line for _, line in lines[-30:])
                raise RuntimeError(f"not up after {now:.1f} s (exit code {proc.returncode}); on the graph: "
                                   f"{sorted(seen)}, services ready: {sorted(ready)}\n{tail}")
            time.sleep(POLL_S)
        up_s = max([*seen.values(), *ready.values()])
        cpu = {pid: cpu_s(pid) for pid in [proc.pid, *pids]}
        stop_s = stop_process(proc)
        reader.join(timeout=5.0)
    finally:
        if proc is not None and proc.poll() is None:
            stop_process(proc)
        leftover = stop_pids(pids)
        observer.close()
    per_node = {}
    started = {m.group(1): (t, int(m.group(2))) for t, line in lines if (m := STARTED.match(line))}
    running = {}
    for t, line in lines:
        if (m := RUNNING.match(line)) and m.group(1) not in running:
            running[m.group(1)] = t
    for name in nodes:
        start_t, pid = started.get(name, (0.0, proc.pid))
        per_node[name] = {
            "started_s": start_t,
            "running_s": running.get(name),
            "discovered_s": seen[name],
            "services_ready_s": max(ready[s] for s in node_services(name)),
            "cpu_s_at_up": cpu.get(pid),
            "service_ready_s": {s: ready[s] for s in node_services(name)},
        }
    return {"up_s": up_s, "stop_s": stop_s, "graph_clear_before": clear, "supervisor_cpu_s_at_up": cpu[proc.pid]
            if pids else None, "per_node": per_node, "exit_code": proc.returncode, "stopped_by_pid": leftover}


def import_seconds(code: str, env: dict[str, str]) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, check=True, stdout=subprocess.DEVNULL,
                   timeout=300)
    return time.perf_counter() - start


def import_tree(module: str, env: dict[str, str]) -> dict:
    """``python -X importtime``: the cumulative ms of each heavy package in a node process's imports."""
    code = f"import rclpy, rclpy.executors, t42_transfer.cli, {module}"
    out = subprocess.run([sys.executable, "-X", "importtime", "-c", code], cwd=REPO, env=env, check=True,
                         capture_output=True, text=True, timeout=300)
    rows = []  # (depth, cumulative us, module), children before their importer
    for line in out.stderr.splitlines():
        if not line.startswith("import time:") or "cumulative" in line:
            continue
        _, cumulative, name = line[len("import time:"):].split("|")
        rows.append(((len(name) - len(name.lstrip()) - 1) // 2, int(cumulative), name.strip()))
    heavy: dict[str, float] = {}
    chains: dict[str, list[str]] = {}
    for i, (depth, cumulative, name) in enumerate(rows):
        if name in HEAVY and name not in heavy:
            heavy[name] = cumulative / 1e3
            chain, level = [], depth
            for later_depth, _, later in rows[i + 1:]:  # the importer: the next row less deep
                if later_depth < level:
                    chain.append(later)
                    level = later_depth
            chains[name] = chain
    total = sum(cumulative for depth, cumulative, _ in rows if depth == 0) / 1e3
    return {"code": code, "total_ms": total, "cumulative_ms": heavy,
            "imported_by": {pkg: chains[pkg] for pkg in ("torch", "mujoco") if pkg in chains}}


def median(values: list[float]) -> float:
    return float(statistics.median(values))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="runs of each measure; medians (5)")
    parser.add_argument("--config", type=Path, default=CONFIG, help="the params file t42 up runs (configs/suite.yaml)")
    parser.add_argument("--only", default=None, help="comma-separated nodes of the config to run (t42 up --only)")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds a run may take to come up (120)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.runs < 1:
        parser.error("--runs must be >= 1")

    def on_term(signum: int, frame: FrameType | None) -> None:
        raise SystemExit(f"stopped by signal {signum}")  # the finally blocks stop what was started

    signal.signal(signal.SIGTERM, on_term)
    os.environ["ROS_DOMAIN_ID"] = os.environ.get("ROS_DOMAIN_ID") or str(random.randint(150, 230))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env = dict(os.environ)
    env.pop("T42_DEMO_DOMAIN", None)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    config = args.config.resolve()
    only = [n for n in args.only.split(",") if n] if args.only else None
    nodes = plan_nodes(config, only)
    suite_cmd = [sys.executable, "-m", "t42_transfer.cli", "up", str(config), *(["--only", args.only] if only else [])]
    bare_cmd = [sys.executable, "-c", BARE_NODE]
    late_cmd = [sys.executable, "-c", BARE_NODE, str(LATE_INIT_S)]

    machine = machine_info()
    load_before = os.getloadavg()
    started = time.monotonic()
    suite_runs, bare_runs, late_runs = [], [], []
    with tempfile.TemporaryDirectory(prefix="t42-startup-") as tmp:
        for i in range(args.runs):  # in turn, so both see the same load
            cwd = Path(tmp) / f"run{i}"
            cwd.mkdir()
            suite_runs.append(one_run(suite_cmd, nodes, cwd, env, args.timeout))
            bare_runs.append(one_run(bare_cmd, ["bare_node"], cwd, env, args.timeout))
            late_runs.append(one_run(late_cmd, ["bare_node"], cwd, env, args.timeout))
            print(f"run {i + 1}/{args.runs}: suite {suite_runs[-1]['up_s']:.2f} s, bare node "
                  f"{bare_runs[-1]['up_s']:.2f} s, bare node starting rclpy {LATE_INIT_S:g} s late "
                  f"{late_runs[-1]['up_s']:.2f} s", flush=True)
    load_after_runs = os.getloadavg()

    modules = {name: NODES[name].node.partition(":")[0] for name in nodes}
    imports = {"python (pass)": "pass", "rclpy": "import rclpy", "torch": "import torch",
               "mujoco": "import mujoco", "t42_transfer.cli": "import t42_transfer.cli"}
    imports |= {module: f"import {module}" for module in modules.values()}
    import_runs: dict[str, list[float]] = {label: [] for label in imports}
    for _ in range(args.runs):
        for label, code in imports.items():
            import_runs[label].append(import_seconds(code, env))
    trees = {name: import_tree(module, env) for name, module in modules.items()}

    suite_up = median([r["up_s"] for r in suite_runs])
    bare_up = median([r["up_s"] for r in bare_runs])
    per_node = {}
    for name in nodes:
        runs = [r["per_node"][name] for r in suite_runs]
        per_node[name] = {key: median([r[key] for r in runs if r[key] is not None])
                          for key in ("started_s", "running_s", "discovered_s", "services_ready_s", "cpu_s_at_up")
                          if any(r[key] is not None for r in runs)}
        per_node[name]["discovery_wait_s"] = median([r["services_ready_s"] - r["running_s"] for r in runs
                                                     if r["running_s"] is not None])
        per_node[name]["module"] = modules[name]
        per_node[name]["imports"] = {pkg: trees[name]["cumulative_ms"][pkg] / 1e3
                                     for pkg in ("torch", "mujoco") if pkg in trees[name]["cumulative_ms"]}
        per_node[name]["import_module_s"] = median(import_runs[modules[name]])
    slowest = max(per_node, key=lambda n: per_node[n]["services_ready_s"])
    result = {
        "benchmark": "startup",
        "command": " ".join(shlex.quote(a) for a in [".venv/bin/python", "bench/bench_startup.py", *sys.argv[1:]]),
        "machine": machine,
        "load_before": load_before,
        "load_after_runs": load_after_runs,
        "load_after": os.getloadavg(),
        "wall_s": time.monotonic() - started,
        "ros": {"domain_id": int(os.environ["ROS_DOMAIN_ID"]), "discovery_range": "LOCALHOST"},
        "env": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "RMW_IMPLEMENTATION")},
        "config": str(config.relative_to(REPO)) if config.is_relative_to(REPO) else str(config),
        "suite_command": " ".join(["python -m t42_transfer.cli up CONFIG", *(["--only", args.only] if only else [])])
        + " (t42 up), in an empty temporary working directory",
        "nodes": nodes,
        "ready_means": {n: node_services(n) for n in [*nodes, "bare_node"]},
        "runs": args.runs,
        "suite_up_s": suite_up,
        "bare_node_s": bare_up,
        "ratio_suite_over_bare": suite_up / bare_up,
        "bare_node_late_init_s": median([r["up_s"] for r in late_runs]),
        "late_init_s": LATE_INIT_S,
        "late_init_wait_s": median([r["up_s"] for r in late_runs]) - LATE_INIT_S,
        "suite_stop_s": median([r["stop_s"] for r in suite_runs]),
        "bare_stop_s": median([r["stop_s"] for r in bare_runs]),
        "suite_up_s_runs": [r["up_s"] for r in suite_runs],
        "bare_node_s_runs": [r["up_s"] for r in bare_runs],
        "bare_node_late_init_s_runs": [r["up_s"] for r in late_runs],
        "slowest_node": slowest,
        "per_node": per_node,
        "import_s": {label: median(times) for label, times in import_runs.items()},
        "import_s_runs": import_runs,
        "import_tree_ms": trees,
        "reference": REFERENCE,
        "runs_detail": {"suite": suite_runs, "bare": bare_runs, "bare_late_init": late_runs},
        "notes": "the observer is created before each run's process starts, as a test's rig node is; per_node "
                 "medians are seconds from starting t42 up (cpu_s_at_up: CPU seconds of the node's process when "
                 "the whole suite was up; discovery_wait_s: from its 'running' log line to its services ready); "
                 "bare_node_late_init_s: the bare node sleeping late_init_s before it imports rclpy; "
                 "imports: python -c 'import X' wall seconds, the "
                 "interpreter's own start included (python (pass)); import_tree_ms: python -X importtime, "
                 "cumulative ms of each package where first imported (nested ones inside their importer's)",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: result[k] for k in ("suite_up_s", "bare_node_s", "bare_node_late_init_s",
                                             "ratio_suite_over_bare", "slowest_node",
                                             "per_node", "import_s", "load_before", "load_after")}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
