"""The experiment runner and report on the fixture bags: cells, resuming, workers, config errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from t42_transfer.cli import main
from t42_transfer.conventions import AUTHORS_ACTION_UNIT_RAD
from t42_transfer.evaluation import experiment as exp
from t42_transfer.evaluation.experiment import run_experiment
from t42_transfer.evaluation.experiment_config import SAFE_NAME, DataSpec, ExperimentConfig, check_spec, load_config
from t42_transfer.models.checkpoint import save_model
from t42_transfer.models.network import Normalisation, TransitionModel
from t42_transfer.models.training import TrainConfig

REPO = Path(__file__).resolve().parents[1]

CONFIG = f"""
name: tiny
source: {{bag: {REPO / 'bags' / 'source_small'}}}
target: {{bag: {REPO / 'bags' / 'target_small'}}}
methods: [direct, naive_finetune, cumulative_residual]
split: paths
amounts: [1, 2]
seeds: 2
lyapunov_steps: 20
source_training: {{epochs: 2}}
transfer:
  naive_finetune: {{train: {{epochs: 2, lr: 0.001, patience: null}}}}
  cumulative_residual: {{train: {{epochs: 2}}, gamma: 0.99}}
workers: 1
"""


@pytest.fixture()
def config_file(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(CONFIG)
    return path


def test_cells_rows_resume_and_report(config_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = load_config(config_file)
    assert cfg.transfer.cumulative_residual.gamma == 0.99 and cfg.transfer.cumulative_residual.alpha == 0.3
    rows = run_experiment(cfg, tmp_path / "runs", progress=False)
    assert len(rows) == (3 + 1) * 2 * 2  # every cell, and the hold-still baseline per amount and seed
    assert {(r["method"], r["amount"], r["seed"]) for r in rows} == {
        (m, a, s) for m in (*cfg.methods, "hold_still") for a in (1, 2) for s in (0, 1)
    }
    for row in rows:
        assert row["train_episodes"] == row["amount"] and row["test_rollouts"] == 4 - row["amount"]
        assert row["divergence_mean"] >= 0 and row["position_mse_mean"] >= 0
    direct = [r for r in rows if r["method"] == "direct" and r["amount"] == 1]
    assert direct[0]["lyapunov_mean"] != direct[1]["lyapunov_mean"]  # different test paths per seed

    # A second run reads every cell back instead of transferring again.
    monkeypatch.setattr(exp, "transfer", lambda *a, **k: pytest.fail("a cached cell was recomputed"))
    again = run_experiment(cfg, tmp_path / "runs", progress=False)
    assert again[:12] == rows[:12]  # the hold-still rows are scored again (nothing to cache), to the same numbers
    assert [{**r, "seconds": 0} for r in again[12:]] == [{**r, "seconds": 0} for r in rows[12:]]

    run_dir = tmp_path / "runs" / "tiny"
    assert (run_dir / "results.csv").read_text().count("\n") == 17
    assert main(["report", str(run_dir)]) == 0
    report = (run_dir / "report" / "report.md").read_text()
    assert "Naive fine-tuning is worse than no adaptation" in report and "Holding still (the object" in report
    tables = report.split("| method |")[1:]
    assert len(tables) == 4  # three metrics and the bound's quantities
    for table in tables:  # each lists the hold-still baseline right after direct
        methods = [line.split(" |")[0][2:] for line in table.split("\n\n")[0].splitlines()[2:]]
        assert list(dict.fromkeys(methods)) == ["direct", "hold_still", "naive_finetune", "cumulative_residual"]
    for figure in ("divergence_mean.png", "position_mse_mean.png", "lyapunov_mean.png", "paths.png"):
        assert (run_dir / "report" / figure).stat().st_size > 5000


@pytest.mark.parametrize("split, amounts, test_sets", [("paths", (1, 2), 4), ("fraction", (0.3, 0.6), 1)])
def test_hold_still_is_scored_on_every_test_set_once(config_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     split: str, amounts: tuple[float, ...], test_sets: int) -> None:
    import csv
    import dataclasses

    from t42_transfer.evaluation.metrics import evaluate_model
    from t42_transfer.models.baselines import HoldStill

    cfg = dataclasses.replace(load_config(config_file), methods=("direct",), split=split, amounts=amounts,
                              test_fraction=0.25)
    scored = []
    scores = exp._test_scores
    monkeypatch.setattr(exp, "_test_scores", lambda model, test, c: scored.append(model.kind) or scores(model, test, c))
    rows = run_experiment(cfg, tmp_path, progress=False)
    assert scored.count("hold_still") == test_sets
    target = exp.load_side(cfg, "target", tmp_path / "data").data
    still = {(r["amount"], r["seed"]): r for r in rows if r["method"] == "hold_still"}
    direct = {(r["amount"], r["seed"]): r for r in rows if r["method"] == "direct"}
    assert sorted(still) == sorted(direct) == sorted((a, s) for a in amounts for s in range(2))
    for (amount, seed), row in still.items():
        _, test = exp.target_split(cfg, target, exp.Cell("direct", amount, seed))
        expected = evaluate_model(HoldStill(), test, cfg.epsilon_mm, cfg.start_offsets, cfg.horizon, cfg.definition)
        assert row["divergence_mean"] == expected["divergence_mean"]
        for eps in (4.0, 10.0):  # both thresholds in use, counted by the run's definition
            at = evaluate_model(HoldStill(), test, eps, cfg.start_offsets, cfg.horizon, cfg.definition)
            assert row[f"divergence_mean_{eps:g}mm"] == at["divergence_mean"]
        assert row["position_mse_mean"] == expected["position_mse_mean"] and row["lyapunov_mean"] == 0.0
        assert row["test_rollouts"] == direct[(amount, seed)]["test_rollouts"]
        assert row["covering_radius"] == direct[(amount, seed)]["covering_radius"]  # the cell's data, not a model's
    with open(tmp_path / "tiny" / "results.csv") as f:
        written = [r for r in csv.DictReader(f) if r["method"] == "hold_still"]
    assert [float(r["divergence_mean"]) for r in written] == [r["divergence_mean"] for r in still.values()]


def test_two_workers_give_the_same_numbers(config_file: Path, tmp_path: Path) -> None:
    import dataclasses

    cfg = dataclasses.replace(load_config(config_file), methods=("naive_finetune",), amounts=(1,))
    serial = run_experiment(cfg, tmp_path / "a", progress=False)
    parallel = run_experiment(dataclasses.replace(cfg, workers=2), tmp_path / "b", progress=False)
    strip = lambda rows: [{k: v for k, v in r.items() if k != "seconds"} for r in rows]  # noqa: E731
    assert strip(serial) == strip(parallel)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda t: t.replace("seeds: 2", "seeds: 2\nsedes: 3"), "unknown experiment settings \\['sedes'\\]"),
        (lambda t: t.replace("[direct,", "[direct, magic,"), "methods must be one of \\[.*'direct'.*\\], got 'magic'"),
        (lambda t: t.replace("source_training: {epochs: 2}", "source_training: {epoch: 2}"),
         "unknown TrainConfig settings"),
        (lambda t: t.replace("name: tiny", ""), "needs name, source and target"),
        (lambda t: "name: [unclosed\n" + t, "not valid YAML: expected ',' or '\\]', but got ':' at line 3, column 5"),
        (lambda t: t.replace("seeds: 2", "seeds: 0"), "seeds must be in \\[1, 1000\\], got 0"),
        (lambda t: t.replace("amounts: [1, 2]", "amounts: [.nan]"), "amounts\\[0\\] must be a finite number, got nan"),
        (lambda t: t.replace("name: tiny", "name: ../../escape"), "name must be one plain path component"),
        (lambda t: t.replace("gamma: 0.99", "gamma: [0.99]"), "transfer.cumulative_residual.gamma must be a finite"),
    ],
)
def test_config_errors_name_the_file_and_setting(config_file: Path, change, message: str) -> None:
    config_file.write_text(change(CONFIG))
    with pytest.raises(ValueError, match=message) as err:
        load_config(config_file)
    assert str(config_file) in str(err.value)


def _experiment_configs() -> list[Path]:
    """Shipped YAMLs but the ROS params files of node suites (suite.yaml, hardware_*.yaml: "/**/node" keys)."""
    shipped = sorted((REPO / "configs").rglob("*.yaml"))
    return [p for p in shipped if not any(str(k).startswith("/") for k in yaml.safe_load(p.read_text()) or {})]


@pytest.mark.parametrize("shipped", _experiment_configs(), ids=lambda p: p.name)
def test_every_shipped_config_loads(shipped: Path) -> None:
    cfg = load_config(shipped)
    assert SAFE_NAME.fullmatch(cfg.name)


def test_configs_built_in_code_keep_the_same_rules(config_file: Path, tmp_path: Path) -> None:
    import dataclasses

    cfg = load_config(config_file)
    with pytest.raises(ValueError, match="name must be one plain path component"):
        dataclasses.replace(cfg, name="../out")
    for bad in (dict(seeds=0), dict(amounts=(float("nan"),)), dict(workers=0), dict(methods=("direct", "direct"))):
        with pytest.raises(ValueError):
            run_experiment(dataclasses.replace(cfg, **bad), tmp_path / "runs", progress=False)
    assert not (tmp_path / "runs").exists()


def test_the_run_lock_is_released_when_the_run_fails(config_file: Path, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    import dataclasses

    cfg = dataclasses.replace(load_config(config_file), methods=("direct",), amounts=(1,), seeds=1)

    def boom(*args: object, **kwargs: object) -> None:
        raise RuntimeError("a failing cell")

    monkeypatch.setattr(exp, "transfer", boom)
    with pytest.raises(RuntimeError, match="a failing cell"):
        run_experiment(cfg, tmp_path, progress=False)
    monkeypatch.undo()
    assert len(run_experiment(cfg, tmp_path, progress=False)) == 2  # not "in use by another run"


def test_results_json_holds_the_config(config_file: Path, tmp_path: Path) -> None:
    import dataclasses

    cfg = dataclasses.replace(load_config(config_file), methods=("direct",), amounts=(1,), seeds=1)
    run_experiment(cfg, tmp_path, progress=False)
    content = json.loads((tmp_path / "tiny" / "results.json").read_text())
    assert content["config"]["split"] == "paths" and [r["method"] for r in content["rows"]] == ["direct", "hold_still"]
    assert load_config(tmp_path / "tiny" / "config.yaml") == cfg


def test_auto_cells_record_the_pick_and_fall_back_on_one_path(config_file: Path, tmp_path: Path) -> None:
    import dataclasses

    from t42_transfer.transfer.config import AutoConfig

    base = load_config(config_file)
    transfer = dataclasses.replace(base.transfer, auto=AutoConfig(candidates=("direct", "naive_finetune"),
                                                                    fallback="cumulative_residual"))
    cfg = dataclasses.replace(base, methods=("auto", "cumulative_residual"), seeds=1, transfer=transfer)
    run_experiment(cfg, tmp_path, progress=False)
    rows = {(r["method"], r["amount"]): r for r in json.loads((tmp_path / "tiny" / "results.json").read_text())["rows"]}
    # One path: nothing to hold out, so the fallback is trained on it: the same model as its own cell.
    assert rows[("auto", 1)]["auto_picked"] == "cumulative_residual"
    assert rows[("auto", 1)]["divergence_mean"] == rows[("cumulative_residual", 1)]["divergence_mean"]
    assert rows[("auto", 2)]["auto_picked"] in ("direct", "naive_finetune")
    assert "auto_picked" not in rows[("cumulative_residual", 2)]


def test_a_method_that_cannot_run_at_some_amount_is_refused_before_the_first_cell(config_file: Path,
                                                                                   tmp_path: Path) -> None:
    """``auto`` without a fallback cannot pick from one path: the run says so before anything is trained."""
    import dataclasses

    from t42_transfer.transfer.config import AutoConfig

    base = load_config(config_file)
    transfer = dataclasses.replace(base.transfer, auto=AutoConfig(candidates=("direct", "naive_finetune")))
    cfg = dataclasses.replace(base, methods=("direct", "auto"), seeds=1, transfer=transfer)
    with pytest.raises(ValueError, match=r"auto at amount 1 \(seed 0, 1 training episode\(s\)\): auto needs at "
                                         r"least 2 target episodes"):
        run_experiment(cfg, tmp_path, progress=False)
    assert not (tmp_path / "tiny" / "cells").exists()  # made just before the first cell runs
    # From two paths up it can: the same config without amount 1 passes the check.
    target = exp.load_side(cfg, "target", tmp_path / "cache").data
    exp._check_methods_fit(dataclasses.replace(cfg, amounts=(2,)), target, None)


def test_cell_models_store_the_planning_workspace(config_file: Path, tmp_path: Path) -> None:
    import dataclasses

    from t42_transfer.models.checkpoint import read_metadata
    from t42_transfer.planning.workspace import Workspace

    cfg = dataclasses.replace(load_config(config_file), methods=("direct",), amounts=(1,), seeds=1)
    run_experiment(cfg, tmp_path, progress=False)
    (model_file,) = (tmp_path / "tiny" / "models").glob("*.safetensors")
    workspace = Workspace.from_metadata(read_metadata(model_file))
    assert workspace is not None and workspace.load_limit == 280.0


# ------------------------------------------------------------------ data specs: quality, real pairs, authors' runs


def _bag(tmp_path: Path, name: str, data) -> str:  # type: ignore[no-untyped-def]
    from t42_transfer.data.bag import write_bag

    return str(write_bag(tmp_path / name, data))


def _with_jump(make_set):  # type: ignore[no-untyped-def]
    """Four 60-step episodes; episode 1 jumps 12 mm at step 20."""
    import dataclasses

    import numpy as np

    data = make_set([60] * 4, seed=7, hand="target")
    states = data[1].states.copy()
    states[21:, 0] += 12.0
    episodes = list(data)
    episodes[1] = dataclasses.replace(episodes[1], states=states)
    return type(data)(episodes, hand="target"), np


def test_new_spec_settings_keep_old_cache_keys() -> None:
    spec = DataSpec(real="A")
    assert list(spec.describe()) == ["hand", "episodes", "steps", "seed", "bag", "real", "mirror_x"]
    assert DataSpec(real="A", flagged="drop").describe()["flagged"] == "drop"
    hand = DataSpec(hand="target", episodes=20, steps=1000, seed=2)
    assert hand.describe() == {"hand": "target", "episodes": 20, "steps": 1000, "seed": 2, "bag": None, "real": None,
                               "mirror_x": False}  # the collected bag's name hashes this: random-policy bags stay
    assert DataSpec(hand="target", policy="sustained").describe()["policy"] == "sustained"


def test_a_test_set_keeps_the_cell_keys_of_runs_without_one(config_file: Path) -> None:
    import dataclasses

    cfg, cell, source = load_config(config_file), exp.Cell("direct", 1, 0), Path("source-0123.safetensors")
    methods = dataclasses.asdict(cfg.transfer)
    for residual in ("cumulative_residual", "recurrent_residual"):  # before the gamma rule could be chosen
        del methods[residual]["gamma_rule"]
    del methods["multistep_l2_finetune"], methods["anchored_finetune"]  # before those methods were registered
    before = {  # what a cell's key hashed before configs could name a test set
        "cell": {"method": "direct", "amount": 1, "seed": 0}, "target": cfg.target.describe(), "split": "paths",
        "test_fraction": 0.2, "epsilon": 4.0, "offsets": [0], "horizon": None, "lyapunov_steps": 20,
        "method_config": methods, "source": source.name, "definition": "paper",
    }
    assert exp.cell_key(cfg, cell, source) == f"direct-1-0-{exp.digest(before)}"
    rule = dataclasses.replace(cfg.transfer.cumulative_residual, gamma_rule="lyapunov")
    ruled = dataclasses.replace(cfg, transfer=dataclasses.replace(cfg.transfer, cumulative_residual=rule))
    assert exp.cell_key(ruled, cell, source) != exp.cell_key(cfg, cell, source)
    longer = dataclasses.replace(cfg.transfer.multistep_l2_finetune, horizon=20)  # a changed setting is hashed
    stretched = dataclasses.replace(cfg, transfer=dataclasses.replace(cfg.transfer, multistep_l2_finetune=longer))
    assert exp.cell_key(stretched, cell, source) != exp.cell_key(cfg, cell, source)
    sustained = dataclasses.replace(cfg, test=DataSpec(hand="target", policy="sustained"))
    random = dataclasses.replace(cfg, test=DataSpec(hand="target"))
    keys = {exp.cell_key(c, cell, source) for c in (cfg, sustained, random)}
    assert len(keys) == 3


def test_the_sustained_policy_collects_long_holds_of_the_discrete_moves(tmp_path: Path) -> None:
    import numpy as np

    from t42_transfer.conventions import REAL_HAND_ACTIONS

    spec = DataSpec(hand="target", episodes=2, steps=150, seed=2, policy="sustained")
    data = exp.load_data(spec, tmp_path)
    moves = np.array(REAL_HAND_ACTIONS)
    for episode in data:
        assert all((moves == a).all(1).any() for a in episode.actions)  # every action one of the eight moves
        held = min(len(episode), 120)  # the shortest hold
        assert (episode.actions[:held] == episode.actions[0]).all()
    random = exp.load_data(DataSpec(hand="target", episodes=2, steps=150, seed=2), tmp_path)
    assert not any((moves == a).all(1).any() for a in random[0].actions)
    assert len(list(tmp_path.iterdir())) == 2  # two bags: the policy is part of the collected set's name


@pytest.mark.parametrize("split, amounts", [("paths", (1, 3)), ("fraction", (0.2, 0.5))])
def test_a_test_set_replaces_the_held_out_episodes_and_keeps_the_training_subsets(
        tmp_path: Path, make_set, split: str, amounts: tuple[float, ...]) -> None:
    import dataclasses

    target = _bag(tmp_path, "t", make_set([30] * 10, seed=3, hand="target"))
    test = make_set([50] * 3, seed=4, hand="target")
    plain = ExperimentConfig(name="t", source=DataSpec(bag=str(REPO / "bags" / "source_small")),
                                 target=DataSpec(bag=target), split=split, amounts=amounts, seeds=2,
                                 test_fraction=0.3)
    with_test = dataclasses.replace(plain, test=DataSpec(bag=_bag(tmp_path, "test", test)))
    episodes = exp.load_side(plain, "target", tmp_path / "cache").data
    tested = exp.load_test(with_test, tmp_path / "cache")
    assert exp.load_test(plain, tmp_path / "cache") is None and len(tested.data) == 3
    for amount in amounts:
        for seed in range(2):
            cell = exp.Cell("direct", amount, seed)
            train, held_out = exp.target_split(plain, episodes, cell)
            train_t, test_t = exp.target_split(with_test, episodes, cell, tested.data)
            assert [t.fingerprint() for t in train_t] == [t.fingerprint() for t in train] and len(train)
            assert test_t is tested.data and len(held_out) and {len(t) for t in held_out} == {30}  # test: 50 steps
    with pytest.raises(ValueError, match="exactly when the config names a test set"):
        exp.target_split(with_test, episodes, exp.Cell("direct", amounts[0], 0))


def test_a_run_scores_every_cell_on_the_test_set(config_file: Path, tmp_path: Path, make_set) -> None:
    import dataclasses

    test = make_set([50] * 2, seed=4, hand="target")
    cfg = dataclasses.replace(load_config(config_file), methods=("direct",), amounts=(1,), seeds=2)
    with_test = dataclasses.replace(cfg, test=DataSpec(bag=_bag(tmp_path, "test", test)))
    plain_rows = [r for r in run_experiment(cfg, tmp_path / "a", progress=False) if r["method"] == "direct"]
    rows = [r for r in run_experiment(with_test, tmp_path / "b", progress=False) if r["method"] == "direct"]
    assert [r["test_rollouts"] for r in plain_rows] == [3, 3] and [r["test_rollouts"] for r in rows] == [2, 2]
    assert [r["train_transitions"] for r in rows] == [r["train_transitions"] for r in plain_rows]
    assert rows[0]["divergence_mean"] == rows[1]["divergence_mean"]  # one test set for every seed
    quality = json.loads((tmp_path / "b" / "tiny" / "data_quality.json").read_text())
    assert quality["test"]["kept_episodes"] == 2 and "test" not in json.loads(
        (tmp_path / "a" / "tiny" / "data_quality.json").read_text())
    assert load_config(tmp_path / "b" / "tiny" / "config.yaml") == with_test
    assert main(["report", str(tmp_path / "b" / "tiny")]) == 0  # its paths figure draws the test set's episodes
    assert "; test: `" in (tmp_path / "b" / "tiny" / "report" / "report.md").read_text()


@pytest.mark.parametrize("how, episodes, origins", [("keep", 4, (0, 1, 2, 3)), ("drop", 3, (0, 2, 3)),
                                                    ("split", 5, (0, 1, 1, 2, 3))])
def test_flagged_episodes_kept_dropped_or_split_by_configuration(tmp_path: Path, make_set, how: str, episodes: int,
                                                                 origins: tuple[int, ...]) -> None:
    data, np = _with_jump(make_set)
    cfg = ExperimentConfig(name="q", source=DataSpec(bag=str(REPO / "bags" / "source_small")),
                               target=DataSpec(bag=_bag(tmp_path, "t", data), flagged=how), split="paths",
                               amounts=(1,))
    side = exp.load_side(cfg, "target", tmp_path / "cache")
    assert (len(side.data), side.origins) == (episodes, origins)
    assert side.quality["flagged_episodes"] == 1 and side.quality["kept_episodes"] == episodes
    assert side.quality["findings"]["1"] == [
        {"kind": "jump", "start": 20, "end": 21, "size": pytest.approx(12.0, abs=2)}
    ]
    if how == "keep":  # the default changes nothing
        assert all(a == b for a, b in zip(side.data, exp.load_data(cfg.target, tmp_path / "cache"), strict=True))
    if how == "split":
        assert [len(t) for t in side.data][1:3] == [20, 39]


def test_the_run_records_what_was_found_per_data_set(tmp_path: Path, make_set) -> None:
    data, _ = _with_jump(make_set)
    cfg = ExperimentConfig(name="q", source=DataSpec(bag=str(REPO / "bags" / "source_small")),
                               target=DataSpec(bag=_bag(tmp_path, "t", data), flagged="drop"), methods=("direct",),
                               split="paths", amounts=(1,), seeds=1, lyapunov_steps=5,
                               source_training=TrainConfig(epochs=1))
    rows = run_experiment(cfg, tmp_path / "runs", progress=False)
    assert rows[0]["test_rollouts"] == 2  # 3 episodes kept, 1 to train
    recorded = json.loads((tmp_path / "runs" / "q" / "data_quality.json").read_text())
    assert recorded["source"]["flagged_episodes"] == 0
    assert (recorded["target"]["flagged_episodes"], recorded["target"]["kept_episodes"]) == (1, 3)
    results = json.loads((tmp_path / "runs" / "q" / "results.json").read_text())
    assert results["data_quality"] == recorded


@pytest.mark.parametrize("spec, message", [
    ("{real: C}", "target.real must be one of \\['A', 'B'\\], got 'C'"),
    ("{real: B, real_object: ../x}", "target.real_object must be an object name"),
    ("{real: B, real_object: sqr30}", "testpaths_sqr30_red_d_v0.pkl: no such file"),
    ("{bag: x, real_object: egg50}", "target.real_object names the object of a real-hand file"),
    ("{real: B, mirror_about: grasp}", "target.mirror_about: grasp needs target.mirror_x: true"),
    ("{real: B, flagged: fix}", "target.flagged must be one of \\('keep', 'drop', 'split'\\)"),
    ("{real: B, exclude_test_sequences: true}", "only the source's training leaves test sequences out"),
    ("{hand: target, policy: wander}", "target.policy must be one of \\['random', 'sustained'\\], got 'wander'"),
    ("{real: B, policy: sustained}", "target.policy drives a simulated hand: it needs target.hand"),
    ("{real: A}\ntest: {hand: target, policy: Sustained}", "test.policy must be one of .*, got 'Sustained'"),
    ("{real: A}\ntest: {real: B, real_object: egg50}", "test.real: .*testpaths_egg50_red_d_v0.pkl: no such file"),
    ("{real: A}\ntest: {real: B, exclude_test_sequences: true}", "test.exclude_test_sequences: only the source"),
    ("{hand: target, paths: [0]}", "target.paths picks episodes of a file: it needs target.real or target.bag"),
    ("{real: B, paths: [1, 1]}", "target.paths must name distinct episodes, got \\[1, 1\\]"),
    ("{real: B, paths: [-1]}", "target.paths must be a path number"),
])
def test_bad_data_specs_are_one_line_errors_before_any_run_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                     capsys: pytest.CaptureFixture[str], spec: str,
                                                                     message: str) -> None:
    import re

    monkeypatch.setenv("T42_REAL_DATA", str(tmp_path))  # an empty folder: no real file is there
    (tmp_path / "testpaths_cyl35_d_v0.pkl").write_bytes(b"")
    config = tmp_path / "c.yaml"
    config.write_text(f"name: pair\nsource: {{real: A}}\ntarget: {spec}\nsplit: paths\namounts: [1]\n")
    assert main(["experiment", str(config), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("t42: error: ") and re.search(message, err), err
    assert not (tmp_path / "out" / "pair").exists()


def test_a_second_run_into_a_directory_in_use_is_refused(config_file: Path, tmp_path: Path) -> None:
    import dataclasses
    import fcntl

    cfg = dataclasses.replace(load_config(config_file), methods=("direct",), amounts=(1,), seeds=1)
    run_dir = tmp_path / "tiny"
    run_dir.mkdir()
    with open(run_dir / ".lock", "w") as held:  # the lock a running experiment holds
        held.write("pid 4242\n")
        held.flush()
        fcntl.flock(held, fcntl.LOCK_EX)
        with pytest.raises(ValueError, match=f"{run_dir}: in use by another run \\(pid 4242\\)"):
            run_experiment(cfg, tmp_path, progress=False)
    assert sorted(p.name for p in run_dir.iterdir()) == [".lock", "cells"]  # nothing of the run was written


def test_source_leaves_out_the_episodes_that_ran_a_test_sequence(tmp_path: Path, make_set) -> None:
    import dataclasses

    source = make_set([40] * 4, seed=8, hand="source")
    others = make_set([40] * 4, seed=9, hand="target")  # target episode k ran source episode k's actions, negated
    target = type(others)([dataclasses.replace(t, actions=-s.actions) for s, t in zip(source, others, strict=True)],
                          hand="target")
    cfg = ExperimentConfig(
        name="excl", source=DataSpec(bag=_bag(tmp_path, "s", source), exclude_test_sequences=True),
        target=DataSpec(bag=_bag(tmp_path, "t", target)), methods=("direct",), split="paths", amounts=(2,),
        seeds=2, lyapunov_steps=5, source_training=TrainConfig(epochs=1))
    sides = [exp.load_side(cfg, side, tmp_path / "cache") for side in ("source", "target")]
    for seed in range(2):
        cell = exp.Cell("direct", 2, seed)
        _, test = exp.target_split(cfg, sides[1].data, cell)
        tested = [i for i, t in enumerate(sides[1].data) if any(t is u for u in test)]
        assert exp.cell_excluded(cfg, cell, *sides) == tuple(tested) and len(tested) == 2
    unrelated = dataclasses.replace(cfg, source=dataclasses.replace(cfg.source, exclude_test_sequences=False))
    assert exp.cell_excluded(unrelated, exp.Cell("direct", 2, 0), *sides) == ()

    from t42_transfer.models.checkpoint import read_metadata

    run_experiment(cfg, tmp_path / "runs", progress=False)
    results = json.loads((tmp_path / "runs" / "excl" / "results.json").read_text())
    left_out = {tuple(v) for v in results["excluded_source_episodes"].values()}
    metas = [read_metadata(p) for p in (tmp_path / "runs" / "sources").glob("*.safetensors")]
    assert {tuple(m["extra"]["excluded_source_episodes"]) for m in metas} == left_out
    assert all(m["data"]["transitions"] == 40 * 2 for m in metas)  # trained on the two sequences not tested


def _real_pair(source: str, target: str, **target_spec) -> ExperimentConfig:  # type: ignore[no-untyped-def]
    return ExperimentConfig(name="pair", source=DataSpec(real=source),
                                target=DataSpec(real=target, **target_spec), split="paths", amounts=(1,))


@pytest.mark.realdata
def test_mirror_about_the_grasp_puts_hand_b_on_hand_a(t42_real_dir: Path, tmp_path: Path) -> None:
    import numpy as np

    from t42_transfer.data.trajectory import grasp_centre

    def gaps(about: str) -> tuple[np.ndarray, np.ndarray]:
        cfg = _real_pair("A", "B", mirror_x=True, mirror_about=about)
        a, b = (exp.load_side(cfg, side, tmp_path).data for side in ("source", "target"))
        starts = np.array([np.linalg.norm(p.states[0, :2] - q.states[0, :2]) for p, q in zip(a, b, strict=True)])
        # The same six action sequences: the mirrored B paths follow A's (first 790 steps, the shortest).
        apart = np.array([np.linalg.norm(p.states[:790, :2] - q.states[:790, :2], axis=1).mean()
                          for p, q in zip(a, b, strict=True)])
        return grasp_centre(b) - grasp_centre(a), starts, apart

    offset, starts, apart = gaps("grasp")
    assert np.abs(offset).max() < 1e-3
    assert np.median(starts) < 6 and apart.max() < 20 and np.median(apart) < 8
    offset, starts, apart = gaps("origin")  # the camera origin: B's grasp about 50 mm from A's
    assert 45 < abs(offset[0]) < 55 and starts.min() > 40 and apart.min() > 40


@pytest.mark.realdata
def test_negated_actions_for_hand_a(t42_real_dir: Path, tmp_path: Path) -> None:
    import numpy as np

    cfg = _real_pair("B", "A", negate_actions=True)
    raw = exp.load_data(cfg.target, tmp_path)
    side = exp.load_side(cfg, "target", tmp_path)
    assert all(np.array_equal(t.actions, -r.actions) and np.array_equal(t.states, r.states)
               for t, r in zip(side.data, raw, strict=True))
    assert exp.load_side(cfg, "source", tmp_path).data[0] == exp.load_data(cfg.source, tmp_path)[0]


@pytest.mark.realdata
def test_the_authors_b_to_a_keeps_test_sequences_out_of_the_source(t42_real_dir: Path, tmp_path: Path) -> None:
    import dataclasses

    from t42_transfer.models.checkpoint import read_metadata

    cfg = dataclasses.replace(load_config(REPO / "configs" / "real_b_to_a_authors.yaml"), methods=("direct",),
                              amounts=(3,), seeds=2, lyapunov_steps=5, horizon=50,
                              source_training=TrainConfig(epochs=1))
    sides = [exp.load_side(cfg, side, tmp_path) for side in ("source", "target")]
    for seed in range(2):
        cell = exp.Cell("direct", 3, seed)
        _, test = exp.target_split(cfg, sides[1].data, cell)
        tested = tuple(i for i, t in enumerate(sides[1].data) if any(t is u for u in test))
        assert exp.cell_excluded(cfg, cell, *sides) == tested  # path i of hand B ran path i of hand A's sequence
    run_experiment(cfg, tmp_path / "runs", progress=False)
    results = json.loads((tmp_path / "runs" / "real_b_to_a_authors" / "results.json").read_text())
    metas = [read_metadata(p) for p in (tmp_path / "runs" / "sources").glob("*.safetensors")]
    assert len(metas) == len(set(map(tuple, results["excluded_source_episodes"].values()))), "a source per draw"
    for meta in metas:
        left_out = meta["extra"]["excluded_source_episodes"]
        assert len(left_out) == 3 and left_out in results["excluded_source_episodes"].values()
        kept = [t for t, origin in zip(sides[0].data, sides[0].origins, strict=True) if origin not in left_out]
        assert meta["data"]["transitions"] == sum(len(t) for t in kept)


def _rows_without_timing(run_dir: Path) -> list[dict]:
    results = json.loads((run_dir / "results.json").read_text())
    return [{k: v for k, v in row.items() if k != "seconds"} for row in results["rows"]]


def test_a_local_dask_cluster_gives_the_results_of_one_worker_bit_for_bit(config_file: Path, tmp_path: Path) -> None:
    import dataclasses

    cfg = dataclasses.replace(load_config(config_file), methods=("naive_finetune",), amounts=(1,))
    run_experiment(cfg, tmp_path / "serial", progress=False)
    run_experiment(cfg, tmp_path / "dask", progress=False, scheduler="local:2")
    serial, dask = _rows_without_timing(tmp_path / "serial" / "tiny"), _rows_without_timing(tmp_path / "dask" / "tiny")
    assert len(serial) >= 2 and serial == dask  # json floats: exact equality is bit for bit


def test_a_bad_scheduler_is_a_one_line_error(config_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["experiment", str(config_file), "--out", str(tmp_path), "--scheduler", "local:0"])
    assert stop.value.code == 2
    assert "scheduler must be local:N" in capsys.readouterr().err
    assert not (tmp_path / "tiny").exists()


def test_a_scheduler_address_nothing_answers_is_refused_before_any_work(config_file: Path, tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture) -> None:
    import socket

    with socket.socket() as closed:  # a port just freed: nothing listens there
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    assert main(["experiment", str(config_file), "--out", str(tmp_path), "--scheduler", f"tcp://127.0.0.1:{port}"]) == 2
    assert f"no Dask scheduler answers at tcp://127.0.0.1:{port}" in capsys.readouterr().err
    assert not (tmp_path / "tiny").exists()  # no source model trained, no cell run


@pytest.mark.slow
def test_a_worker_killed_mid_run_loses_only_its_cell(config_file: Path, tmp_path: Path) -> None:
    """A Dask worker SIGKILLed while cells run: its nanny starts a new one, the scheduler reruns the lost cell, and
    the run ends with the numbers of a serial run."""
    import dataclasses
    import os
    import signal
    import threading

    from distributed import Client, LocalCluster

    from t42_transfer.evaluation import cluster

    cfg = dataclasses.replace(load_config(config_file), methods=("naive_finetune", "cumulative_residual"))
    run_experiment(cfg, tmp_path / "serial", progress=False)
    killed: list[int] = []
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as local:
        def kill_one_worker_once_cells_run() -> None:
            with Client(local) as client:
                while not any(client.processing().values()):
                    threading.Event().wait(0.05)
                pids = client.run(os.getpid)
                killed.append(next(iter(pids.values())))
                os.kill(killed[0], signal.SIGKILL)

        killer = threading.Thread(target=kill_one_worker_once_cells_run, daemon=True)
        killer.start()
        run_experiment(cfg, tmp_path / "dask", progress=False, scheduler=local.scheduler_address)
        killer.join(timeout=30)
    assert killed, "no worker was killed"
    assert _rows_without_timing(tmp_path / "serial" / "tiny") == _rows_without_timing(tmp_path / "dask" / "tiny")
    assert cluster.check_scheduler(local.scheduler_address) == local.scheduler_address


def test_rows_name_their_training_draw_the_same_for_every_method(config_file: Path, tmp_path: Path) -> None:
    import dataclasses

    cfg = dataclasses.replace(load_config(config_file), methods=("direct", "naive_finetune"), amounts=(1, 2))
    rows = run_experiment(cfg, tmp_path, progress=False)
    assert {r["method"] for r in rows} == {"direct", "naive_finetune", "hold_still"}
    draws = {(r["amount"], r["seed"]): set() for r in rows}
    for row in rows:
        draws[(row["amount"], row["seed"])].add(row["train_draw"])
    assert all(len(d) == 1 for d in draws.values())  # one draw per cell, whatever the method, hold-still too
    assert len({next(iter(d)) for (amount, _), d in draws.items() if amount == 2}) == 2  # two seeds, two draws

    # cells kept from before the column get their draw back when the run is resumed, from the split alone
    for cell in (tmp_path / cfg.name / "cells").glob("*.json"):
        row = json.loads(cell.read_text())
        del row["train_draw"]
        cell.write_text(json.dumps(row))
    def untimed(table: list[dict]) -> list[dict]:
        return [{k: v for k, v in row.items() if k != "seconds"} for row in table]

    assert untimed(run_experiment(cfg, tmp_path, progress=False)) == untimed(rows)


def test_paths_pick_a_files_episodes_in_order_and_refuse_what_is_not_there(tmp_path: Path) -> None:
    from t42_transfer.evaluation.experiment import load_spec
    from t42_transfer.evaluation.experiment_config import DataSpec

    bag = str(REPO / "bags" / "target_small")
    every = load_spec(DataSpec(bag=bag), tmp_path).data
    assert len(every) >= 3
    picked = load_spec(DataSpec(bag=bag, paths=(2, 0)), tmp_path).data
    assert len(picked) == 2
    for got, want in zip(picked, (every[2], every[0]), strict=True):
        np.testing.assert_array_equal(got.states, want.states)
        np.testing.assert_array_equal(got.actions, want.actions)
    with pytest.raises(ValueError, match=rf"paths: the data has {len(every)} episodes \(0 to {len(every) - 1}\), "
                                         rf"not {len(every)}"):
        load_spec(DataSpec(bag=bag, paths=(0, len(every))), tmp_path)


@pytest.mark.parametrize("side", ["source", "target"])
def test_a_path_the_file_lacks_is_refused_before_anything_is_written(side: str, config_file: Path, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    bag = REPO / "bags" / f"{side}_small"
    text = config_file.read_text().replace(f"{side}: {{bag: {bag}}}", f"{side}: {{bag: {bag}, paths: [0, 999]}}")
    assert "999" in text
    config_file.write_text(text)
    assert main(["experiment", str(config_file), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "paths: the data has" in err and "not 999" in err, err
    assert not (tmp_path / "out" / "tiny").exists()


def test_sides_whose_actions_are_in_different_units_are_refused_before_anything_is_written(
        config_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    authors = save_model(TransitionModel(Normalisation.identity()), tmp_path / "authors.safetensors", method="source",
                         action_unit_rad=AUTHORS_ACTION_UNIT_RAD)  # as an import of the authors' real-hand models is
    text = config_file.read_text().replace(f"source: {{bag: {REPO / 'bags' / 'source_small'}}}",
                                           f"source: {{model: {authors}}}")
    text = text.replace("source_training: {epochs: 2}\n", "")
    assert str(authors) in text
    config_file.write_text(text)
    assert main(["experiment", str(config_file), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the sides' actions are in different units (source 0.00388 rad, target 0.025 " \
        "rad a step at an action of 1" in err, err
    assert not (tmp_path / "out" / "tiny").exists()


@pytest.mark.parametrize("spec, message", [
    (dict(hand="target", action_unit_rad=0.01), "target.action_unit_rad is the unit a bag is read in: it needs "
                                                "target.bag"),
    (dict(bag="b", action_unit_rad=0.5), r"action_unit_rad must be in \(0, 0.1\]"),
    (dict(bag="b", action_unit_rad=0.0), r"action_unit_rad must be in \(0, 0.1\]"),
])
def test_a_bags_action_unit_is_checked(spec: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        check_spec(DataSpec(**spec), "target")
