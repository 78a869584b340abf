"""The demo's story in phases (see :mod:`t42_transfer.demo`): start the suite, explore, transfer and plan in rounds."""

from __future__ import annotations

import json
import os
import random
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

from msg_adapters import names, status_event
from t42_transfer.demo.goals import GoalRun, closed_bags, run_goal
from t42_transfer.demo.report import goal_table, plot_paths, rounds_table, write_report
from t42_transfer.demo.settings import (
    DRIVER,
    HELDOUT_SEED,
    POSE_SOURCE,
    RECORDER_START,
    RECORDER_STOP,
    DemoSize,
    demo_size,
    suite_nodes,
)
from t42_transfer.demo.suite import Suite, say, servo_link, source_model, suite_params


@dataclass
class Story:
    """What the phases of one run share: its sizes, directory, source model, suite and the operator node."""

    size: DemoSize
    hardware: str
    """``sim`` (the mock driver) or ``emulated`` (the Dynamixel driver on the emulated servo bus)."""
    run_dir: Path
    model: Path
    workspace: Any
    suite: Suite
    op: Any = None
    heldout: Any = None
    """Target episodes collected apart (never recorded by the suite) that score each round's model."""
    summary: dict[str, Any] = field(default_factory=dict)
    runs: list[GoalRun] = field(default_factory=list)
    spinner: threading.Thread | None = None
    """The thread spinning the operator's executor (:meth:`Operator.spin`)."""
    stop_spinning: threading.Event = field(default_factory=threading.Event)
    update: bool = True
    """False: the transfer runs in round 1 only, and later rounds plan with its model (a loop that never updates)."""

    @property
    def phases(self) -> int:
        """Numbered lines of the story: source, suite, data, one per round, the report."""
        return 4 + self.size.rounds


def run_demo(out: Path, quick: bool = False, workers: int | None = None, hardware: str = "sim",
             rounds: int | None = None, goals: int | None = None, update: bool = True) -> int:
    """Run the whole story (see the package docstring) on ``hardware``; 0 when every step completed.

    ``rounds`` and ``goals`` (per round, their lengths cycling through the size's) lengthen the online loop;
    ``update=False`` transfers in round 1 only, the loop that never updates its model, to set beside it."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from t42_transfer.models.checkpoint import read_metadata
    from t42_transfer.planning.workspace import Workspace
    from t42_transfer.ros.runner import keep_discovery_local

    size = demo_size(quick, rounds, goals)
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    run_dir = out / time.strftime("%Y%m%d-%H%M%S")
    run_dir.mkdir(parents=False, exist_ok=False)
    started = time.perf_counter()
    on = {"sim": "", "emulated": " (the Dynamixel driver on an emulated servo bus)",
          "camera": " (seen by a camera: rendered frames, the object tracker)"}[hardware]
    say(f"t42 demo{' --quick' if quick else ''}: transfer to a new simulated hand{on} over ROS 2 -> {run_dir}")
    model = source_model(out, size, workers)
    params_file = run_dir / "suite.yaml"
    params_file.write_text(yaml.safe_dump(suite_params(run_dir, model, size, hardware), sort_keys=False))
    domain = int(os.environ.get("T42_DEMO_DOMAIN") or os.environ.get("ROS_DOMAIN_ID") or random.randint(100, 230))
    discovery = keep_discovery_local()
    suite = Suite(run_dir, params_file, dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1"))
    story = Story(size, hardware, run_dir, model, Workspace.from_dict(read_metadata(model)["extra"]["workspace"]),
                  suite, update=update)
    story.summary = {"mode": "quick" if quick else "full", "update": update, "hardware": hardware,
                     "driver": DRIVER[hardware], "pose_source": POSE_SOURCE[hardware], "size": asdict(size),
                     "domain": domain, "discovery": discovery, "middleware": "", "source_model": str(model),
                     "suite": str(params_file)}
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    executor = SingleThreadedExecutor(context=context)
    failed = True
    try:
        story.summary["middleware"] = rclpy.get_rmw_implementation_identifier()
        _start_suite(story, executor, context, started)
        _explore(story, workers)
        for round_ in range(1, size.rounds + 1):
            _round(story, round_)
        story.summary["executed_plans"] = executed_plans(story)
        story.summary["transfer"] = story.summary["rounds"][0]["transfer"]
        failed = False
    except (RuntimeError, TimeoutError) as err:
        say(f"FAILED: {err}")
    finally:  # whatever happened (Ctrl-C, a bug), no node process outlives the demo
        story.stop_spinning.set()
        _shutdown(executor, context, story.spinner)
        story.summary["exit_codes"] = suite.stop()
    return _finish(story, failed, started)


def _start_suite(story: Story, executor: Any, context: Any, started: float) -> None:
    from t42_transfer.demo.operator import Operator, wait_until

    suite, nodes = story.suite, suite_nodes(story.hardware)
    for name in nodes:
        suite.supervisor.start(name)
        if name == "hw_emulator":  # the driver opens the bus at start: the emulator's pty must be there first
            link = servo_link(story.run_dir)
            wait_until(link.exists, 60.0, f"the emulated servo bus at {link}", suite.check)
    story.op = Operator(context=context)
    executor.add_node(story.op)
    story.spinner = threading.Thread(target=story.op.spin, args=(executor, story.stop_spinning), daemon=True)
    story.spinner.start()
    story.op.wait_until(story.op.ready, 120.0, "the suite's services", suite.check)
    if story.hardware == "emulated":
        wait_until(lambda: story.op.lifecycle_state("dynamixel_driver", 10.0, suite.check) == "active", 60.0,
                   "the Dynamixel driver to be active", suite.check)
    say(f"[2/{story.phases}] suite up: {', '.join(nodes)} as processes on ROS domain "
        f"{story.summary['domain']} ({time.perf_counter() - started:.0f} s); logs in {story.suite.log_path}")


def _explore(story: Story, workers: int | None) -> None:
    """The explorer node records target episodes through topics; held-out episodes are collected apart."""
    from t42_transfer.hand.collect import collect

    op, suite, size = story.op, story.suite, story.size
    since = len(op.bags_closed)
    explorer = suite.supervisor.start("explorer")
    suite.may_end.add("explorer")
    t0, shown = time.perf_counter(), -1

    def explored() -> bool:
        nonlocal shown
        episodes = sum(status_event(s) == names.RESET for s in op.statuses) - 1
        if episodes != shown and episodes >= 1:
            shown = episodes
            say(f"      exploring: episode {min(episodes, size.target_episodes)}/{size.target_episodes}")
        return explorer.proc.poll() is not None

    op.wait_until(explored, 60.0 + size.target_episodes * size.target_steps * 0.1 / size.rate_factor * 5,
                  "the explorer", suite.check)
    if explorer.proc.returncode != 0:
        raise RuntimeError(f"explorer exited with code {explorer.proc.returncode}; see {suite.log_path}")
    bags = closed_bags(op, suite, since)
    story.summary["exploration"] = {"episodes": size.target_episodes, "steps": size.target_steps, "bags": len(bags),
                                    "bags_closed": [bag._asdict() for bag in bags]}
    say(f"[3/{story.phases}] target data: {len(bags)} episode bags recorded through topics "
        f"({time.perf_counter() - t0:.0f} s) in {story.run_dir / 'bags'}")
    heldout, _ = collect("target", size.heldout_episodes, size.target_steps, seed=HELDOUT_SEED, workers=workers)
    story.summary["heldout"] = {"episodes": len(heldout), "steps": size.target_steps, "seed": HELDOUT_SEED}
    story.summary["rounds"] = []
    story.heldout = heldout


def _round(story: Story, round_: int) -> None:
    """Transfer, score the model on the held-out episodes, then the round's goals, recorded like any episode."""
    op, suite, size = story.op, story.suite, story.size
    record = transfer(story, round_) if story.update or round_ == 1 else _kept(story, round_)
    record["heldout"] = heldout_scores(record["model"], story.model, story.heldout)
    say(f"      held-out divergence: model {record['heldout']['model']:.1f} steps, source "
        f"{record['heldout']['source']:.1f}, hold still {record['heldout']['hold_still']:.1f}")
    since = len(op.bags_closed)

    def start_recording() -> None:
        """Called after the first goal's reset: a bag opened before it would hold only a few steps of the hand
        still holding the last object, too short to train on."""
        ok = op.call(RECORDER_START, 30.0, suite.check)
        if not ok.success:
            raise RuntimeError(f"{RECORDER_START}: {ok.message}")

    mine = []
    for index, steps in enumerate(size.goal_steps):
        run = run_goal(op, suite, steps, index, story.workspace, round_, start_recording if index == 0 else None)
        mine.append(run)
        error = "" if run.error_mm is None else f" final error {run.error_mm:.1f} mm"
        verdict = run.verdict if run.accepted else f"refused: {run.reason}"
        say(f"      round {round_} goal {index + 1}/{len(size.goal_steps)} ({steps} steps, "
            f"{run.start_distance_mm:.1f} mm away):{error} -> {verdict} (doing nothing: "
            f"{run.still_error_mm:.1f} mm, {run.still_verdict})")
    op.call(RECORDER_STOP, 30.0, suite.check)
    record["bags_closed"] = [bag._asdict() for bag in closed_bags(op, suite, since)]
    if story.hardware == "camera":
        _again_with_the_simulators_pose(story, mine, round_)
        record["sim_pose_hits"] = sum(r.sim_pose_verdict == "hit" for r in mine)
    story.runs.extend(mine)
    record.update(goals=len(mine), hits=sum(r.success for r in mine),
                  still_hits=sum(r.still_verdict == "hit" for r in mine))
    story.summary["rounds"].append(record)
    say(f"[{4 + round_ - 1}/{story.phases}] round {round_}: {record['hits']}/{record['goals']} goals hit "
        f"(doing nothing: {record['still_hits']}/{record['goals']})")


def _again_with_the_simulators_pose(story: Story, runs: list[GoalRun], round_: int) -> None:
    """Each goal of the round again, from the same grasp (the driver's seed set back to it) with the
    simulator's pose instead of the tracker's, unrecorded: what the camera costs the plans."""
    op, suite = story.op, story.suite
    for index, run in enumerate(runs):
        op.set_parameters("mock_driver", {"seed": run.grasp_seed, "pose_source": "sim"}, 30.0, suite.check)
        again = run_goal(op, suite, run.steps, index, story.workspace, round_)
        if again.grasp_seed != run.grasp_seed or again.goal_mm != run.goal_mm:
            raise RuntimeError(f"goal {index + 1} could not be made again: grasp {again.grasp_seed} vs "
                               f"{run.grasp_seed}, goal {again.goal_mm} vs {run.goal_mm}")
        run.sim_pose_error_mm, run.sim_pose_verdict = again.error_mm, again.verdict
        say(f"      round {round_} goal {index + 1}/{len(runs)} again with the simulator's pose: "
            + ("" if again.error_mm is None else f"final error {again.error_mm:.1f} mm -> ") + again.verdict)
    op.set_parameters("mock_driver", {"pose_source": "topic"}, 30.0, suite.check)


def transfer(story: Story, round_: int) -> dict[str, Any]:
    """One ``t42/transfer`` action goal (the server's method, the bags closed since the last transfer) with its
    feedback shown per epoch; the round's record.

    The model is the result's path, which the server has announced on ``t42/model_updated`` before the result
    (the planner loads it from there), and the episodes it trained on are that announcement's: nothing is read out
    of the result's text.
    """
    from msg_adapters.transfer import transfer_goal, transfer_outcome, transfer_progress

    op, suite = story.op, story.suite
    t0, last, shown, feedback = time.perf_counter(), [""], [0], []

    def progress() -> None:  # a line per stage and per epoch, as the feedback came
        for f in feedback[shown[0]:]:
            shown[0] += 1
            line = f"      transfer: {f.phase}" + (f" epoch {f.epoch}/{f.epochs}" if f.epoch else "")
            if line != last[0]:
                last[0] = line
                say(line)

    handle = op.send_goal(op.transfer_client, names.TRANSFER, transfer_goal(), 30.0, suite.check,
                          lambda message: feedback.append(transfer_progress(message)))
    outcome = transfer_outcome(op.goal_result(handle, 1800.0, f"the result of the {names.TRANSFER} goal",
                                              suite.check, progress))
    progress()
    seconds = time.perf_counter() - t0
    say(f"[{4 + round_ - 1}/{story.phases}] round {round_}: {names.TRANSFER} ({seconds:.0f} s): {outcome.message}")
    if not outcome.success:
        raise RuntimeError(f"the transfer failed: {outcome.message}")

    def announced() -> Any:
        return next((m for m in op.models if m.path == outcome.model_path), None)

    op.wait_until(lambda: announced() is not None and op.diagnostic.get("stage") == "done", 10.0,
                  f"the new model on {names.MODEL_UPDATED} and the final diagnostics", suite.check)
    epochs = [f for f in feedback if f.epochs]
    return {"round": round_, "model": outcome.model_path, "episodes": announced().episodes,
            "transfer": {"success": True, "message": outcome.message, "seconds": seconds,
                         "scores": {name: getattr(outcome, name)._asdict()
                                    for name in ("model", "source", "hold_still")},
                         "skipped": [list(pair) for pair in outcome.skipped],
                         "feedback": len(feedback), "epochs_reported": len(epochs),
                         "last_epoch": [epochs[-1].epoch, epochs[-1].epochs] if epochs else None,
                         "diagnostics": dict(op.diagnostic)}}


def _kept(story: Story, round_: int) -> dict[str, Any]:
    """The round's record without a transfer (``update=False``): round 1's model, still the planner's."""
    first = story.summary["rounds"][0]
    message = f"not updated (the loop that never updates): round 1's model {first['model']}"
    say(f"[{4 + round_ - 1}/{story.phases}] round {round_}: {message}")
    return {"round": round_, "model": first["model"], "episodes": first["episodes"],
            "transfer": dict(first["transfer"], message=message, seconds=0.0, updated=False)}


def heldout_scores(model_path: str | Path, source: str | Path, episodes: Any) -> dict[str, float]:
    """Mean divergence steps (4 mm) of the round's model, the source and holding still on ``episodes``."""
    from t42_transfer.evaluation.metrics import evaluate_model
    from t42_transfer.models.baselines import HoldStill
    from t42_transfer.models.checkpoint import load_model

    models = {"model": load_model(model_path)[0], "source": load_model(source)[0], "hold_still": HoldStill()}
    return {name: float(evaluate_model(m, episodes)["divergence_mean"]) for name, m in models.items()}


def executed_plans(story: Story) -> dict[str, Any]:
    """Each round's model, the source and holding still on the last round's executed goal episodes, which no
    model trained on (recorded after the last transfer), from each one's first command
    (:mod:`t42_transfer.evaluation.online_loop`)."""
    import warnings

    from t42_transfer.data.bag import read_bag
    from t42_transfer.data.trajectory import TrajectorySet
    from t42_transfer.evaluation.online_loop import executed_plan_scores
    from t42_transfer.models.baselines import HoldStill
    from t42_transfer.models.checkpoint import load_model

    rounds = story.summary["rounds"]
    with warnings.catch_warnings():  # (a goal's episode cut short by a drop is left out by the reader, as always)
        warnings.simplefilter("ignore")
        episodes = TrajectorySet([t for bag in rounds[-1]["bags_closed"] if bag["episodes"]
                                  for t in read_bag(bag["path"])], hand="target")
    models = {"source": load_model(story.model)[0], "hold_still": HoldStill(),
              **{f"round {r['round']}": load_model(r["model"])[0] for r in rounds}}
    try:
        plans, scores = executed_plan_scores(models, episodes)
    except ValueError as err:  # (every goal refused, or cut short): nothing to score, said so in the report
        say(f"      no executed plan of round {rounds[-1]['round']} to score the models on: {err}")
        return {"round": rounds[-1]["round"], "episodes": 0, "scores": {}, "why": str(err)}
    say(f"      each round's model on round {rounds[-1]['round']}'s executed plans (no model trained on them), "
        "position MSE: " + ", ".join(f"{name} {s['position_mse_mm2']:.1f} mm^2" for name, s in scores.items()))
    return {"round": rounds[-1]["round"], "episodes": plans, "scores": scores}


def _finish(story: Story, failed: bool, started: float) -> int:
    """demo.json always; on success also the figure and report.md, and the tables on stdout."""
    summary, run_dir, suite = story.summary, story.run_dir, story.suite
    if failed:
        (run_dir / "demo.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
        _tail(suite.log_path)
        return 1
    summary["goals"] = [asdict(r) for r in story.runs]
    summary["seconds"] = time.perf_counter() - started
    (run_dir / "demo.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
    hand = {"sim": "the simulated target hand", "emulated": "the emulated T42 (Dynamixel driver)",
            "camera": "the simulated target hand seen by a camera"}[story.hardware]
    plot_paths(story.runs, run_dir / "paths.png", hand)
    report = write_report(run_dir, summary, story.runs)
    say(f"[{story.phases}/{story.phases}] peg-in-hole, {story.size.rounds} round(s):\n")
    say(rounds_table(summary["rounds"]))
    say("")
    say(goal_table(story.runs))
    say(f"\nreport: {report} (plots: {run_dir / 'paths.png'}); {summary['seconds']:.0f} s in all")
    unclean = {n: c for n, c in summary["exit_codes"].items() if c != 0 and n != "explorer"}
    if unclean:
        say(f"FAILED: nodes did not stop cleanly: {unclean}; see {suite.log_path}")
        return 1
    return 0


def _shutdown(executor: Any, context: Any, spinner: threading.Thread | None) -> None:
    """Stop the operator's executor, then destroy its node: its spin thread must be out of its wait first, or a
    callback it takes of a node being destroyed fails in a task nobody reads ("never retrieved")."""
    import rclpy

    executor.shutdown(timeout_sec=5.0)
    if spinner is not None:
        spinner.join(timeout=5.0)
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
