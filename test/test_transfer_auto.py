"""Method ``auto``: candidates trained on some target episodes, scored on others held out whole, the best kept."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from t42_transfer.data.bag import assign_start_times, write_bag
from t42_transfer.data.trajectory import Trajectory, TrajectorySet, split_by_fraction
from t42_transfer.models import Normalisation, TransitionModel
from t42_transfer.models.checkpoint import load_model, save_model
from t42_transfer.models.training import TrainConfig, train_transition_model
from t42_transfer.planning.workspace import Workspace
from t42_transfer.transfer import METHODS, TransferConfig, transfer
from t42_transfer.transfer.config import AutoConfig
from t42_transfer.transfer.methods import select_method
from t42_transfer.transfer.online import STATE_FILE, OnlineTransferSpec, TransferRefused, run_transfer

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _constant_velocity(speed_mm: float) -> TransitionModel:
    """A hand-made model: the object moves ``speed_mm`` along x every step, whatever the action."""
    model = TransitionModel(Normalisation(*(np.asarray(v, np.float32) for v in (
        [0] * 4, [1] * 4, [speed_mm, 0, 0, 0], [1] * 4))), hidden=4, dropout=0.0)
    with torch.no_grad():
        for p in model.net.parameters():
            p.zero_()
    return model.eval()


def _target(episodes: int, steps: int = 30) -> TrajectorySet:
    """The target hand moves the object 1 mm along x per step."""
    rng = np.random.default_rng(0)
    out = []
    for _ in range(episodes):
        states = np.zeros((steps + 1, 4), np.float32)
        states[:, 0] = np.arange(steps + 1)
        out.append(Trajectory(states, rng.uniform(-1, 1, (steps, 2)).astype(np.float32)))
    return TrajectorySet(out, hand="target")


@pytest.fixture
def rigged(monkeypatch):
    """Candidates whose held-out scores are known: exact (1 mm/step), too fast (3 mm/step), failing."""
    monkeypatch.setitem(METHODS, "exact", lambda s, t, c, seed, on_epoch=None: _constant_velocity(1.0))
    monkeypatch.setitem(METHODS, "too_fast", lambda s, t, c, seed, on_epoch=None: _constant_velocity(3.0))

    def broken(source, target, cfg, seed, on_epoch=None):
        raise ValueError("no episode is long enough")

    monkeypatch.setitem(METHODS, "broken", broken)


def _auto(candidates: tuple[str, ...], **settings) -> TransferConfig:
    return dataclasses.replace(TransferConfig(), auto=AutoConfig(candidates=candidates, **settings))


def test_auto_picks_the_best_held_out_score_and_reports_every_candidate(rigged) -> None:
    source = _constant_velocity(0.0)  # direct: the object stays put
    target = _target(8)
    selection = select_method(source, target, _auto(("direct", "too_fast", "broken", "exact")), seed=1)
    held_out, train = split_by_fraction(target, 0.25, 1)
    assert (selection.held_out_episodes, selection.train_episodes) == (len(held_out), len(train)) == (2, 6)
    scores = {c.method: c for c in selection.candidates}
    assert list(scores) == ["direct", "too_fast", "broken", "exact"]
    # errors along x: direct k mm (past 4 mm at k = 5), too_fast 2k (past at 3), exact none (30 steps)
    assert scores["direct"].divergence_steps == 4 and scores["too_fast"].divergence_steps == 2
    assert scores["exact"].divergence_steps == 30 and scores["exact"].position_mse_mm2 == 0
    assert "no episode is long enough" in scores["broken"].error and scores["broken"].divergence_steps is None
    assert selection.best == "exact" and not selection.note
    x0, actions = torch.zeros(1, 4), torch.zeros(1, 5, 2)
    assert torch.equal(selection.model.rollout(x0, actions), _constant_velocity(1.0).rollout(x0, actions))
    text = selection.describe()
    assert all(name in text for name in scores) and "auto picked exact" in text
    assert transfer("auto", source, target, _auto(("direct", "exact")), seed=1).rollout(x0, actions)[0, -1, 0] == 5


def test_ties_go_to_the_lower_mse_then_the_earlier_candidate(rigged) -> None:
    source = _constant_velocity(0.0)
    same = select_method(source, _target(4), _auto(("exact", "direct", "too_fast")), seed=0)
    assert same.best == "exact"
    # On 3-step paths every candidate but too_fast survives: direct and exact tie on divergence, exact has MSE 0.
    short = select_method(source, _target(4, steps=3), _auto(("direct", "exact")), seed=0)
    scores = {c.method: c for c in short.candidates}
    assert scores["direct"].divergence_steps == scores["exact"].divergence_steps == 3 and short.best == "exact"


def test_too_few_episodes_is_an_error_saying_so_unless_a_fallback_is_named(rigged) -> None:
    source = _constant_velocity(0.0)
    with pytest.raises(ValueError, match="auto needs at least 2 target episodes .* got 1 .*auto.fallback"):
        select_method(source, _target(1), _auto(("direct", "exact")))
    fallback = select_method(source, _target(1), _auto(("direct", "exact"), fallback="exact"))
    assert fallback.best == "exact" and fallback.candidates == () and fallback.note.startswith("fallback")
    assert "nothing scored" in fallback.describe()
    with pytest.raises(ValueError, match="no candidate could be trained"):
        select_method(source, _target(4), _auto(("broken",)))
    with pytest.raises(ValueError, match="other than auto"):
        select_method(source, _target(4), _auto(("direct", "auto")))


@pytest.fixture(scope="module")
def source_file(tmp_path_factory, make_set, one_torch_thread):
    data = make_set([40] * 6, seed=10, hand="source")
    model, _ = train_transition_model(data, TrainConfig(epochs=1))
    path = tmp_path_factory.mktemp("source") / "source.safetensors"
    return save_model(model, path, method="source", extra={"workspace": Workspace.from_trajectories(data).to_dict()})


def test_the_service_runs_auto_and_reports_every_candidate(tmp_path, source_file, make_set) -> None:
    write_bag(tmp_path / "bags" / "b0", TrajectorySet(assign_start_times(make_set([30] * 8, seed=11, hand="target"))))
    fast = TrainConfig(epochs=2, patience=None)
    cfg = dataclasses.replace(
        _auto(("direct", "naive_finetune", "cumulative_residual")),
        naive_finetune=dataclasses.replace(TransferConfig().naive_finetune, train=dataclasses.replace(fast, lr=1e-3)),
        cumulative_residual=dataclasses.replace(TransferConfig().cumulative_residual, train=fast),
    )
    spec = OnlineTransferSpec(source_model=source_file, model_dir=tmp_path / "models", bag_dir=tmp_path / "bags",
                              method="auto", config=cfg)
    result = run_transfer(spec)
    assert result.selection is not None and result.selection.best in cfg.auto.candidates
    summary = result.summary()
    for name in cfg.auto.candidates:
        assert name in summary
    assert summary.startswith(f"auto (auto picked {result.selection.best}") and "\n" not in summary
    _, meta = load_model(result.model_path)
    assert meta["method"] == result.selection.best
    picked = meta["extra"]["selection"]
    assert picked["best"] == result.selection.best and [c["method"] for c in picked["candidates"]] == list(
        cfg.auto.candidates)
    record = json.loads((tmp_path / "models" / STATE_FILE).read_text())["transfers"][-1]
    assert record["method"] == "auto" and record["selection"] == picked


def test_the_service_refuses_auto_when_too_few_episodes_remain(tmp_path, source_file, make_set) -> None:
    write_bag(tmp_path / "bags" / "b0", TrajectorySet(assign_start_times(make_set([30, 30], seed=12, hand="target"))))
    spec = OnlineTransferSpec(source_model=source_file, model_dir=tmp_path / "models", bag_dir=tmp_path / "bags",
                              method="auto")
    with pytest.raises(TransferRefused, match="auto needs at least 2 target episodes .* got 1"):
        run_transfer(spec)
    assert not (tmp_path / "models").exists() or not any((tmp_path / "models").iterdir())


def _plan_like(episode: Trajectory) -> Trajectory:
    """The episode with its actions zeroed but for a stretch in the middle: an executed plan's shape."""
    actions = np.zeros_like(episode.actions)
    actions[5:10] = episode.actions[5:10]
    return dataclasses.replace(episode, actions=actions)


def test_hold_out_takes_a_share_of_each_kind_of_episode(make_set) -> None:
    from t42_transfer.transfer.online import hold_out

    explored = list(make_set([30] * 6, seed=13, hand="target"))
    plans = [_plan_like(t) for t in make_set([30] * 4, seed=14, hand="target")]
    data = TrajectorySet(explored + plans, hand="target")
    for seed in range(10):  # a share of all ten at random would hold out no plan for some seeds
        train, held = hold_out(data, 0.25, seed)
        kinds = sorted(int(np.abs(t.actions).sum(axis=1).astype(bool).mean() < 0.5) for t in held)
        assert kinds == [0, 1] and len(train) == 8  # int(0.25 * 6) = 1 exploration, int(0.25 * 4) -> 1 plan
    one_plan = TrajectorySet(explored + plans[:1], hand="target")
    train, held = hold_out(one_plan, 0.25, 0)  # a kind with one episode trains
    assert len(held) == 1 and all(np.abs(t.actions).sum() > 0 for t in held) and plans[0] in list(train)
    only_two = TrajectorySet([explored[0], plans[0]], hand="target")
    assert [len(part) for part in hold_out(only_two, 0.25, 0)] == [1, 1]  # no kind can split: one held out of all


def test_the_service_scores_each_kind_of_held_out_episode(tmp_path, source_file, make_set) -> None:
    explored = list(make_set([30] * 6, seed=15, hand="target"))
    plans = [_plan_like(t) for t in make_set([30] * 4, seed=16, hand="target")]
    write_bag(tmp_path / "bags" / "b0", TrajectorySet(assign_start_times(explored + plans)))
    fast = dataclasses.replace(TransferConfig().l2_finetune, train=TrainConfig(epochs=1, patience=None))
    spec = OnlineTransferSpec(source_model=source_file, model_dir=tmp_path / "models", bag_dir=tmp_path / "bags",
                              config=dataclasses.replace(TransferConfig(), l2_finetune=fast))
    result = run_transfer(spec)
    by_kind = result.held_out_by_kind
    assert sorted(by_kind) == ["exploration", "plan"] and by_kind["exploration"]["episodes"] == 1
    assert by_kind["plan"]["episodes"] == 1 and result.held_out_episodes == 2
    for scores in by_kind.values():
        assert scores["hold_still_divergence_steps"] >= 1 and scores["model_position_mse_mm2"] > 0
    assert "held out by kind: exploration (1):" in result.summary() and ", plan (1):" in result.summary()
    _, meta = load_model(result.model_path)
    assert meta["extra"]["evaluation"]["by_kind"] == json.loads(json.dumps(by_kind))
