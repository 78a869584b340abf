"""An experiment whose source is a trained model (``source: {model: PATH}``): no source data, no source training.

The model is a project model file or one of the paper authors' files (a hand-made one here, written in their
legacy format by test_authors_models' writer), imported on the fly with the spec's action negation.
"""

from __future__ import annotations

import json
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from test_authors_models import Net, Norm, Writer, trajnet

from t42_transfer.cli import main
from t42_transfer.conventions import AUTHORS_ACTION_UNIT_RAD
from t42_transfer.data.bag import read_bag, write_bag
from t42_transfer.evaluation import experiment as exp
from t42_transfer.evaluation.experiment import run_experiment
from t42_transfer.evaluation.experiment_config import DataSpec, ExperimentConfig, load_config
from t42_transfer.evaluation.metrics import evaluate_model
from t42_transfer.models.authors import import_authors_model
from t42_transfer.models.checkpoint import load_model

REPO = Path(__file__).resolve().parents[1]
TARGET = REPO / "bags" / "target_small"


@pytest.fixture(scope="module")
def authors_pkl(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A hand-made authors' plain model (the family of their B source model)."""
    rng = np.random.default_rng(3)
    path = tmp_path_factory.mktemp("authors") / "real_B_heldout0.1_1.pkl"
    path.write_bytes(Writer().file(trajnet(Net.random(rng, 16), Norm.random(rng), "a", task="real_B")))
    return path


def _no_source_training(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(exp, "train_transition_model", lambda *a, **k: pytest.fail("the source was trained"))
    monkeypatch.setattr(exp, "load_data", lambda spec, cache, progress=True: pytest.fail(f"data was read for {spec}")
                        if spec.model is not None else _load_data(spec, cache, progress))


_load_data = exp.load_data


def _config(model: Path, methods: tuple[str, ...] = ("direct",), target: DataSpec | None = None,
            **source: object) -> ExperimentConfig:
    target = DataSpec(bag=str(TARGET)) if target is None else target
    return ExperimentConfig(name="m", source=DataSpec(model=str(model), **source), target=target,
                            methods=methods, split="paths", amounts=(2,), seeds=1, lyapunov_steps=5, workers=1)


@pytest.fixture(scope="module")
def authors_target(tmp_path_factory: pytest.TempPathFactory) -> DataSpec:
    """TARGET's episodes as the steps of a hand driven in the authors' unit, read in it: the same actions."""
    bag = write_bag(tmp_path_factory.mktemp("authors_unit") / "target", read_bag(TARGET),
                    action_unit_rad=AUTHORS_ACTION_UNIT_RAD)
    return DataSpec(bag=str(bag), action_unit_rad=AUTHORS_ACTION_UNIT_RAD)


def _direct_row(rows: list[dict]) -> dict:
    return next(r for r in rows if r["method"] == "direct")


def test_a_model_file_is_the_source_as_it_is(source_model: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                             one_torch_thread: None) -> None:
    _no_source_training(monkeypatch)
    cfg = _config(source_model, ("direct", "naive_finetune"))
    rows = run_experiment(cfg, tmp_path / "runs", progress=False)
    assert {r["method"] for r in rows} == {"direct", "naive_finetune", "hold_still"}
    kept = exp.source_model_path(cfg, tmp_path / "runs" / "m")
    assert kept.read_bytes() == source_model.read_bytes()  # kept under its content's name, unchanged
    _, test = exp.target_split(cfg, read_bag(TARGET), exp.Cell("direct", 2, 0))
    expected = evaluate_model(load_model(source_model)[0], test, cfg.epsilon_mm)
    assert _direct_row(rows)["divergence_mean"] == expected["divergence_mean"]
    quality = json.loads((tmp_path / "runs" / "m" / "data_quality.json").read_text())
    assert quality["source"]["model"] == str(source_model) and quality["source"]["episodes"] == 0
    assert load_config(tmp_path / "runs" / "m" / "config.yaml") == cfg  # the report reads the run's config back
    # The cells' models keep the source file's workspace for the planner.
    cell_model = next((tmp_path / "runs" / "m" / "models").glob("direct-*.safetensors"))
    assert load_model(cell_model)[1]["extra"]["workspace"] == load_model(source_model)[1]["extra"]["workspace"]


@pytest.mark.parametrize("negate", [False, True])
def test_an_authors_file_is_imported_on_the_fly_with_the_specs_negation(authors_pkl: Path, tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch,
                                                                        authors_target: DataSpec,
                                                                        negate: bool) -> None:
    _no_source_training(monkeypatch)
    cfg = _config(authors_pkl, target=authors_target, negate_actions=negate)
    with pytest.raises(ValueError, match=r"the sides' actions are in different units \(source 0\.00388 rad, "
                                         r"target 0\.025 rad"):
        run_experiment(_config(authors_pkl, negate_actions=negate), tmp_path / "refused", progress=False)
    assert not (tmp_path / "refused").exists()
    rows = run_experiment(cfg, tmp_path / "runs", progress=False)
    imported = import_authors_model(authors_pkl, negate_actions=negate)[0].model
    kept, meta = load_model(exp.source_model_path(cfg, tmp_path / "runs" / "m"))
    assert meta["extra"]["authors"]["negate_actions"] is negate and meta["extra"]["authors"]["family"] == "mlp"
    episode = read_bag(TARGET)[0]
    x0, actions = torch.tensor(episode.states[:1]), torch.tensor(episode.actions[None])
    assert torch.equal(kept.rollout(x0, actions), imported.rollout(x0, actions))
    _, test = exp.target_split(cfg, read_bag(TARGET), exp.Cell("direct", 2, 0))
    assert _direct_row(rows)["divergence_mean"] == evaluate_model(imported, test, cfg.epsilon_mm)["divergence_mean"]


def test_the_negation_makes_a_different_source(authors_pkl: Path, tmp_path: Path) -> None:
    plain, negated = (exp.source_model_path(_config(authors_pkl, negate_actions=n), tmp_path) for n in (False, True))
    assert plain != negated


def test_a_model_source_loads_from_yaml(authors_pkl: Path, tmp_path: Path) -> None:
    config = tmp_path / "c.yaml"
    config.write_text(f"name: m\nsource: {{model: {authors_pkl}, negate_actions: true}}\ntarget: {{bag: {TARGET}}}\n"
                      f"split: paths\namounts: [1]\n")
    cfg = load_config(config)
    assert cfg.source.model == str(authors_pkl) and cfg.source.negate_actions
    assert cfg.source_training is None  # nothing trains it


def _not_a_model(tmp_path: Path) -> str:
    path = tmp_path / "norms.pkl"
    path.write_bytes(pickle.dumps({"x_mean": [0.0] * 4}, protocol=2))
    return str(path)


def _garbage_checkpoint(tmp_path: Path) -> str:
    path = tmp_path / "broken.safetensors"
    path.write_bytes(b"\x10\0\0\0\0\0\0\0{not json at all")
    return str(path)


@pytest.mark.parametrize(("source", "target", "extra", "message"), [
    (lambda d: f"{{model: {d / 'missing.pkl'}}}", "", "", r"source\.model: .*missing\.pkl: does not exist"),
    (lambda d: f"{{model: {d / 'missing.safetensors'}}}", "", "", r"source\.model: .*missing\.safetensors: does not"),
    (lambda d: f"{{model: {_not_a_model(d)}}}", "", "", r"source\.model: .*norms\.pkl: .*not a legacy torch file"),
    (lambda d: f"{{model: {_garbage_checkpoint(d)}}}", "", "", r"source\.model: .*broken\.safetensors: "),
    (lambda d: f"{{model: {_garbage_checkpoint(d)}, negate_actions: true}}", "", "",
     r"source\.negate_actions applies to an authors' \.pkl file"),
    (lambda d: f"{{model: {d / 'm.pkl'}, bag: {TARGET}}}", "", "",
     r"source needs exactly one of hand, bag, real or model, got \['bag', 'model'\]"),
    (lambda d: f"{{model: {d / 'm.pkl'}, mirror_x: true}}", "", "", r"no data for \['mirror_x'\] to apply to"),
    (lambda d: f"{{model: {d / 'm.pkl'}, flagged: drop}}", "", "", r"no data for \['flagged'\]"),
    (lambda d: f"{{model: {d / 'm.pkl'}}}", "", "source_training: {epochs: 2}\n",
     r"source_training trains the source on its data; source\.model is a trained model"),
    (lambda d: f"{{bag: {TARGET}}}", f"{{model: {TARGET}}}", "", r"target\.model: only an experiment's source"),
    (lambda d: f"{{model: {d / 'm.pkl'}}}", f"{{bag: {TARGET}, mirror_x: true, mirror_about: grasp}}", "",
     r"target\.mirror_about: grasp mirrors onto the source's grasp, and source\.model has no source data"),
    (lambda d: "{model: ''}", "", "", r"source\.model must be a file path"),
])
def test_bad_model_sources_are_one_line_errors_before_anything_is_written(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], source, target: str, extra: str, message: str) -> None:
    config = tmp_path / "c.yaml"
    config.write_text(f"name: m\nsource: {source(tmp_path)}\ntarget: {target or f'{{bag: {TARGET}}}'}\n"
                      f"split: paths\namounts: [1]\n{extra}")
    assert main(["experiment", str(config), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("t42: error: ") and re.search(message, err), err
    assert not (tmp_path / "out").exists()
