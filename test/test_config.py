"""The one config layer: settings dataclasses check their own ranges, and every reader says the same thing."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from t42_transfer.cli import main as t42
from t42_transfer.config import between, check, from_mapping, inline_mapping, one_of
from t42_transfer.models.training import TrainConfig
from t42_transfer.planning.planner import PlannerConfig
from t42_transfer.transfer.config import TransferConfig
from t42_transfer.transfer.online import config_from_file, config_with_overrides

BAD_LR = "lr must be > 0, got -1"


@dataclasses.dataclass(frozen=True)
class Inner:
    rate: float = 1.0
    names: tuple[str, ...] = ("a",)

    def __post_init__(self) -> None:
        check(self, {"rate": between(0, 10, low_open=True), "names": one_of(("a", "b"))})


@dataclasses.dataclass(frozen=True)
class Outer:
    inner: Inner = Inner()
    count: int = 3
    label: str | None = None


def test_a_nested_mapping_applies_on_top_of_the_current_value() -> None:
    cfg = from_mapping(Outer, {"inner": {"names": ["b", "a"]}, "count": 5})
    assert cfg == Outer(Inner(1.0, ("b", "a")), 5)
    base = Outer(Inner(rate=2.0))
    assert from_mapping(Outer, {"inner": {"names": ["b"]}}, base=base).inner == Inner(2.0, ("b",))


@pytest.mark.parametrize("data, message", [
    ({"inner": {"rate": 0}}, "inner.rate must be in (0, 10], got 0"),
    ({"inner": {"names": ["a", "c"]}}, "inner.names must be one of ('a', 'b'), got 'c'"),
    ({"inner": {"rate": float("nan")}}, "inner.rate must be a finite number, got nan"),
    ({"count": 2.5}, "count must be an integer, got 2.5"),
    ({"count": True}, "count must be an integer, got True"),
    ({"label": 3}, "label must be a string, got 3"),
    ({"inner": []}, "inner must be a mapping of Inner settings, got []"),
    ({"inner": {"names": []}}, "inner.names must be a non-empty list, got []"),
    ({"nope": 1, "count": 1}, "unknown Outer settings ['nope']; known: ['count', 'inner', 'label']"),
    ({"inner": {"speed": 1}}, "unknown Inner settings ['speed'] in inner"),
])
def test_bad_settings_are_one_line_naming_the_dotted_setting(data: dict, message: str) -> None:
    with pytest.raises(ValueError) as err:
        from_mapping(Outer, data)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_a_config_built_in_code_keeps_the_file_rules() -> None:
    with pytest.raises(ValueError, match=f"^{BAD_LR}$"):
        TrainConfig(lr=-1)
    with pytest.raises(ValueError, match="elite_fraction must be in \\(0, 1\\), got 1.5"):
        PlannerConfig(elite_fraction=1.5)
    with pytest.raises(ValueError, match="rate must be"):
        Inner(rate="fast")  # type: ignore[arg-type]  # a type the rule cannot compare is out of range


def test_unset_settings_are_not_checked_and_good_ones_pass() -> None:
    assert Outer(label=None).label is None
    assert TrainConfig(lr=1e-3, epochs=1).lr == 1e-3


def test_the_same_bad_value_says_the_same_thing_in_an_experiment_a_server_file_and_overrides(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``lr: -1`` was refused by ``t42 experiment`` and trained on by the transfer server: now one message."""
    section = {"l2_finetune": {"train": {"lr": -1}}}
    expected = f"transfer.l2_finetune.train.{BAD_LR}"
    with pytest.raises(ValueError) as overrides:
        config_with_overrides(section)
    assert str(overrides.value) == expected

    server_file = tmp_path / "server.yaml"
    server_file.write_text("l2_finetune: {train: {lr: -1}}\n")
    with pytest.raises(ValueError) as from_file:
        config_from_file(server_file)
    assert str(from_file.value) == f"{server_file}: {expected}"

    experiment = tmp_path / "exp.yaml"
    experiment.write_text("name: bad\nsource: {hand: source}\ntarget: {hand: target}\n"
                          "transfer: {l2_finetune: {train: {lr: -1}}}\n")
    assert t42(["experiment", str(experiment), "--out", str(tmp_path / "runs")]) == 2
    assert capsys.readouterr().err.strip() == f"t42: error: {experiment}: {expected}"
    assert not (tmp_path / "runs" / "bad").exists(), "nothing ran"


def test_an_experiment_transfer_section_keeps_the_definition_settings_it_does_not_name(tmp_path: Path) -> None:
    from t42_transfer.evaluation.experiment_config import load_config

    file = tmp_path / "exp.yaml"
    file.write_text("name: ok\ndefinition: authors\nsource: {hand: source}\ntarget: {hand: target}\n"
                    "transfer: {l2_finetune: {train: {epochs: 3}}}\n")
    cfg = load_config(file)
    authors = TransferConfig.for_definition("authors")
    assert cfg.transfer is not None
    assert cfg.transfer.l2_finetune.train == dataclasses.replace(authors.l2_finetune.train, epochs=3)
    assert cfg.transfer.cumulative_residual == authors.cumulative_residual


def test_an_inline_mapping_is_parsed_or_refused_in_one_line_naming_where() -> None:
    assert inline_mapping("{a: 1, b: [2, 3]}", "--x", "things", "{a: 1}") == {"a": 1, "b": [2, 3]}
    for text, says in (("[1]", "--x must be a mapping of things such as '{a: 1}'"), ("{a: 1", "--x: not a YAML"),
                       ("{a: " + "1" * 5000 + "}", "--x: 5005 characters; things are a short mapping")):
        with pytest.raises(ValueError, match=re.escape(says)):
            inline_mapping(text, "--x", "things", "{a: 1}")
