"""The README's main job: the whole transfer story on simulated hands, as separate ROS 2 node processes.

1. **Source model**: random-action episodes of the simulated *source* hand go into
   a rosbag2 bag, and the paper's transition model is trained on it (cached in the
   output directory and reused while the demo's sizes stay the same).
2. **The suite** starts as separate rclpy processes on a private ROS domain (discovery
   kept on this machine), through the supervisor ``t42 up`` uses: the mock driver on the simulated *target* hand, the
   recorder, the transfer server and the planner.  The driver is the clock of the
   graph (``sim_time``, ``/clock``) and runs ``rate_factor`` times faster than real
   time; every other node runs with ``use_sim_time``.
3. **Target data through topics**: the explorer node (another process) resets the
   hand and sends random-action trajectories; it starts and stops the recorder,
   which writes one MCAP bag per episode.
4. **Transfer**: one call of ``/t42/transfer``; its progress arrives on
   ``/diagnostics``; the answer names the model, which the planner loads when the
   server announces it.
5. **Peg-in-hole**: for each goal the hand is reset; the goal is a point the true
   target hand reaches from that grasp in ``n`` steps, at least twice the
   tolerance from the start and from where holding still would leave the object;
   it is sent to the planner as a ``PointStamped``; the driver executes the
   planned ``JointTrajectory`` open loop; the rule of
   :func:`~t42_transfer.evaluation.peg_in_hole.verdict` decides success (completed,
   half way towards the goal at least, within the tolerance), and doing nothing
   is scored by the same rule on the same grasps.  The recorder records these
   episodes like any other.
6. **Second round**: ``/t42/transfer`` again, now with the executed plans among
   the episodes, then new goals of the same kind: does the suite improve with use?
   Each round's model is also scored on the same held-out target episodes
   (collected apart, never seen by the suite) beside the source model and the
   hold-still baseline.
7. **Report**: ``report.md``, ``demo.json`` and ``paths.png`` (planned vs executed
   paths) in the run directory; node logs in ``logs/``.
"""

from __future__ import annotations

import json
import os
import random
import re
import shutil
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from msg_adapters import RCLPY, goal_msg, names, object_xy_mm, path_xy_mm, stamp_to_ns, status_event, status_report
from t42_transfer.conventions import CONTROL_PERIOD_NS

SUITE_NODES = ("mock_driver", "recorder", "transfer_server", "planner")
TRANSFER_STATUS = "t42_transfer: transfer"
RECORDER_START = names.private_of("recorder", names.RECORDER_START)
RECORDER_STOP = names.private_of("recorder", names.RECORDER_STOP)
SERVICES = (names.HAND_RESET, names.TRANSFER, RECORDER_START, RECORDER_STOP)


@dataclass(frozen=True)
class DemoSize:
    source_episodes: int
    source_steps: int
    source_epochs: int
    target_episodes: int
    """Episodes the explorer collects from the target hand (a quarter is held out for scoring)."""
    target_steps: int
    goal_steps: tuple[int, ...]
    """One peg-in-hole goal per entry, that many control steps from the grasp."""
    planner_samples: int
    rate_factor: float
    rounds: int = 2
    """Transfer-then-goals rounds; from the second on, the transfer also learns from the executed plans."""
    heldout_episodes: int = 6
    """Random-policy target episodes collected apart (never recorded by the suite) to score each round's model."""
    transfer: dict[str, Any] = field(default_factory=dict)
    """Overrides of the transfer server's TransferConfig (nested; written to the YAML file its ``config`` names)."""


FULL = DemoSize(source_episodes=80, source_steps=400, source_epochs=40, target_episodes=12, target_steps=150,
                goal_steps=(30, 40, 50, 60, 30, 40, 50, 60), planner_samples=250, rate_factor=5.0)
QUICK = DemoSize(source_episodes=10, source_steps=150, source_epochs=5, target_episodes=4, target_steps=60,
                 goal_steps=(30, 40), planner_samples=100, rate_factor=10.0, heldout_episodes=3,
                 transfer={"l2_finetune": {"train": {"epochs": 10}}})
TOLERANCE_MM = 10.0
"""The paper's peg-in-hole tolerance."""
MIN_GOAL_DISTANCE_MM = 2 * TOLERANCE_MM
"""Goals lie at least this far from the start and from where holding still ends: doing nothing scores 0."""
HELDOUT_SEED = 99
HOLD_STEPS = (5, 40)
SETTLE_STEPS = 80
"""Steps of holding still after a grasp: the simulated object has stopped sinking by then."""
GRASP_MATCH_MM = 1.0


def _say(message: str) -> None:
    print(message, flush=True)


# --------------------------------------------------------------------------- 1. source model
def source_model(out: Path, size: DemoSize, workers: int | None) -> Path:
    """The source model for ``size`` under ``out`` (trained unless a matching one is cached)."""
    import torch

    from t42_transfer.data.bag import assign_start_times, read_bag, write_bag
    from t42_transfer.data.trajectory import TrajectorySet
    from t42_transfer.hand.collect import collect
    from t42_transfer.models.checkpoint import read_metadata, save_model
    from t42_transfer.models.training import ProgressBar, TrainConfig, train_transition_model
    from t42_transfer.planning.workspace import Workspace

    key = {"episodes": size.source_episodes, "steps": size.source_steps, "epochs": size.source_epochs, "seed": 0}
    path = out / f"source_model_{size.source_episodes}x{size.source_steps}.safetensors"
    if path.is_file():
        try:
            if read_metadata(path).get("data", {}).get("demo") == key:
                _say(f"[1/{4 + size.rounds}] source model: cached {path}")
                return path
        except Exception:
            pass
    start = time.perf_counter()
    data, stats = collect("source", size.source_episodes, size.source_steps, seed=0, workers=workers)
    bag_dir = out / f"source_bag_{size.source_episodes}x{size.source_steps}"
    if bag_dir.exists():
        shutil.rmtree(bag_dir)
    bag = write_bag(bag_dir, TrajectorySet(assign_start_times(data), hand=data.hand), metadata={"collector": "t42 demo"})
    data = read_bag(bag)
    torch.set_num_threads(1)
    model, report = train_transition_model(data, TrainConfig(epochs=size.source_epochs), on_epoch=ProgressBar(),
                                           phase="source model")
    extra = {"workspace": Workspace.from_trajectories(data).to_dict()}
    save_model(model, path, method="source", data={"demo": key, "source": data.fingerprint()}, extra=extra)
    _say(f"[1/{4 + size.rounds}] source model: {len(data)} source-hand episodes ({data.num_transitions} transitions) "
         f"-> {bag}; "
         f"{report.epochs_run} epochs -> {path} ({time.perf_counter() - start:.0f} s)")
    return path


# --------------------------------------------------------------------------- 2. the suite
def suite_params(run_dir: Path, model: Path, size: DemoSize) -> dict[str, Any]:
    """The params file of the suite (and the explorer) for this run; method settings go to their own file."""
    methods = run_dir / "transfer_methods.yaml"
    methods.write_text(yaml.safe_dump(size.transfer, sort_keys=False))

    def node(**params: Any) -> dict[str, Any]:
        return {"ros__parameters": params}

    sections = {
        # Stamps are in simulated time, which runs rate_factor times faster: allow the same wall-time lag.
        "mock_driver": node(hand="target", rate_factor=size.rate_factor, seed=0, sim_time=True,
                            max_command_age_s=0.5 * size.rate_factor),
        "recorder": node(out_dir=str(run_dir / "bags"), mode="episode", start_immediately=False, use_sim_time=True),
        "transfer_server": node(source_model=str(model), model_dir=str(run_dir / "models"),
                                bag_dir=str(run_dir / "bags"),
                                new_bags_only=False, config=str(methods), use_sim_time=True),
        "planner": node(samples=size.planner_samples, max_state_age_s=0.5 * size.rate_factor, use_sim_time=True),
        "explorer": node(episodes=size.target_episodes, steps=size.target_steps, seed=1,
                         rate_factor=size.rate_factor, record_start_service=RECORDER_START,
                         record_stop_service=RECORDER_STOP, use_sim_time=True),
    }
    return {f"/**/{name}": section for name, section in sections.items()}


def _operator_class() -> type:
    """The demo's own rclpy node class (imported late: ``t42 demo --help`` needs no ROS)."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PointStamped, PoseStamped
    from nav_msgs.msg import Path as PathMsg
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from t42_transfer.ros.qos import profile

    class Operator(Node):
        """Watches the hand and the suite's outputs, calls services, sends goals; spun by a background executor."""

        def __init__(self, **node_kwargs: Any) -> None:
            super().__init__("t42_demo", parameter_overrides=[Parameter("use_sim_time", value=True)], **node_kwargs)
            self.poses: list[tuple[int, np.ndarray]] = []
            self.applied = 0
            self.statuses: list[str] = []
            self.results: list[dict[str, Any]] = []
            self.paths: list[np.ndarray] = []
            self.diagnostic: dict[str, str] = {}
            self.create_subscription(PoseStamped, names.OBJECT_POSE, self._on_pose, 100)
            self.create_subscription(JointState, names.APPLIED_ACTION, self._on_applied, 100, raw=True)
            self.create_subscription(String, names.HAND_STATUS, lambda m: self.statuses.append(m.data),
                                     profile(names.EVENTS))
            self.create_subscription(String, names.PLAN_RESULT, lambda m: self.results.append(json.loads(m.data)), 10)
            self.create_subscription(PathMsg, names.PLANNED_PATH, lambda m: self.paths.append(path_xy_mm(m)), 10)
            self.create_subscription(DiagnosticArray, names.DIAGNOSTICS, self._on_diagnostics, 10)
            self.goal_pub = self.create_publisher(PointStamped, names.GOAL, 10)
            self.trigger_clients = {name: self.create_client(Trigger, name) for name in SERVICES}

        def _on_pose(self, msg: Any) -> None:
            self.poses.append((stamp_to_ns(msg.header.stamp), object_xy_mm(msg).astype(np.float64)))
            del self.poses[:-2000]

        def _on_applied(self, data: bytes) -> None:
            self.applied += 1

        def _on_diagnostics(self, msg: Any) -> None:
            try:
                report = status_report(msg, TRANSFER_STATUS)
            except KeyError:
                return
            self.diagnostic = {"message": report.message, **report.values}

        def ready(self) -> bool:
            return all(c.service_is_ready() for c in self.trigger_clients.values())

        def wait_until(self, cond: Any, timeout_s: float, what: str, alive: Any = None, progress: Any = None) -> None:
            """Wait (the executor thread spins) until ``cond()``; ``alive()`` raises if a node died."""
            deadline = time.monotonic() + timeout_s
            while not cond():
                if time.monotonic() > deadline:
                    raise TimeoutError(f"timed out after {timeout_s:.0f} s waiting for {what}")
                if alive is not None:
                    alive()
                if progress is not None:
                    progress()
                time.sleep(0.05)

        def call(self, service: str, timeout_s: float, alive: Any = None, progress: Any = None) -> Any:
            """Call a Trigger service and wait for its answer (showing progress meanwhile)."""
            future = self.trigger_clients[service].call_async(Trigger.Request())
            self.wait_until(future.done, timeout_s, f"the answer of {service}", alive, progress)
            if future.exception() is not None:
                raise RuntimeError(f"{service}: {future.exception()}")
            return future.result()

        def latest_pose(self) -> tuple[int, np.ndarray]:
            return self.poses[-1] if self.poses else (-1, np.full(2, np.nan))

        def now_ns(self) -> int:
            return self.get_clock().now().nanoseconds

    return Operator


class _Suite:
    """The node processes of one demo run, with their output in ``logs/``."""

    def __init__(self, run_dir: Path, params_file: Path, env: dict[str, str]) -> None:
        from t42_transfer.ros.launcher import Supervisor

        (run_dir / "logs").mkdir(exist_ok=True)
        self.log_path = run_dir / "logs" / "nodes.log"
        self.log = self.log_path.open("w")
        self.supervisor = Supervisor(params_file, out=self.log, stop_timeout_s=10.0, env=env)
        self.may_end: set[str] = set()
        """Nodes whose exit is not a failure (the explorer ends when done)."""

    def check(self) -> None:
        """Raise if a suite node died."""
        dead = [c for c in self.supervisor.children if c.proc.poll() is not None and c.name not in self.may_end]
        if dead:
            names = ", ".join(f"{c.name} (exit {c.proc.returncode})" for c in dead)
            raise RuntimeError(f"node process ended: {names}; see {self.log_path}")

    def stop(self) -> dict[str, int]:
        codes = self.supervisor.stop()
        self.log.close()
        return codes


# --------------------------------------------------------------------------- 5. peg-in-hole
@dataclass
class GoalRun:
    steps: int
    grasp_seed: int
    goal_mm: list[float]
    start_mm: list[float]
    accepted: bool
    status: str
    reason: str
    horizon: int = 0
    predicted_error_mm: float | None = None
    planning_time_s: float = 0.0
    """The planner's own planning time."""
    goal_to_result_s: float = 0.0
    """Wall time from publishing the goal to receiving the plan result (published after the sequence)."""
    final_mm: list[float] | None = None
    error_mm: float | None = None
    end: str = ""
    success: bool = False
    verdict: str = ""
    """:func:`~t42_transfer.evaluation.peg_in_hole.verdict` at ``TOLERANCE_MM``."""
    still_error_mm: float = 0.0
    """Where holding still for the goal's steps leaves the object, from the goal (the same grasp and noise)."""
    still_verdict: str = ""
    """The same rule applied to doing nothing."""
    round: int = 1
    planned: list[list[float]] = field(default_factory=list)
    executed: list[list[float]] = field(default_factory=list)

    @property
    def start_distance_mm(self) -> float:
        return float(np.linalg.norm(np.subtract(self.goal_mm, self.start_mm)))


def _grasp_seed(message: str) -> int:
    match = re.search(r"\(seed (-?\d+)\)", message)
    if match is None:
        raise RuntimeError(f"cannot tell the grasp seed from the reset answer {message!r}")
    return int(match.group(1))


def _wait_for_closed_bags(op: Any, suite: _Suite, bag_dir: Path) -> list[Path]:
    """The episode bags once the recorder has closed them all: a stop completes after the step in progress,
    and a transfer uses finished bags only."""
    def bags() -> list[Path]:
        return sorted(bag_dir.glob("episode_*"))

    op.wait_until(lambda: all((p / "metadata.yaml").is_file() for p in bags()), 30.0,
                  "the recorder to close its bags", suite.check)
    return bags()


def run_goal(op: Any, suite: _Suite, steps: int, index: int, workspace: Any, round_: int = 1) -> GoalRun:
    from t42_transfer.hand.sim import SimulatedHand
    from t42_transfer.evaluation.peg_in_hole import progress_towards, reachable_goal, verdict

    response = op.call(names.HAND_RESET, 30.0, suite.check)
    if not response.success:
        raise RuntimeError(f"reset failed: {response.message}")
    seed = _grasp_seed(response.message)
    reset_stamp = op.latest_pose()[0]
    seeds = (int(np.random.SeedSequence([7, round_, index, attempt]).generate_state(1)[0]) for attempt in range(50))
    goal = reachable_goal(SimulatedHand("target"), steps, HOLD_STEPS, seeds, workspace, grasp_seed=seed, trial=index,
                          settle_steps=SETTLE_STEPS, min_distance_mm=MIN_GOAL_DISTANCE_MM)
    still_error = float(goal.still_distance_mm)
    still = verdict(goal.distance_mm, still_error,
                    progress_towards(goal.grasp[:2], goal.position, goal.still), True, TOLERANCE_MM)
    # After a grasp the object sinks into the fingers for a few seconds: the goal is made from the
    # settled state (the same seed grasps and settles identically here and in the driver), and the
    # goal is sent once the driver's hand has held still that long and rests there.
    settled = reset_stamp + SETTLE_STEPS * CONTROL_PERIOD_NS

    def at_grasp() -> bool:
        stamp, xy = op.latest_pose()
        return stamp > settled and float(np.linalg.norm(xy - goal.grasp[:2])) < GRASP_MATCH_MM

    op.wait_until(at_grasp, 30.0, f"the object at the new grasp {goal.grasp[:2].round(1).tolist()} mm", suite.check)
    start = op.latest_pose()[1]
    results = len(op.results)
    paths = len(op.paths)
    sent = time.perf_counter()
    op.goal_pub.publish(goal_msg(goal.position, op.now_ns(), RCLPY))
    op.wait_until(lambda: len(op.results) > results, 60.0, "the planner's result", suite.check)
    answered_s = time.perf_counter() - sent
    result = op.results[results]
    run = GoalRun(steps, seed, goal.position.tolist(), start.tolist(), result["accepted"], result["status"],
                  result["reason"], result["horizon"], result["predicted_error_mm"], result["planning_time_s"],
                  goal_to_result_s=answered_s, still_error_mm=still_error, still_verdict=still, round=round_)
    if not run.accepted:
        run.end = "not executed"
        run.verdict = "incomplete"
        return run
    op.wait_until(lambda: len(op.paths) > paths, 10.0, "the planned path", suite.check)
    run.planned = op.paths[paths].tolist()
    plan_stamp = op.latest_pose()[0]
    statuses = len(op.statuses)
    settle = plan_stamp + (run.horizon + 5) * CONTROL_PERIOD_NS  # the plan, then five steps of holding still

    def ends() -> list[str]:  # the episode's end events (a drop...): trajectory_done is not one
        return [e for e in map(status_event, op.statuses[statuses:]) if e in names.END_EVENTS]

    op.wait_until(lambda: op.latest_pose()[0] >= settle or ends(), 120.0, "the plan's execution", suite.check)
    run.executed = [xy.tolist() for stamp, xy in op.poses if stamp >= plan_stamp]
    run.final_mm = op.latest_pose()[1].tolist()
    run.error_mm = float(np.linalg.norm(np.subtract(run.final_mm, run.goal_mm)))
    ended = ends()
    run.end = ended[0] if ended else "completed"
    run.verdict = verdict(run.start_distance_mm, run.error_mm,
                          progress_towards(np.asarray(run.start_mm), goal.position, np.asarray(run.final_mm)),
                          not ended, TOLERANCE_MM)
    run.success = run.verdict == "hit"
    return run


# --------------------------------------------------------------------------- 6. report
def plot_paths(runs: list[GoalRun], path: Path) -> Path:
    from t42_transfer.plots import pyplot, save

    plt = pyplot()

    cols = min(4, max(1, len(runs)))
    rows = (len(runs) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.2 * rows), squeeze=False)
    for ax, run in zip(axes.flat, runs):
        if run.planned:
            planned = np.asarray(run.planned)
            ax.plot(planned[:, 0], planned[:, 1], "--", color="tab:blue", label="planned")
        if run.executed:
            executed = np.asarray(run.executed)
            ax.plot(executed[:, 0], executed[:, 1], "-", color="tab:orange", label="executed")
        ax.plot(*run.start_mm, "ko", ms=4, label="start")
        ax.add_patch(plt.Circle(run.goal_mm, TOLERANCE_MM, color="tab:green", alpha=0.2))
        ax.plot(*run.goal_mm, "g*", ms=10, label="goal")
        verdict = run.verdict if run.accepted else "refused"
        error = "" if run.error_mm is None else f", {run.error_mm:.1f} mm"
        ax.set_title(f"round {run.round}, {run.steps} steps: {verdict}{error}", fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (mm)", fontsize=8)
        ax.set_ylabel("y (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(runs):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7, loc="best")
    fig.suptitle(f"peg-in-hole on the simulated target hand (tolerance {TOLERANCE_MM:g} mm)", fontsize=10)
    return save(fig, path)


def goal_table(runs: list[GoalRun]) -> str:
    lines = ["| round | goal | steps | start->goal mm | plan | predicted mm | final error mm | end | verdict "
             "| doing nothing: error mm |",
             "|---:|---:|---:|---:|---|---:|---:|---|---|---:|"]
    for k, run in enumerate(runs):
        predicted = "" if run.predicted_error_mm is None else f"{run.predicted_error_mm:.1f}"
        error = "" if run.error_mm is None else f"{run.error_mm:.1f}"
        plan = f"{run.horizon} steps" if run.accepted else f"refused ({run.status})"
        lines.append(f"| {run.round} | {k + 1} | {run.steps} | {run.start_distance_mm:.1f} | {plan} | {predicted} "
                     f"| {error} | {run.end} | {run.verdict} | {run.still_error_mm:.1f} ({run.still_verdict}) |")
    return "\n".join(lines)


def rounds_table(rounds: list[dict[str, Any]]) -> str:
    """Per round: success against doing nothing, and divergence on the held-out episodes against the baselines."""
    lines = ["| round | target episodes used | goals hit | doing nothing hits | held-out divergence, model (steps) "
             "| source alone | hold still |",
             "|---:|---:|---|---|---:|---:|---:|"]
    for r in rounds:
        d = r["heldout"]
        lines.append(f"| {r['round']} | {r['episodes']} | {r['hits']}/{r['goals']} | {r['still_hits']}/{r['goals']} "
                     f"| {d['model']:.1f} | {d['source']:.1f} | {d['hold_still']:.1f} |")
    return "\n".join(lines)


def heldout_scores(model_path: str | Path, source: str | Path, episodes: Any) -> dict[str, float]:
    """Mean divergence steps (4 mm) of the round's model, the source and holding still on ``episodes``."""
    from t42_transfer.evaluation.metrics import evaluate_model
    from t42_transfer.models.baselines import HoldStill
    from t42_transfer.models.checkpoint import load_model

    models = {"model": load_model(model_path)[0], "source": load_model(source)[0], "hold_still": HoldStill()}
    return {name: float(evaluate_model(m, episodes)["divergence_mean"]) for name, m in models.items()}


def write_report(run_dir: Path, summary: dict[str, Any], runs: list[GoalRun]) -> Path:
    lines = [
        "# t42 demo",
        "",
        f"Run {run_dir.name}: {summary['mode']}; suite of rclpy nodes over {summary['middleware']} on ROS domain "
        f"{summary['domain']} (discovery {summary['discovery']}).",
        "",
        "## Data and transfer",
        "",
        f"- Source model: `{summary['source_model']}`.",
        f"- Target data: {summary['exploration']['bags']} explored episode bags recorded through topics in `bags/`, "
        "then each goal's episode.",
        *(f"- Round {r['round']}: `/t42/transfer` answered in {r['transfer']['seconds']:.1f} s: "
          f"{r['transfer']['message']}" for r in summary["rounds"]),
        "",
        "## Rounds",
        "",
        f"Goals hit within {TOLERANCE_MM:g} mm (open loop; completed, at least half way, within the tolerance), "
        "doing nothing scored by the same rule on the same grasps, and the divergence time (4 mm) of each "
        f"round's model on {summary['heldout']['episodes']} held-out target episodes the suite never saw.",
        "",
        rounds_table(summary["rounds"]),
        "",
        "## Peg-in-hole goals",
        "",
        goal_table(runs),
        "",
        "![planned vs executed paths](paths.png)",
        "",
    ]
    path = run_dir / "report.md"
    path.write_text("\n".join(lines))
    return path


# --------------------------------------------------------------------------- the story
def _transfer(op: Any, suite: _Suite, summary: dict[str, Any], round_: int, rounds: int) -> dict[str, Any]:
    """One call of /t42/transfer with its progress shown; the round's record (the model it made)."""
    t0, last = time.perf_counter(), [""]

    def progress() -> None:
        d = op.diagnostic
        line = f"      transfer: {d.get('stage', 'starting')}"
        if "epoch" in d:
            line += f" epoch {d['epoch']}/{d.get('epochs', '?')}"
        if line != last[0]:
            last[0] = line
            _say(line)

    response = op.call(names.TRANSFER, 1800.0, suite.check, progress)
    transfer = {"success": bool(response.success), "message": response.message,
                "seconds": time.perf_counter() - t0, "diagnostics": op.diagnostic}
    _say(f"[{4 + round_ - 1}/{4 + rounds}] round {round_}: /t42/transfer ({transfer['seconds']:.0f} s): "
         f"{response.message}")
    if not response.success:
        raise RuntimeError(f"the transfer failed: {response.message}")
    match = re.search(r"(\S+\.safetensors)", response.message)
    if match is None:
        raise RuntimeError(f"the transfer answer names no model file: {response.message!r}")
    trained = re.search(r"trained on (\d+) episodes", response.message)
    return {"round": round_, "transfer": transfer, "model": match.group(1).rstrip(".,;:)"),
            "episodes": int(trained.group(1)) if trained else None}


def run_demo(out: Path, quick: bool = False, workers: int | None = None) -> int:
    """Run the whole story (see the module docstring); 0 when every step completed."""
    import rclpy
    from rclpy.executors import MultiThreadedExecutor

    from t42_transfer.hand.collect import collect
    from t42_transfer.models.checkpoint import read_metadata
    from t42_transfer.planning.workspace import Workspace
    from t42_transfer.ros.runner import keep_discovery_local

    size = QUICK if quick else FULL
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    run_dir = out / time.strftime("%Y%m%d-%H%M%S")
    run_dir.mkdir(parents=False, exist_ok=False)
    started = time.perf_counter()
    _say(f"t42 demo{' --quick' if quick else ''}: transfer to a new simulated hand over ROS 2 -> {run_dir}")
    model = source_model(out, size, workers)
    workspace = Workspace.from_dict(read_metadata(model)["extra"]["workspace"])

    params_file = run_dir / "suite.yaml"
    params_file.write_text(yaml.safe_dump(suite_params(run_dir, model, size), sort_keys=False))
    domain = int(os.environ.get("T42_DEMO_DOMAIN") or os.environ.get("ROS_DOMAIN_ID") or random.randint(100, 230))
    discovery = keep_discovery_local()
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1")
    suite = _Suite(run_dir, params_file, env)
    summary: dict[str, Any] = {"mode": "quick" if quick else "full", "size": asdict(size), "domain": domain,
                               "discovery": discovery, "middleware": "",
                               "source_model": str(model), "suite": str(params_file)}
    runs: list[GoalRun] = []
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    executor = MultiThreadedExecutor(context=context)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    try:
        summary["middleware"] = rclpy.get_rmw_implementation_identifier()
        for name in SUITE_NODES:
            suite.supervisor.start(name)
        op = _operator_class()(context=context)
        executor.add_node(op)
        spinner.start()
        op.wait_until(op.ready, 120.0, "the suite's services", suite.check)
        _say(f"[2/{4 + size.rounds}] suite up: {', '.join(SUITE_NODES)} as processes on ROS domain {domain} "
             f"({time.perf_counter() - started:.0f} s); logs in {suite.log_path}")

        explorer = suite.supervisor.start("explorer")
        suite.may_end.add("explorer")
        t0, shown = time.perf_counter(), -1

        def explored() -> bool:
            nonlocal shown
            episodes = sum(status_event(s) == names.RESET for s in op.statuses) - 1
            if episodes != shown and episodes >= 1:
                shown = episodes
                _say(f"      exploring: episode {min(episodes, size.target_episodes)}/{size.target_episodes}")
            return explorer.proc.poll() is not None

        op.wait_until(explored, 60.0 + size.target_episodes * size.target_steps * 0.1 / size.rate_factor * 5,
                      "the explorer", suite.check)
        if explorer.proc.returncode != 0:
            raise RuntimeError(f"explorer exited with code {explorer.proc.returncode}; see {suite.log_path}")
        bags = _wait_for_closed_bags(op, suite, run_dir / "bags")
        summary["exploration"] = {"episodes": size.target_episodes, "steps": size.target_steps, "bags": len(bags)}
        _say(f"[3/{4 + size.rounds}] target data: {len(bags)} episode bags recorded through topics "
             f"({time.perf_counter() - t0:.0f} s) in {run_dir / 'bags'}")

        heldout, _ = collect("target", size.heldout_episodes, size.target_steps, seed=HELDOUT_SEED, workers=workers)
        summary["heldout"] = {"episodes": len(heldout), "steps": size.target_steps, "seed": HELDOUT_SEED}
        summary["rounds"] = []
        for round_ in range(1, size.rounds + 1):
            record = _transfer(op, suite, summary, round_, size.rounds)
            record["heldout"] = heldout_scores(record["model"], model, heldout)
            _say(f"      held-out divergence: model {record['heldout']['model']:.1f} steps, source "
                 f"{record['heldout']['source']:.1f}, hold still {record['heldout']['hold_still']:.1f}")
            ok = op.call(RECORDER_START, 30.0, suite.check)
            if not ok.success:
                raise RuntimeError(f"{RECORDER_START}: {ok.message}")
            mine = []
            for index, steps in enumerate(size.goal_steps):
                run = run_goal(op, suite, steps, index, workspace, round_)
                mine.append(run)
                error = "" if run.error_mm is None else f" final error {run.error_mm:.1f} mm"
                verdict = run.verdict if run.accepted else f"refused: {run.reason}"
                _say(f"      round {round_} goal {index + 1}/{len(size.goal_steps)} ({steps} steps, "
                     f"{run.start_distance_mm:.1f} mm away):{error} -> {verdict} (doing nothing: "
                     f"{run.still_error_mm:.1f} mm, {run.still_verdict})")
            op.call(RECORDER_STOP, 30.0, suite.check)
            _wait_for_closed_bags(op, suite, run_dir / "bags")
            runs.extend(mine)
            record.update(goals=len(mine), hits=sum(r.success for r in mine),
                          still_hits=sum(r.still_verdict == "hit" for r in mine))
            summary["rounds"].append(record)
            _say(f"[{4 + round_ - 1}/{4 + size.rounds}] round {round_}: {record['hits']}/{record['goals']} goals hit "
                 f"(doing nothing: {record['still_hits']}/{record['goals']})")
        summary["transfer"] = summary["rounds"][0]["transfer"]
    except (RuntimeError, TimeoutError) as err:
        _say(f"FAILED: {err}")
        failed = True
    else:
        failed = False
    finally:  # whatever happened (Ctrl-C, a bug), no node process outlives the demo
        _shutdown(executor, context)
        codes = suite.stop()
    summary["exit_codes"] = codes
    if failed:
        (run_dir / "demo.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
        _tail(suite.log_path)
        return 1
    summary["goals"] = [asdict(r) for r in runs]
    summary["seconds"] = time.perf_counter() - started
    (run_dir / "demo.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
    plot_paths(runs, run_dir / "paths.png")
    report = write_report(run_dir, summary, runs)
    _say(f"[{4 + size.rounds}/{4 + size.rounds}] peg-in-hole, {size.rounds} round(s):\n")
    _say(rounds_table(summary["rounds"]))
    _say("")
    _say(goal_table(runs))
    _say(f"\nreport: {report} (plots: {run_dir / 'paths.png'}); {summary['seconds']:.0f} s in all")
    unclean = {n: c for n, c in codes.items() if c != 0 and n != "explorer"}
    if unclean:
        _say(f"FAILED: nodes did not stop cleanly: {unclean}; see {suite.log_path}")
        return 1
    return 0


def _shutdown(executor: Any, context: Any) -> None:
    import rclpy

    executor.shutdown(timeout_sec=5.0)
    for node in executor.get_nodes():
        node.destroy_node()
    if context.ok():
        rclpy.shutdown(context=context)


def _tail(path: Path, lines: int = 25) -> None:
    try:
        text = path.read_text().splitlines()[-lines:]
    except OSError:
        return
    print("\n".join(["--- last node log lines ---", *text]), file=sys.stderr)
