"""Every benchmark in bench/ at its smallest sensible setting: it exits 0 and writes the JSON it documents.

Each runs as the README runs it (``python bench/X.py ...`` from the repository root), in a subprocess of
its own session (a timeout kills it and whatever it started), writing to the test's ``tmp_path``.
bench_cell.py has its own test (test_bench_cell.py).  The figures themselves are not judged (they vary
with the machine's load): only that every documented field is there and sound.  Benchmarks that start
ROS nodes run on the test's own ``ros_domain`` (ROS_DOMAIN_ID, LOCALHOST discovery).

In the slow suite (CI runs it too): these check the benchmark scripts, not the suite's behaviour, which the
default suite covers, and together they cost ~40 s of the default suite's 10-minute budget.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def run_bench(script: str, *args: str, out: Path, timeout_s: float = 120.0) -> dict:
    """Run ``bench/<script> *args --out <out>``; fail with its output unless it exits 0; the JSON it wrote."""
    cmd = [sys.executable, str(REPO / "bench" / script), *args, "--out", str(out)]
    env = dict(os.environ)
    env.pop("T42_DEMO_DOMAIN", None)  # the demo would take it over the test's ROS_DOMAIN_ID
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # its own session: the ROS processes it started go too
        stdout, stderr = proc.communicate()
        pytest.fail(f"{script} ran past {timeout_s} s\n{stdout[-2000:]}\n{stderr[-3000:]}")
    assert proc.returncode == 0, f"{script} exited {proc.returncode}\n{stdout[-2000:]}\n{stderr[-3000:]}"
    assert out.is_file(), f"{script} wrote no {out}"
    return json.loads(out.read_text())


def positive(value: object) -> bool:
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    return number and math.isfinite(value) and value > 0


# --------------------------------------------------------------------------- no ROS


def test_bench_collect(tmp_path: Path) -> None:
    result = run_bench("bench_collect.py", "--episodes", "1", "--steps", "20", "--workers", "1",
                       out=tmp_path / "collect.json")
    assert result["benchmark"] == "collect"
    hands = {"source", "target"}
    for key in ("control_steps_per_s_per_core", "baseline_bare_physics_steps_per_s", "ratio_to_bare_physics"):
        assert set(result[key]) == hands and all(positive(v) for v in result[key].values()), key
    dataset = result["dataset"]
    assert (dataset["episodes"], dataset["steps"], dataset["workers"]) == (1, 20, 1)
    assert set(dataset["per_hand"]) == hands
    for run in dataset["per_hand"].values():
        assert positive(run["wall_s"]) and run["episodes_kept"] == 1 and run["transitions"] == 20  # (seeded grasps)
        assert sum(run["end_reasons"].values()) == run["episodes_kept"]
        assert {"too_short", "grasp_failed"} <= set(run)
    assert positive(result["dataset_wall_s_both_hands"]) and positive(result["dataset_control_steps_per_s"])
    assert result["target_wall_s"] == 600.0 and result["meets_target"] is True
    assert {"command", "machine", "load_average_at_end"} <= set(result)


def test_bench_planner(tmp_path: Path) -> None:
    result = run_bench("bench_planner.py", "--samples", "50", "--horizon", "5", "--repeats", "1",
                       "--rss-samples", "200", "--threads", "1", out=tmp_path / "planner.json")
    assert result["benchmark"] == "planner"
    params = result["parameters"]
    assert (params["samples"], params["horizon"], params["repeats"]) == (50, 5, 1)
    cases = {"planner_default", "planner_one_round", "fused_rollout", "eager_loop", "matmul_bound",
             "matmul_bound_mkl", "transcendental_floor"}
    cases |= set() if "mppi" in result["notes"] else {"mppi"}  # a note instead when pytorch_mppi is absent
    for key in ("sample_steps_per_s", "best_sample_steps_per_s", "ms_per_call", "repeats_s", "rollouts_per_call"):
        assert set(result[key]) == cases, key
    assert all(positive(v) for v in result["sample_steps_per_s"].values())
    assert all(len(ts) == 1 for ts in result["repeats_s"].values())
    # rates count the rollouts made: the default mode refines (about 1 + refine_iterations draws of K), one round not
    made = result["rollouts_per_call"]
    assert made["planner_one_round"] == 50 and made["planner_default"] > 2 * 50 and made["fused_rollout"] == 50
    for name, per_s in result["sample_steps_per_s"].items():
        assert per_s == pytest.approx(made[name] * 5 / (result["ms_per_call"][name] / 1e3)), name
    pairs = {f"{p}_vs_{b}" for p in ("planner_default", "planner_one_round") for b in ("eager_loop", "matmul_bound")}
    pairs |= {"fused_rollout_vs_matmul_bound", "transcendental_floor_vs_matmul_bound",
              "fused_rollout_vs_transcendental_floor", "fused_rollout_vs_matmul_bound_mkl",
              "matmul_bound_mkl_vs_matmul_bound"}
    pairs |= {f"{p}_vs_mppi" for p in ("planner_default", "planner_one_round")} if "mppi" in cases else set()
    assert set(result["ratios"]) == set(result["ratios_described"]) == pairs
    assert all(positive(v) for v in result["ratios"].values())
    # the bound takes, per layer, whichever form was fastest in this run
    forms = result["matmul_forms"]
    assert set(forms) == {"layer1", "layer2", "layer3"}
    for layer in forms.values():
        us = layer["us_per_product"]
        assert {"mkl", "mkl_weight_view", "mkl_transposed_output"} <= set(us) and all(positive(v) for v in us.values())
        assert layer["form"] == min(us, key=us.get)
    assert set(result["targets"]) == {"fused_rollout_vs_matmul_bound >= 0.8", "planner_default_vs_matmul_bound >= 0.5"}
    assert "time_to_rate" in result["latency_at_equal_success"] or "note" in result["latency_at_equal_success"]
    assert [(r["samples"], r["chunk"]) for r in result["peak_rss"]] == [(200, params["chunk"]), (200, 200)]
    for r in result["peak_rss"]:
        assert r["peak_rss_mib"] >= r["rss_mib_before"] > 0 and positive(r["seconds"])
    assert result["machine"]["threads"] == 1 and "load_average_at_end" in result["machine"]


def test_bench_planner_quality(tmp_path: Path) -> None:
    """An untrained model file storing a wide workspace stands in for the experiment's transferred model."""
    import torch

    from t42_transfer.models import Normalisation, TransitionModel
    from t42_transfer.models.checkpoint import save_model
    from t42_transfer.planning.workspace import Workspace

    torch.manual_seed(0)
    norm = Normalisation(
        state_mean=np.array([0.0, 80.0, 120.0, -120.0], np.float32),
        state_std=np.array([15.0, 10.0, 30.0, 30.0], np.float32),
        delta_mean=np.zeros(4, np.float32),
        delta_std=np.array([0.4, 0.4, 2.0, 2.0], np.float32),
    )
    model = save_model(TransitionModel(norm), tmp_path / "m.safetensors", method="naive_finetune",
                       extra={"workspace": Workspace.box(-200, 200, -100, 300).to_dict()})
    result = run_bench("bench_planner_quality.py", "--model", str(model), "--goals", "1", "--steps", "10",
                       "--budgets", "4", "--refine-iterations", "1", "--cem-iterations", "1",
                       "--mppi-iterations", "1", "--targets", "0.5", "--quiet",
                       out=tmp_path / "planner_quality.json")
    assert result["benchmark"] == "planner_quality"
    optimisers = ["default", "default_search", "default_settled", "default_robust", "ours", "ours_cem",
                  "random_shooting", "cem", "cem_mean", "mppi"]
    assert result["setting"]["budgets"] == [4] and result["setting"]["optimisers"] == optimisers
    assert result["model"]["path"] == str(model) and result["model"]["method"] == "naive_finetune"
    assert result["workspace"] == "stored in the model file" and positive(result["seconds_total"])
    assert result["goals"]["count"] == 1 and result["goals"]["steps"] == [10]
    assert [(r["optimiser"], r["budget"]) for r in result["rows"]] == [(o, 4) for o in optimisers]
    for r in result["rows"]:
        assert r["trials"] == 1 and [s["tolerance_mm"] for s in r["success"]] == [10.0, 4.0]
        for s in r["success"]:
            assert 0.0 <= s["ci_low"] <= s["success_rate"] <= s["ci_high"] <= 1.0
        assert positive(r["median_plan_seconds"]) and r["median_rollouts"] >= 1
    assert len(result["time_to_rate"]) == len(optimisers) * 2  # x tolerances, one target rate
    assert len(result["trials"]) == len(optimisers)
    assert (tmp_path / "planner_quality.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # the figure, beside
    assert {"command", "machine"} <= set(result)


def test_bench_rollout(tmp_path: Path) -> None:
    result = run_bench("bench_rollout.py", "--batch", "10", "--horizon", "5", "--repeats", "1",
                       "--threads", "1", out=tmp_path / "rollout.json")
    assert result["benchmark"] == "rollout"
    assert result["parameters"]["batch"] == 10 and result["parameters"]["horizon"] == 5
    kinds = {"transition", "transition_grasp_input", "cumulative_residual", "recurrent_residual"}
    for key in ("results", "ratios", "ratios_per_mlp_call", "details"):
        assert set(result[key]) == kinds, key
    assert all(positive(v) for v in result["results"].values())
    assert all(positive(v) for v in result["ratios"].values())
    for d in result["details"].values():
        assert positive(d["ms_per_rollout"]) and d["mlp_calls_per_step"] in (1, 2)
        assert len(d["repeats_s"]["model"]) == len(d["repeats_s"]["baseline"]) == 1
    assert positive(result["baseline"]["sample_steps_per_s"])
    assert set(result["method_to_kind"].values()) <= kinds
    assert result["machine"]["threads"] == 1


def test_bench_training(tmp_path: Path) -> None:
    result = run_bench("bench_training.py", "--episodes", "2", "--steps", "50", "--batches", "64",
                       "--repeats", "1", "--traj-episodes", "2", "--traj-steps", "20", "--traj-epochs", "1",
                       "--traj-repeats", "1", "--threads", "1", out=tmp_path / "training.json")
    assert result["benchmark"] == "training"
    single = result["parameters"]["single_step"]
    assert single["transitions"] == 100 and single["batch_sizes"] == [64]
    assert result["parameters"]["trajectory_finetune"]["model_steps_per_run"] == 2 * 20
    res, base, ratios = result["results"], result["baseline"], result["ratios"]
    fused = result["proposal_fused_adam"]
    for per_batch in (res["single_step_samples_per_s"], res["single_step_end_to_end_samples_per_s"],
                      base["single_step_samples_per_s"], ratios["single_step_loop_ours_over_baseline"],
                      ratios["single_step_end_to_end_ours_over_baseline"],
                      ratios["single_step_loop_median_paired_ratio"], fused["samples_per_s"],
                      fused["over_baseline"]):
        assert set(per_batch) == {"64"} and positive(per_batch["64"])
    assert positive(res["trajectory_finetune_model_steps_per_s"])
    assert positive(base["trajectory_model_steps_per_s"])
    assert positive(ratios["trajectory_finetune_ours_over_baseline"])
    assert len(result["details"]["trajectory_seconds"]["ours"]) == 1
    assert result["machine"]["threads"] == 1


# --------------------------------------------------------------------------- ROS nodes


def test_bench_pubsub_latency(tmp_path: Path, ros_domain: int) -> None:
    result = run_bench("bench_pubsub_latency.py", "--trips", "10", "--warmup", "2",
                       out=tmp_path / "pubsub.json")
    assert result["ros"]["domain_id"] == ros_domain and result["ros"]["discovery_range"] == "LOCALHOST"
    assert result["ros"]["rmw"] and (result["round_trips_per_case"], result["warmup_per_case"]) == (10, 2)
    for kind in ("geometry_msgs/PoseStamped", "sensor_msgs/JointState"):
        per = result[kind]
        for case in ("ours_msg_adapters", "baseline_bare_rclpy"):
            stats = per[case]
            assert set(stats) == {"median_ms", "p90_ms", "p99_ms", "mean_ms", "max_ms"}
            assert 0 < stats["median_ms"] <= stats["p90_ms"] <= stats["p99_ms"] <= stats["max_ms"]
        assert set(per["ratio_ours_over_bare"]) == {"median_ms", "p90_ms", "p99_ms"}
        assert all(positive(v) for v in per["ratio_ours_over_bare"].values())
    assert positive(result["wall_s"])


@pytest.mark.slow
def test_bench_recorder(tmp_path: Path, ros_domain: int) -> None:
    """Eight publisher -> receiver runs of 0.5 s (each rate and executor the summary compares): a minute+."""
    result = run_bench("bench_recorder.py", "--run-seconds", "0.5", out=tmp_path / "recorder.json",
                       timeout_s=480)
    expected = [("recorder", 1000, "runner"), ("sink", 1000, "runner"), ("recorder", 5000, "runner"),
                ("sink", 5000, "runner"), ("recorder", 10000, "runner"), ("sink", 10000, "runner"),
                ("recorder", 5000, "multi4"), ("sink", 5000, "multi4")]
    runs = result["runs"]
    assert [(r["receiver"], r["rate_hz"], r["executor"]) for r in runs] == expected
    for r in runs:
        assert r["seconds"] == 0.5 and r["sent"] == int(r["rate_hz"] * 0.5)
        assert 0 < r["received"] <= r["sent"] and r["lost"] == r["sent"] - r["received"]
        assert (r["in_bag"] is None) == (r["receiver"] == "sink")
        assert r["rss_mb_peak"] is not None and r["rss_mb_peak"] > 0
    summary = result["summary"]
    rates = {"1khz", "5khz", "10khz"}
    assert set(summary["recorder_sent_recorded"]) == set(summary["sink_sent_counted"]) == rates
    assert set(summary["cpu_us_per_msg_recorder_vs_sink_and_ratio"]) == rates
    assert all(len(v) == 3 for v in summary["cpu_us_per_msg_recorder_vs_sink_and_ratio"].values())
    assert len(summary["recorder_rss_mb_30s_run_first_peak_end"]) == 3
    assert positive(summary["recorder_own_work_us_per_msg"])
    assert set(summary["not_the_runner_multi4_5khz"]) == {"recorder_sent_recorded", "sink_sent_counted",
                                                          "cpu_us_per_msg_recorder_vs_sink_and_ratio"}
    assert "SingleThreadedExecutor" in summary["executor"]


@pytest.mark.slow
def test_bench_suite_latency(tmp_path: Path, ros_domain: int) -> None:
    """The whole quick demo (a source model trained, the suite as node processes, two rounds): minutes."""
    result = run_bench("bench_suite_latency.py", out=tmp_path / "suite_latency.json", timeout_s=900)
    assert result["demo"] == "quick" and result["middleware"]
    call = result["service_call_to_model_ready"]
    assert all(positive(call[k]) for k in ("call_s", "server_elapsed_s", "ratio_call_over_server"))
    goals = result["goal_to_plan_result"]
    assert goals["goals"] >= 1
    assert 0 < goals["median_s"] <= goals["max_s"] and positive(goals["planning_median_s"])
    assert positive(goals["ratio_median_over_planning"]) and positive(result["whole_demo_s"])
    assert {"command", "machine", "load_average_after"} <= set(result)


def test_bench_driver(tmp_path: Path, ros_domain: int) -> None:
    """Six runs one after the other (driver, bare loop, bare loop reading in select, idle node on each of two
    executors, the driver's ROS traffic without a bus), each 1 s timed:
    ~10 steps at 10 Hz, enough for the intervals and above a clock tick of driver CPU (~2-4 ms a step).  The
    driver's window is an episode (hand/reset first, a command each period): its steps publish the full step."""
    result = run_bench("bench_driver.py", "--seconds", "1", out=tmp_path / "driver.json")
    driver, bare = result["driver"], result["bare_sdk_loop"]
    assert result["seconds"] == 1.0 and 5 <= driver["steps"] <= 15 and 5 <= bare["steps"] <= 15
    assert all(positive(driver[k]) for k in ("cpu_ms_per_step",)) and positive(bare["round_trip_ms"])
    assert set(driver["interval_ms"]) == {"mean", "std", "p99", "max"} and 80 < driver["interval_ms"]["mean"] < 130
    episode = driver["episode"]
    assert "grasped" in episode["reset"] and episode["commands_sent"] >= 5, episode
    assert episode["joint_states"] >= 5 and episode["applied_actions"] >= 5 and episode["actions_that_moved"] >= 3
    assert isinstance(driver["late_steps"], int) and positive(result["cpu_ratio_driver_to_stock_sdk_loop"])
    assert positive(result["cpu_ratio_driver_to_select_reads_loop"])
    assert result["target"] == {"ratio": "cpu_ratio_driver_to_select_reads_loop", "cpu_ratio_max": 1.5,
                                "late_steps": 0, "every_step_published": True}
    assert "load_average" in result["machine"]
    assert isinstance(result["target_met"], bool) and result["target_met"] == (not result["target_missed_because"])
    select, idle = result["bare_sdk_loop_select_reads"], result["idle_rclpy_node"]
    assert 5 <= select["steps"] <= 15 and positive(select["cpu_ms_per_step"]) and positive(select["round_trip_ms"])
    assert 5 <= idle["periods"] <= 15 and positive(idle["cpu_ms_per_period"])
    events = result["idle_rclpy_node_events_executor"]
    assert 5 <= events["periods"] <= 15 and positive(events["cpu_ms_per_period"])
    assert math.isfinite(result["driver_cpu_above_idle_node_ms_per_step"])
    floor = result["rclpy_interface_floor"]
    assert 5 <= floor["periods"] <= 15 and positive(floor["cpu_ms_per_period"])
    assert floor["joint_states_received"] >= 5  # its messages reached the peer: the traffic was the driver's
    assert result["driver_cpu_above_interface_floor_ms_per_step"] == pytest.approx(
        driver["cpu_ms_per_step"] - floor["cpu_ms_per_period"])
    assert result["cpu_ratio_interface_floor_to_select_reads_loop"] == pytest.approx(
        floor["cpu_ms_per_period"] / select["cpu_ms_per_step"])


def test_bench_startup(tmp_path: Path, ros_domain: int) -> None:
    """One run each (suite, bare node, bare node starting late), each import once: the figures are there, finite
    and positive (30-40 s)."""
    result = run_bench("bench_startup.py", "--runs", "1", out=tmp_path / "startup.json", timeout_s=300)
    assert result["benchmark"] == "startup" and result["runs"] == 1
    assert result["ros"] == {"domain_id": ros_domain, "discovery_range": "LOCALHOST"}
    for key in ("suite_up_s", "bare_node_s", "ratio_suite_over_bare", "suite_stop_s", "bare_stop_s", "wall_s"):
        assert positive(result[key]), key
    assert len(result["suite_up_s_runs"]) == len(result["bare_node_s_runs"]) == 1
    nodes = ["mock_driver", "recorder", "transfer_server", "planner"]
    assert result["nodes"] == nodes and set(result["per_node"]) == set(nodes) and result["slowest_node"] in nodes
    for name, node in result["per_node"].items():
        for key in ("started_s", "running_s", "discovered_s", "services_ready_s", "cpu_s_at_up", "import_module_s"):
            assert positive(node[key]), (name, key)
        assert node["started_s"] < node["running_s"] and node["services_ready_s"] <= result["suite_up_s"], name
        assert all(positive(v) for v in node["imports"].values()), name
    assert "torch" in result["per_node"]["planner"]["imports"]  # the heavy import the JSON is there to show
    expected = {"python (pass)", "rclpy", "torch", "mujoco", "t42_transfer.cli"}
    assert expected <= set(result["import_s"]) and all(positive(v) for v in result["import_s"].values())
    assert set(result["import_tree_ms"]) == set(nodes)
    assert all(positive(tree["total_ms"]) for tree in result["import_tree_ms"].values())
    assert all(not r["stopped_by_pid"] for runs in result["runs_detail"].values() for r in runs)  # t42 up stopped them
    assert {"command", "machine", "load_before", "load_after", "reference"} <= set(result)


def test_bench_tracker(tmp_path: Path) -> None:
    """Three frames at two small resolutions, one pass: the fields, and ratios that are finite positive numbers."""
    result = run_bench("bench_tracker.py", "--frames", "3", "--repeats", "1", "--resolutions", "320x240", "640x360",
                       out=tmp_path / "tracker.json")
    assert result["benchmark"] == "tracker" and result["parameters"]["frames"] == 3
    assert list(result["resolutions"]) == ["320x240", "640x360"]
    for run in result["resolutions"].values():
        for case in ("render", "tracker", "bare"):
            assert all(positive(run[case][k]) for k in ("fps", "ms_per_frame", "cpu_ms_per_frame")), case
        assert run["render"]["frames"] == 3 and sum(run["tracker"]["statuses"].values()) == 3
        assert 0 <= run["tracker"]["tracked"] <= 3 and 0 <= run["bare"]["marker_poses_per_frame"] <= 3
        ratios = run["ratio_tracker_to_bare"]
        assert positive(ratios["ms_per_frame"]) and positive(ratios["cpu_ms_per_frame"])
        assert len(ratios["ms_per_frame_per_repeat"]) == 1 and {"load_before", "load_after"} <= set(run)
    at_640 = result["resolutions"]["640x360"]["tracker"]  # 320x240 is too coarse for the markers; 640x360 is not
    assert at_640["tracked"] == 3 and at_640["median_error_mm"] < 2.0, at_640  # a fast but wrong tracker fails
    assert result["target"]["ratio_tracker_to_bare_max"] == 1.3 and isinstance(result["target_met"], bool)
    assert {"command", "load_before", "load_after"} <= set(result) and "load_average" in result["machine"]
