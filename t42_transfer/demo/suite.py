"""The demo's suite: the source model it starts from, the params file of its nodes, and their processes."""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

import yaml

from t42_transfer.demo.settings import CAMERA, RECORDER_START, RECORDER_STOP, DemoSize
from t42_transfer.hardware.emulator import EMULATED_LATENCY_TIMER_MS


def say(message: str) -> None:
    """One line of the demo's story on stdout, at once (a log file or CI reads it live)."""
    print(message, flush=True)


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
                say(f"[1/{4 + size.rounds}] source model: cached {path}")
                return path
        except Exception:
            pass
    start = time.perf_counter()
    data, stats = collect("source", size.source_episodes, size.source_steps, seed=0, workers=workers)
    bag_dir = out / f"source_bag_{size.source_episodes}x{size.source_steps}"
    if bag_dir.exists():
        shutil.rmtree(bag_dir)
    bag = write_bag(bag_dir, TrajectorySet(assign_start_times(data), hand=data.hand),
                    metadata={"collector": "t42 demo"})
    data = read_bag(bag)
    torch.set_num_threads(1)
    model, report = train_transition_model(data, TrainConfig(epochs=size.source_epochs), on_epoch=ProgressBar(),
                                           phase="source model")
    extra = {"workspace": Workspace.from_trajectories(data).to_dict()}
    save_model(model, path, method="source", data={"demo": key, "source": data.fingerprint()}, extra=extra)
    say(f"[1/{4 + size.rounds}] source model: {len(data)} source-hand episodes ({data.num_transitions} transitions) "
         f"-> {bag}; "
         f"{report.epochs_run} epochs -> {path} ({time.perf_counter() - start:.0f} s)")
    return path


def servo_link(run_dir: Path) -> Path:
    """Where the emulator links its servo bus's pty, and the port the Dynamixel driver opens."""
    return run_dir / "servos"


def hand_params(run_dir: Path, size: DemoSize, hardware: str) -> dict[str, dict[str, Any]]:
    """The hand's nodes' parameters: the graph's clock, rate_factor times faster than real time, is theirs."""
    # Stamps are in simulated time, which runs rate_factor times faster: allow the same wall-time lag.
    max_command_age_s = 0.5 * size.rate_factor
    mock_driver = dict(hand="target", rate_factor=size.rate_factor, seed=0, sim_time=True,
                       max_command_age_s=max_command_age_s)
    if hardware == "sim":
        return {"mock_driver": mock_driver}
    if hardware == "camera":
        from t42_transfer.hand.mjcf import object_marker_height_mm
        from t42_transfer.hand.params import variant

        # The tracker's defaults are the simulated scene's markers; the object's marker face stands this high.
        height_m = object_marker_height_mm(variant("target")) / 1000.0
        return {"mock_driver": dict(mock_driver, pose_source="topic", **CAMERA),
                "object_tracker": dict(object_marker_height_m=height_m, use_sim_time=True)}
    port = str(servo_link(run_dir))
    return {"hw_emulator": dict(link=port, hand="target", seed=0, sim_time=True, rate_factor=size.rate_factor),
            "dynamixel_driver": dict(port=port, autostart=True, use_sim_time=True,
                                     latency_timer_ms=EMULATED_LATENCY_TIMER_MS, max_command_age_s=max_command_age_s)}


def suite_params(run_dir: Path, model: Path, size: DemoSize, hardware: str = "sim") -> dict[str, Any]:
    """The params file of the suite (and the explorer) for this run; method settings go to their own file."""
    methods = run_dir / "transfer_methods.yaml"
    methods.write_text(yaml.safe_dump(size.transfer, sort_keys=False))

    def node(**params: Any) -> dict[str, Any]:
        return {"ros__parameters": params}

    sections = {
        **{name: node(**params) for name, params in hand_params(run_dir, size, hardware).items()},
        "recorder": node(out_dir=str(run_dir / "bags"), mode="episode", start_immediately=False, use_sim_time=True),
        "transfer_server": node(source_model=str(model), model_dir=str(run_dir / "models"),
                                bag_dir=str(run_dir / "bags"),
                                new_bags_only=False, config=str(methods), use_sim_time=True),
        "planner": node(max_state_age_s=0.5 * size.rate_factor, use_sim_time=True),
        "explorer": node(episodes=size.target_episodes, steps=size.target_steps, seed=1,
                         rate_factor=size.rate_factor, record_start_service=RECORDER_START,
                         record_stop_service=RECORDER_STOP, use_sim_time=True),
    }
    return {f"/**/{name}": section for name, section in sections.items()}


class Suite:
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
