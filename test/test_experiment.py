"""The experiment runner and report on the fixture bags: cells, resuming, workers, config errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from t42_transfer.cli import main
from t42_transfer.evaluation import experiment as exp
from t42_transfer.evaluation.experiment import load_config, run_experiment

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
    assert len(rows) == 3 * 2 * 2
    assert {(r["method"], r["amount"], r["seed"]) for r in rows} == {
        (m, a, s) for m in cfg.methods for a in (1, 2) for s in (0, 1)
    }
    for row in rows:
        assert row["train_episodes"] == row["amount"] and row["test_rollouts"] == 4 - row["amount"]
        assert row["divergence_mean"] >= 0 and row["position_mse_mean"] >= 0
    direct = [r for r in rows if r["method"] == "direct" and r["amount"] == 1]
    assert direct[0]["lyapunov_mean"] != direct[1]["lyapunov_mean"]  # different test paths per seed

    # A second run reads every cell back instead of transferring again.
    monkeypatch.setattr(exp, "transfer", lambda *a, **k: pytest.fail("a cached cell was recomputed"))
    again = run_experiment(cfg, tmp_path / "runs", progress=False)
    assert again == rows

    run_dir = tmp_path / "runs" / "tiny"
    assert (run_dir / "results.csv").read_text().count("\n") == 13
    assert main(["report", str(run_dir)]) == 0
    report = (run_dir / "report" / "report.md").read_text()
    assert "Naive fine-tuning is worse than no adaptation" in report
    for figure in ("divergence_mean.png", "position_mse_mean.png", "lyapunov_mean.png", "paths.png"):
        assert (run_dir / "report" / figure).stat().st_size > 5000


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
        (lambda t: t.replace("source_training: {epochs: 2}", "source_training: {epoch: 2}"), "unknown TrainConfig settings"),
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


@pytest.mark.parametrize("shipped", sorted(set((REPO / "configs").rglob("*.yaml")) - {REPO / "configs" / "suite.yaml"}),
                         ids=lambda p: p.name)
def test_every_shipped_config_loads(shipped: Path) -> None:
    cfg = load_config(shipped)
    assert exp.SAFE_NAME.fullmatch(cfg.name)


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
    assert len(run_experiment(cfg, tmp_path, progress=False)) == 1  # not "in use by another run"


def test_results_json_holds_the_config(config_file: Path, tmp_path: Path) -> None:
    import dataclasses

    cfg = dataclasses.replace(load_config(config_file), methods=("direct",), amounts=(1,), seeds=1)
    run_experiment(cfg, tmp_path, progress=False)
    content = json.loads((tmp_path / "tiny" / "results.json").read_text())
    assert content["config"]["split"] == "paths" and len(content["rows"]) == 1
    assert load_config(tmp_path / "tiny" / "config.yaml") == cfg


def test_cell_models_store_the_planning_workspace(config_file: Path, tmp_path: Path) -> None:
    import dataclasses

    from t42_transfer.models.checkpoint import read_metadata
    from t42_transfer.planning.workspace import Workspace

    cfg = dataclasses.replace(load_config(config_file), methods=("direct",), amounts=(1,), seeds=1)
    run_experiment(cfg, tmp_path, progress=False)
    (model_file,) = (tmp_path / "tiny" / "models").glob("*.safetensors")
    workspace = Workspace.from_metadata(read_metadata(model_file))
    assert workspace is not None and workspace.load_limit == 280.0
