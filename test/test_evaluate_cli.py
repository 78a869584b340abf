"""``t42 evaluate``: hand-made models on hand-made paths with known divergence, the JSON, bad input, and the
authors' reference figures on the real files when they are present."""

from __future__ import annotations

import json
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from t42_transfer.cli import main
from t42_transfer.conventions import AUTHORS_ACTION_UNIT_RAD
from t42_transfer.data.bag import assign_start_times, write_bag
from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.evaluation.evaluate import evaluate_models, score_model
from t42_transfer.models.checkpoint import save_model
from t42_transfer.models.network import Normalisation, TransitionModel

SPEEDS = (1.0, 0.5, 2.0)
"""Hand-made paths: the object moves along x at these mm per step (y and loads still)."""
LENGTHS = (40, 30, 50)
MODEL_SPEED = 0.5
"""The hand-made model moves x 0.5 mm per step whatever the action."""
AUTHORS_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "authors_models"


def _paths() -> TrajectorySet:
    rng = np.random.default_rng(0)
    episodes = []
    for speed, steps in zip(SPEEDS, LENGTHS, strict=True):
        k = np.arange(steps + 1)
        states = np.column_stack([10 + speed * k, np.full(steps + 1, 100.0), np.full(steps + 1, 80.0),
                                  np.full(steps + 1, -80.0)])
        episodes.append(Trajectory(states=states, actions=rng.choice([-1.0, 1.0], (steps, 2)), hand="made"))
    return TrajectorySet(assign_start_times(episodes), hand="made")


def _expected(speed_gap: float, steps: int, eps: float) -> int:
    """Steps before |speed_gap| k first exceeds eps (paper count), or ``steps`` when it never does."""
    k = np.arange(1, steps + 1)
    over = np.nonzero(abs(speed_gap) * k > eps)[0]
    return int(k[over[0]] - 1) if len(over) else steps


def _expected_mse(speed_gap: float, steps: int) -> float:
    return float(np.mean((speed_gap * np.arange(1, steps + 1)) ** 2))


def _constant_model() -> TransitionModel:
    """x += 0.5 mm per step: a zero last layer, the change's mean 0.5 mm in x."""
    zeros, ones = np.zeros(4, np.float32), np.ones(4, np.float32)
    model = TransitionModel(Normalisation(zeros, ones, np.array([MODEL_SPEED, 0, 0, 0], np.float32), ones))
    with torch.no_grad():
        model.net[6].weight.zero_()
        model.net[6].bias.zero_()
    return model.eval()


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("evaluate")
    write_bag(root / "paths", _paths())
    constant = save_model(_constant_model(), root / "constant.safetensors", method="made")
    torch.manual_seed(0)
    norm = Normalisation(np.array([20, 100, 80, -80], np.float32), np.array([10, 10, 10, 10], np.float32),
                         np.zeros(4, np.float32), np.full(4, 0.5, np.float32))
    noisy = save_model(TransitionModel(norm, dropout=0.3).eval(), root / "noisy.safetensors", method="made")
    authors_unit = save_model(_constant_model(), root / "authors_unit.safetensors", method="made",
                              action_unit_rad=AUTHORS_ACTION_UNIT_RAD)
    torch.manual_seed(0)  # the same weights as noisy's, in the authors' unit
    noisy_authors = save_model(TransitionModel(norm, dropout=0.3).eval(), root / "noisy_authors.safetensors",
                               method="made", action_unit_rad=AUTHORS_ACTION_UNIT_RAD)
    authors_bag = write_bag(root / "authors_paths", _paths(), action_unit_rad=AUTHORS_ACTION_UNIT_RAD)
    return {"bag": root / "paths", "constant": constant, "noisy": noisy, "authors_unit": authors_unit,
            "noisy_authors": noisy_authors, "authors_bag": authors_bag}


def _run(made: dict[str, Path], *extra: str, models: tuple[str, ...] = ("constant",)) -> int:
    return main(["evaluate", *(str(made[m]) for m in models), "--on", f"{{bag: {made['bag']}}}", "--quiet", *extra])


def test_known_divergence_and_mse_per_path_and_overall(made, tmp_path, capsys):
    out = tmp_path / "e.json"
    assert _run(made, "--json", str(out)) == 0
    result = json.loads(out.read_text())
    for scores, speed in ((result["models"][0], MODEL_SPEED), (result["hold_still"], 0.0)):
        for i, (path, true_speed, steps) in enumerate(zip(scores["per_path"], SPEEDS, LENGTHS, strict=True)):
            gap = true_speed - speed
            assert path == {"episode": i, "steps": steps, "divergence_4mm": _expected(gap, steps, 4.0),
                            "divergence_10mm": _expected(gap, steps, 10.0),
                            "position_mse": pytest.approx(_expected_mse(gap, steps), rel=1e-5)}
        for key, per in (("divergence_mean_4mm", "divergence_4mm"), ("divergence_mean_10mm", "divergence_10mm"),
                         ("position_mse_mean", "position_mse")):
            assert scores[key] == pytest.approx(np.mean([p[per] for p in scores["per_path"]]))
    # The values worked out by hand: model 8, 30 (never), 2 at 4 mm; hold-still 4, 8, 2.
    assert [p["divergence_4mm"] for p in result["models"][0]["per_path"]] == [8, 30, 2]
    assert [p["divergence_4mm"] for p in result["hold_still"]["per_path"]] == [4, 8, 2]
    table = capsys.readouterr().out
    assert "hold still" in table and "constant.safetensors" in table and "dropout on" in table  # the paper's note



def test_a_model_of_another_unit_scores_as_much_on_the_same_steps_recorded_in_its_unit(made, tmp_path):
    """The same weights in the authors' unit, on the same paths as the steps of a hand driven in it: the bag declares
    that unit and is read in it, or in the unit named (written to three figures, as people write it)."""
    ours, theirs, named = (tmp_path / f"{name}.json" for name in ("ours", "theirs", "named"))
    assert _run(made, "--json", str(ours), models=("noisy",)) == 0
    assert main(["evaluate", str(made["noisy_authors"]), "--on", f"{{bag: {made['authors_bag']}}}", "--quiet",
                 "--json", str(theirs)]) == 0
    assert main(["evaluate", str(made["noisy_authors"]), "--on", f"{{bag: {made['authors_bag']}, action_unit_rad: "
                 "0.00388}", "--quiet", "--json", str(named)]) == 0
    scores = [json.loads(f.read_text())["models"][0]["per_path"] for f in (ours, theirs, named)]
    assert scores[0] == scores[1]
    assert [p["position_mse"] for p in scores[2]] == pytest.approx([p["position_mse"] for p in scores[0]], rel=1e-3)
    assert main(["evaluate", str(made["noisy"]), "--on", f"{{bag: {made['authors_bag']}}}", "--quiet"]) == 2
    # A file saved before model files stored their unit cannot say which it is: it is taken as in the data's.
    with safe_open(str(made["noisy"]), framework="pt") as f:
        meta, tensors = json.loads(f.metadata()["t42_transfer"]), {k: f.get_tensor(k) for k in f.keys()}
    del meta["action_unit_rad"]
    old = tmp_path / "old.safetensors"
    save_file(tensors, str(old), metadata={"t42_transfer": json.dumps(meta)})
    assert main(["evaluate", str(old), "--on", f"{{bag: {made['authors_bag']}}}", "--quiet", "--json",
                 str(tmp_path / "old.json")]) == 0
    assert json.loads((tmp_path / "old.json").read_text())["models"][0]["per_path"] == scores[0]


def test_two_files_of_one_name_are_told_apart_by_their_paths(made, tmp_path, capsys):
    other = tmp_path / "b" / "constant.safetensors"
    other.parent.mkdir()
    other.write_bytes(made["constant"].read_bytes())
    assert main(["evaluate", str(made["constant"]), str(other), "--on", f"{{bag: {made['bag']}}}", "--quiet"]) == 0
    rows = [line.split()[0] for line in capsys.readouterr().out.splitlines() if "dropout" in line]
    assert rows[:2] == [str(made["constant"]), str(other)], rows


def test_the_json_has_exactly_the_documented_shape(made, tmp_path):
    out = tmp_path / "e.json"
    assert _run(made, "--json", str(out), "--paths", "2,0", models=("constant", "noisy")) == 0
    result = json.loads(out.read_text())
    keys = {"path", "divergence_mean_4mm", "divergence_mean_10mm", "position_mse_mean", "per_path"}
    assert set(result) == {"models", "hold_still"}
    assert [m["path"] for m in result["models"]] == [str(made["constant"]), str(made["noisy"])]
    assert all(set(m) == keys for m in [*result["models"], result["hold_still"]])
    assert result["hold_still"]["path"] is None
    assert [p["episode"] for p in result["hold_still"]["per_path"]] == [2, 0]  # --paths picks and orders
    assert all(isinstance(v, float) for m in result["models"] for k, v in m.items() if k.endswith("mean_4mm"))


def test_the_authors_definition_counts_the_crossing_step(made, tmp_path):
    out = tmp_path / "e.json"
    assert _run(made, "--json", str(out), "--definition", "authors") == 0
    per = json.loads(out.read_text())["models"][0]["per_path"]
    assert [p["divergence_4mm"] for p in per] == [9, 31, 3]  # one more, censored at T + 1
    assert per[0]["position_mse"] == pytest.approx(_expected_mse(0.5, 40) / 2, rel=1e-5)


def test_dropout_draws_are_seeded_averaged_and_reported_beside_dropout_off(made, tmp_path, capsys):
    from t42_transfer.evaluation.model_files import load_model_file

    data = _paths()
    noisy = load_model_file(made["noisy"])[0]
    off = score_model(noisy, data, "noisy")
    on = score_model(noisy, data, "noisy", dropout_draws=8, seed=1)
    assert on == score_model(noisy, data, "noisy", dropout_draws=8, seed=1) and not noisy.training
    assert on != off and on != score_model(noisy, data, "noisy", dropout_draws=8, seed=2)
    assert all((8 * p[k]).is_integer() for p in on.per_path for k in ("divergence_4mm", "divergence_10mm"))  # means
    # A model whose output dropout cannot change scores the same in both modes.
    constant = load_model_file(made["constant"])[0]
    assert score_model(constant, data, dropout_draws=3).per_path == score_model(constant, data).per_path
    both = evaluate_models([("noisy", noisy)], data, dropout_draws=8, seed=1)
    assert both.models[0] == on and both.dropout_off[0] == off
    out = tmp_path / "e.json"
    assert _run(made, "--dropout-draws", "8", "--seed", "1", "--json", str(out), models=("noisy",)) == 0
    stored = json.loads(out.read_text())
    assert set(stored) == {"models", "hold_still", "dropout_draws", "dropout_off"} and stored["dropout_draws"] == 8
    assert stored["models"][0]["divergence_mean_4mm"] == on.divergence_mean_4mm
    kept_off = {**json.loads(json.dumps(off.as_dict())), "path": str(made["noisy"])}
    assert stored["dropout_off"][0] == kept_off  # both modes kept
    table = capsys.readouterr().out
    assert "dropout off" in table and "dropout on (8 draws)" in table


def _not_a_model(tmp_path: Path) -> str:
    path = tmp_path / "norms.pkl"
    path.write_bytes(pickle.dumps({"x_mean": [0.0] * 4}, protocol=2))
    return str(path)


@pytest.mark.parametrize(("args", "message"), [
    (lambda m, d: [str(d / "missing.pkl"), "--on", "{real: A}"], r"missing\.pkl: does not exist"),
    (lambda m, d: [_not_a_model(d), "--on", f"{{bag: {m['bag']}}}"], r"norms\.pkl: .*not a legacy torch file"),
    (lambda m, d: [str(m["constant"]), "--on", "[1, 2]"], r"--on must be a mapping of data settings"),
    (lambda m, d: [str(m["constant"]), "--on", "{real: A"], r"--on: not a YAML mapping"),
    (lambda m, d: [str(m["constant"]), "--on", "{bags: x}"], r"unknown DataSpec settings \['bags'\] in --on"),
    (lambda m, d: [str(m["constant"]), "--on", "{real: C}"], r"--on\.real must be one of"),
    (lambda m, d: [str(m["constant"]), "--on", f"{{model: {m['constant']}}}"], r"--on\.model: only an experiment's"),
    (lambda m, d: [str(m["constant"]), "--on", "{}"], r"--on needs exactly one of hand, bag or real, got none"),
    (lambda m, d: [str(m["constant"]), "--on", f"{{bag: {m['bag']}, mirror_x: true, mirror_about: grasp}}"],
     r"mirror_about: grasp mirrors onto another data set's grasp"),
    (lambda m, d: [str(m["constant"]), "--on", f"{{bag: {m['bag']}}}", "--paths", "0,3"],
     r"--paths: .* has 3 paths \(0 to 2\), not 3"),
    (lambda m, d: [str(m["constant"]), "--on", f"{{bag: {m['bag']}}}", "--paths", "0,0"], r"distinct path numbers"),
    (lambda m, d: [str(m["constant"]), "--on", f"{{bag: {m['bag']}}}", "--paths", "a"], r"distinct path numbers"),
    (lambda m, d: [str(m["constant"]), "--on", f"{{bag: {m['bag']}}}", "--dropout-draws", "0"],
     r"--dropout-draws: expected an integer from 1 to 1000"),
    (lambda m, d: [str(m["constant"]), "--on", f"{{bag: {m['bag']}}}", "--negate-actions"],
     r"constant\.safetensors: negating actions applies to an authors' \.pkl file"),
    (lambda m, d: [str(m["constant"]), "--on", f"{{bag: {m['bag']}}}", "--json", str(m["constant"])],
     r"constant\.safetensors: exists already"),
    (lambda m, d: [str(m["constant"])], r"the following arguments are required: --on"),
    (lambda m, d: [str(m["authors_unit"]), "--on", f"{{bag: {m['bag']}}}"],
     r"authors_unit\.safetensors: its actions are in steps of 0\.00388 rad at an action of 1, the actions of "
     r"\{bag: .*\} in 0\.025 rad"),
])
def test_bad_input_is_one_line_exit_2(made, tmp_path, capsys, args, message):
    try:
        code = main(["evaluate", *args(made, tmp_path), "--quiet"])
    except SystemExit as exit_:  # the parser's own errors
        code = exit_.code
    assert code == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and captured.err.startswith("t42: error: "), captured.err
    assert re.search(message, captured.err), captured.err
    assert not captured.out


# --------------------------------------------------------------------------- the authors' files
@pytest.mark.realdata
def test_bs_model_reproduces_the_readmes_reference_figures(t42_real_dir, tmp_path):
    """B's model used directly on hand A's paths 0-3 (actions negated, dropout off, 4 mm): 702 steps; holding
    still 61 (README).  Those round the paper count (701.75, 61.25); the authors' count is one more (702.75)."""
    model = AUTHORS_DIR / "real_B_heldout0.1_1.pkl"
    if not model.is_file():
        pytest.skip(f"the authors' models are not in {AUTHORS_DIR} (public repository schrammlb2/"
                    "Liam-Bayesian-hand-transfer, not redistributed)")
    results = {}
    for definition in ("paper", "authors"):
        out = tmp_path / f"{definition}.json"
        assert main(["evaluate", str(model), "--on", "{real: A, negate_actions: true}", "--paths", "0,1,2,3",
                     "--definition", definition, "--json", str(out), "--quiet"]) == 0
        results[definition] = json.loads(out.read_text())
    paper, authors = results["paper"], results["authors"]
    assert paper["models"][0]["divergence_mean_4mm"] == 701.75 and paper["hold_still"]["divergence_mean_4mm"] == 61.25
    assert round(paper["models"][0]["divergence_mean_4mm"]) == 702 and round(paper["hold_still"][
        "divergence_mean_4mm"]) == 61
    assert authors["models"][0]["divergence_mean_4mm"] == 702.75
    assert [p["steps"] for p in paper["hold_still"]["per_path"]] == [798, 1248, 1198, 898]


def test_quiet_silences_the_collection_of_a_simulated_data_set_too(made, tmp_path, capsys):
    """--quiet says "no progress bar": the bar of collecting a ``hand`` data set came out regardless."""
    on = "{hand: target, episodes: 2, steps: 30}"
    assert main(["evaluate", str(made["constant"]), "--on", on, "--cache", str(tmp_path / "cache"), "--quiet"]) == 0
    assert "collect" not in capsys.readouterr().err
    assert main(["evaluate", str(made["constant"]), "--on", on, "--cache", str(tmp_path / "other")]) == 0
    assert "collect" in capsys.readouterr().err  # (the bar the first run left out)
