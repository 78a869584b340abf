"""Bad command lines, as an attacker or a careless user types them: each is one ``t42: error:`` line, exit 2.

Every case must be refused before any work: nothing is written (``{out}`` never appears),
nothing hangs (a FIFO where a file belongs), nothing allocates what a typo asks for
(``--samples 1000000000`` would be 800 GB), and no traceback reaches the user.
"""

from __future__ import annotations

import errno
import json
import os
import pickle
import shlex
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import yaml

from t42_transfer.cli import main
from t42_transfer.models import Normalisation, TransitionModel
from t42_transfer.models.checkpoint import save_model
from t42_transfer.models.legacy_torch import LEGACY_MAGIC, LEGACY_PROTOCOL
from t42_transfer.planning import Workspace

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "source_small"
TIMEOUT_S = 60


@contextmanager
def _deadline(seconds: float) -> Iterator[None]:
    """A hang (a blocking open of a FIFO) becomes a test failure instead of a stuck suite."""

    def on_alarm(signum: int, frame: object) -> None:
        raise TimeoutError(f"still running after {seconds} s: a hang")

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``t42 argv``; assert exit 2 and exactly one ``t42: error:`` line on stderr; that line."""
    with _deadline(TIMEOUT_S):
        try:
            code = main(argv)
        except SystemExit as exit_info:
            code = exit_info.code
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2, f"exit {code}, stderr {err!r}"
    assert len(lines) == 1 and lines[0].startswith("t42: error: "), err
    assert "Traceback" not in err
    return lines[0]


@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real (untrained) model file storing a workspace, so the commands would run on it."""
    norm = Normalisation(
        state_mean=np.array([0.0, 80.0, 120.0, -120.0], np.float32),
        state_std=np.array([15.0, 10.0, 30.0, 30.0], np.float32),
        delta_mean=np.zeros(4, np.float32),
        delta_std=np.array([0.4, 0.4, 2.0, 2.0], np.float32),
    )
    path = tmp_path_factory.mktemp("model") / "m.safetensors"
    return save_model(TransitionModel(norm), path, method="new_model",
                      extra={"workspace": Workspace.box(-60, 60, 30, 130).to_dict()})


@pytest.fixture(scope="module")
def other_models(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Files a user takes for model files: an authors' model (``pkl``), a model whose delta_std has a 0."""
    folder = tmp_path_factory.mktemp("other_models")
    # how the authors' legacy torch.save files start: pickles of the format's magic number and protocol
    (folder / "real_B.pkl").write_bytes(pickle.dumps(LEGACY_MAGIC, 2) + pickle.dumps(LEGACY_PROTOCOL, 2))
    zeros, ones = np.zeros(4, np.float32), np.ones(4, np.float32)
    norm = Normalisation(zeros, ones, zeros, np.array([1, 0, 1, 1], np.float32))
    authors_unit = save_model(TransitionModel(Normalisation.identity()), folder / "authors_unit.safetensors",
                              method="new_model", extra={"workspace": Workspace.box(-60, 60, 30, 130).to_dict()},
                              action_unit_rad=0.00388)
    return {"pkl": folder / "real_B.pkl", "authors_unit": authors_unit,
            "zero_std": save_model(TransitionModel(norm), folder / "zero_std.safetensors", method="new_model")}


@pytest.fixture()
def paths(tmp_path: Path, model_file: Path, other_models: dict[str, Path]) -> dict[str, str]:
    """Names the cases use: real inputs, wrong kinds of path, and ``out`` (which must never appear)."""
    (tmp_path / "file").write_text("not a directory, not a model, not a bag\n")
    (tmp_path / "binary").write_bytes(b"\xff\xfe1,2\n")
    (tmp_path / "dir").mkdir()
    os.mkfifo(tmp_path / "fifo")
    run = tmp_path / "run"
    run.mkdir()
    (run / "results.json").write_text(json.dumps({"config": {}, "rows": []}))
    return {
        **{name: str(path) for name, path in other_models.items()},
        "model": str(model_file), "bag": str(BAG), "file": str(tmp_path / "file"), "dir": str(tmp_path / "dir"),
        "fifo": str(tmp_path / "fifo"), "missing": str(tmp_path / "missing"), "under": str(tmp_path / "file" / "sub"),
        "out": str(tmp_path / "out"), "run": str(run), "tmp": str(tmp_path),
        "binary": str(tmp_path / "binary"),
    }


PLAN = "plan {model} --start 0 80 120 -120 --goal 1 85 --out {out}"
PEG = "peg-in-hole {model} --distances 5 --trials 1 --samples 50 --horizon 10 --quiet --out {out}"
COLLECT = "sim collect --hand target --episodes 1 --steps 20 --workers 1 --quiet --out {out}"

CASES = {
    # the command line itself
    "unknown command": ("bogus", "invalid choice"),
    "plan without arguments": ("plan", "required"),
    # t42 plan
    "plan --samples 1000000000 (800 GB)": (PLAN + " --samples 1000000000", "--samples"),
    "plan --samples 0": (PLAN + " --samples 0", "--samples"),
    "plan --samples -5": (PLAN + " --samples -5", "--samples"),
    "plan --samples abc": (PLAN + " --samples abc", "--samples"),
    "plan --samples 1e3": (PLAN + " --samples 1e3", "--samples"),
    "plan --horizon 0": (PLAN + " --horizon 0", "--horizon"),
    "plan --horizon 100000000": (PLAN + " --horizon 100000000", "--horizon"),
    "plan samples x horizon": (PLAN + " --samples 1000000 --horizon 10000", "sampled steps"),
    "plan --tolerance nan": (PLAN + " --tolerance nan", "--tolerance"),
    "plan --tolerance inf": (PLAN + " --tolerance inf", "--tolerance"),
    "plan --tolerance -1": (PLAN + " --tolerance -1", "--tolerance"),
    "plan --tolerance 0": (PLAN + " --tolerance 0", "--tolerance"),
    "plan --refine -1": (PLAN + " --refine -1", "--refine"),
    "plan --refine 1000000000": (PLAN + " --refine 1000000000", "--refine"),
    "plan --seed -1": (PLAN + " --seed -1", "--seed"),
    "plan --seed 2**70": (PLAN + f" --seed {2**70}", "--seed"),
    "plan --start nan": ("plan {model} --start nan 80 120 -120 --goal 1 85 --out {out}", "--start"),
    "plan --start inf": ("plan {model} --start 0 inf 120 -120 --goal 1 85 --out {out}", "--start"),
    "plan --goal nan": ("plan {model} --start 0 80 120 -120 --goal 1 nan --out {out}", "--goal"),
    "plan --sampler bogus": (PLAN + " --sampler bogus", "--sampler"),
    "plan model missing": ("plan {missing} --start 0 80 120 -120 --goal 1 85 --out {out}", "{missing}: does not exist"),
    "plan model is a directory": ("plan {dir} --start 0 80 120 -120 --goal 1 85 --out {out}",
                                  "{dir}: is a directory, not a regular file"),
    "plan model is a FIFO": ("plan {fifo} --start 0 80 120 -120 --goal 1 85 --out {out}",
                             "{fifo}: is a FIFO, not a regular file"),
    "plan model is an authors' pickle": ("plan {pkl} --start 0 80 120 -120 --goal 1 85 --out {out}",
                                         "{pkl}: is a pickle (as the paper authors' models are), not a model file; "
                                         "convert an authors' model first: t42 model import-authors {pkl}"),
    "plan model with a zero std": ("plan {zero_std} --start 0 80 120 -120 --goal 1 85 --out {out}",
                                   "{zero_std}: holds a normalisation std that is not positive in delta_std"),
    "plan --workspace missing": (PLAN + " --workspace {missing}", "{missing}: does not exist"),
    "plan --workspace is a file": (PLAN + " --workspace {file}", "{file}: not a directory"),
    "plan --out is a file": ("plan {model} --start 0 80 120 -120 --goal 1 85 --out {file}", "{file}"),
    "plan --out under a file": ("plan {model} --start 0 80 120 -120 --goal 1 85 --out {under}", "{under}"),
    # t42 peg-in-hole
    "peg goals too near for the hand": (PEG, "no goal 5 steps away without a drop"),
    "peg a model name twice": (PEG.replace("{model}", "{model} {model}"), "model name(s) ['m'] given twice"),
    "peg a model named as a baseline": (PEG.replace("{model}", "oracle={model}"), "['oracle'] given twice or a "
                                        "baseline's"),
    "peg --trials -1": (PEG + " --trials -1", "--trials"),
    "peg --trials 0": (PEG + " --trials 0", "--trials"),
    "peg --trials 1e9": (PEG + " --trials 1000000000", "--trials"),
    "peg --distances 0": (PEG + " --distances 0", "--distances"),
    "peg --distances -5": (PEG + " --distances 5 -5", "--distances"),
    "peg --distances 1000000000": (PEG + " --distances 1000000000", "--distances"),
    "peg --tolerances nan": (PEG + " --tolerances nan", "--tolerances"),
    "peg --tolerances -3": (PEG + " --tolerances 10 -3", "--tolerances"),
    "peg --samples 0": (PEG + " --samples 0", "--samples"),
    "peg --samples 1000000000": (PEG + " --samples 1000000000", "--samples"),
    "peg --horizon 0": (PEG + " --horizon 0", "--horizon"),
    "peg samples x horizon": (PEG + " --samples 1000000 --horizon 10000", "sampled steps"),
    "peg --threads 0": (PEG + " --threads 0", "--threads"),
    "peg --threads -1": (PEG + " --threads -1", "--threads"),
    "peg --seed -1": (PEG + " --seed -1", "--seed"),
    "peg --hand bogus": (PEG + " --hand bogus", "bogus"),
    "peg model missing": ("peg-in-hole {missing} --out {out}", "{missing}: does not exist"),
    "peg NAME=model missing": ("peg-in-hole a={missing} --out {out}", "{missing}: does not exist"),
    "peg model is an authors' pickle": ("peg-in-hole {pkl} --out {out}", "{pkl}: is a pickle"),
    "peg model is a FIFO": ("peg-in-hole {fifo} --out {out}", "{fifo}: is a FIFO, not a regular file"),
    "peg model of another unit": ("peg-in-hole {authors_unit} --out {out}",
                                  "{authors_unit}: its actions are in steps of 0.00388 rad at an action of 1, the "
                                  "actions of the simulated hands in 0.025 rad"),
    "peg --workspace missing": (PEG + " --workspace {missing}", "{missing}: does not exist"),
    "peg --out is a file": ("peg-in-hole {model} --out {file}", "{file}"),
    "peg without --out": ("peg-in-hole {model}", "--out"),
    # t42 sim collect
    "collect --workers 0": (COLLECT + " --workers 0", "--workers"),
    "collect --workers -1": (COLLECT + " --workers -1", "--workers"),
    "collect --workers 100000": (COLLECT + " --workers 100000", "workers"),
    "collect --episodes 0": (COLLECT + " --episodes 0", "--episodes"),
    "collect --episodes -1": (COLLECT + " --episodes -1", "--episodes"),
    "collect --episodes 1000000000": (COLLECT + " --episodes 1000000000", "episodes"),
    "collect --steps 0": (COLLECT + " --steps 0", "--steps"),
    "collect --steps 1000000000": (COLLECT + " --steps 1000000000", "steps"),
    "collect episodes x steps": (COLLECT + " --episodes 100000 --steps 100000", "transitions"),
    "collect --hold-max 0": (COLLECT + " --hold-max 0", "--hold-max"),
    "collect --hold-max 1000000000": (COLLECT + " --hold-max 1000000000", "hold_max"),
    "collect --seed -1": (COLLECT + " --seed -1", "--seed"),
    "collect --policy bogus": (COLLECT + " --policy bogus", "--policy must be one of random, sustained"),
    "collect sustained --hold-max 50": (COLLECT + " --policy sustained --hold-max 50",
                                        "--hold-max must be at least 120 with --policy sustained"),
    "collect --hand bogus": (COLLECT + " --hand bogus", "bogus"),
    "collect --hand family-x": (COLLECT + " --hand family-x", "family-x"),
    "collect --storage bogus": (COLLECT + " --storage bogus", "--storage"),
    "collect --out exists": ("sim collect --episodes 1 --steps 20 --workers 1 --quiet --out {dir}", "{dir}: exists"),
    "collect --out under a file": ("sim collect --episodes 1 --steps 20 --workers 1 --quiet --out {under}",
                                   "{under}"),
    # t42 sim compare-real
    "compare-real --real-dir missing": ("sim compare-real --real-dir {missing}", "{missing}: does not exist"),
    "compare-real --real-dir is a file": ("sim compare-real --real-dir {file}", "{file}: not a directory"),
    "compare-real --hands bogus": ("sim compare-real --real-dir {dir} --hands source bogus", "bogus"),
    "compare-real --seed -1": ("sim compare-real --real-dir {dir} --seed -1", "--seed"),
    "compare-real --moving-threshold 0": (
        "sim compare-real --real-dir {dir} --moving-threshold 0", "--moving-threshold"),
    "compare-real --moving-window 0": ("sim compare-real --real-dir {dir} --moving-window 0", "--moving-window"),
    "compare-real --moving-window 100": ("sim compare-real --real-dir {dir} --moving-window 100", "--moving-window"),
    "compare-real --out-dir is a file": ("sim compare-real --real-dir {dir} --out-dir {file}", "{file}"),
    # t42 experiment (the config's own cases are in the next test)
    "experiment config missing": ("experiment {missing} --out {out}", "{missing}"),
    "experiment config is a directory": ("experiment {dir} --out {out}",
                                         "{dir}: the experiment config is a directory, not a regular file"),
    "experiment config is a FIFO": ("experiment {fifo} --out {out}",
                                    "{fifo}: the experiment config is a FIFO, not a regular file"),
    "experiment --workers 0": ("experiment {file} --workers 0 --out {out}", "--workers"),
    "experiment --workers -2": ("experiment {file} --workers -2 --out {out}", "--workers"),
    "experiment --workers and --scheduler": ("experiment {file} --workers 2 --scheduler local:2 --out {out}",
                                             "--workers or --scheduler, not both"),
    # t42 report
    "report run dir missing": ("report {missing}", "{missing}: does not exist"),
    "report run dir is a file": ("report {file}", "{file}: not a directory"),
    "report run dir is a FIFO": ("report {fifo}", "{fifo}: not a directory"),
    "report run dir without results": ("report {dir}", "results.json: does not exist"),
    "report --out is a file": ("report {run} --out {file}", "{file}"),
    "report --out under a file": ("report {run} --out {under}", "{under}"),
    # t42 bag (bag info belongs to the bag reader's own tests)
    "import-t42 pickle missing": ("bag import-t42 {missing} {out}", "{missing}: does not exist"),
    "import-t42 pickle is a directory": ("bag import-t42 {dir} {out}", "{dir}: is a directory, not a regular file"),
    "import-t42 pickle is a FIFO": ("bag import-t42 {fifo} {out}", "{fifo}: is a FIFO, not a regular file"),
    "import-t42 out exists": ("bag import-t42 {file} {dir}", "{dir}: exists"),
    "import-t42 out under a file": ("bag import-t42 {file} {under}", "{under}"),
    "repair bag missing": ("bag repair {missing}", "{missing}: does not exist"),
    "repair bag is a file": ("bag repair {file}", "{file}: not a directory"),
    "repair bag is a FIFO": ("bag repair {fifo}", "{fifo}: not a directory"),
    "play bag missing": ("bag play {missing}", "{missing}: does not exist"),
    "play bag is a FIFO": ("bag play {fifo}", "{fifo}: not a directory"),
    "play --rate 0": ("bag play {bag} --rate 0", "rate must be"),
    "play --rate -1": ("bag play {bag} --rate -1", "rate must be"),
    "play --rate nan": ("bag play {bag} --rate nan", "rate must be"),
    "play --rate inf": ("bag play {bag} --rate inf", "rate must be"),
    "play --clock -1": ("bag play {bag} --clock -1", "clock_hz must be"),
    "play --clock nan": ("bag play {bag} --clock nan", "clock_hz must be"),
    "play --wait-subscribers -1": ("bag play {bag} --wait-subscribers -1", "--wait-subscribers"),
    "play --wait-subscribers inf": ("bag play {bag} --wait-subscribers inf", "--wait-subscribers"),
    # t42 up (params-file contents are in the next tests)
    "up params file missing": ("up {missing}", "{missing}"),
    "up params file is a directory": ("up {dir}", "{dir}: the params file is a directory, not a regular file"),
    "up params file is a FIFO": ("up {fifo}", "{fifo}: the params file is a FIFO, not a regular file"),
    "up --stop-timeout -1": ("up {file} --stop-timeout -1", "--stop-timeout"),
    "up --stop-timeout nan": ("up {file} --stop-timeout nan", "--stop-timeout"),
    "up --stop-timeout 0": ("up {file} --stop-timeout 0", "--stop-timeout"),
    "up --namespace with a space": ("up {file} --namespace 'bad ns'", "--namespace"),
    "up --namespace starting with a digit": ("up {file} --namespace /1left", "--namespace"),
    # t42 demo and t42 node
    "demo --out is a file": ("demo --quick --out {file}", "{file}"),
    "demo --out under a file": ("demo --quick --out {under}", "{under}"),
    "demo --workers 0": ("demo --quick --workers 0 --out {out}", "--workers"),
    "demo --workers -1": ("demo --quick --workers -1 --out {out}", "--workers"),
    "node unknown": ("node bogus", "bogus"),
    # t42 view --snapshot
    "snapshot not a .png": ("view --snapshot {out} --object 0 80", "{out}: --snapshot writes a PNG"),
    "snapshot path file not text": ("view --snapshot {out}.png --path {binary}", "{binary}: not a text file"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_command_line_is_one_error_line_before_any_work(
    case: str, paths: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    template, expected = CASES[case]
    line = refused(shlex.split(template.format(**paths)), capsys)
    assert expected.format(**paths) in line
    assert not Path(paths["out"]).exists(), "an output was written before the input was refused"


# ------------------------------------------------------------------ experiment configs

CONFIG = {
    "name": "tiny", "source": {"bag": str(BAG)}, "target": {"bag": str(REPO / "bags" / "target_small")},
    "methods": ["direct"], "split": "paths", "amounts": [1], "seeds": 1, "lyapunov_steps": 5,
    "source_training": {"epochs": 1}, "workers": 1,
}


def _changed(**changes: object) -> dict:
    config = json.loads(json.dumps(CONFIG))
    for key, value in changes.items():
        if value is None:
            config.pop(key, None)
        else:
            config[key] = value
    return config


CONFIG_CASES = {
    "name escapes --out": (_changed(name="../../../../somewhere"), "name"),
    "name with a slash": (_changed(name="a/b"), "name"),
    "name ..": (_changed(name=".."), "name"),
    "name .": (_changed(name="."), "name"),
    "name empty": (_changed(name=""), "name"),
    "name absolute": (_changed(name="/tmp/x"), "name"),
    "name a number": (_changed(name=5), "name"),
    "name a list": (_changed(name=["a"]), "name"),
    "amounts [.nan]": (_changed(amounts=[float("nan")]), "amounts[0]"),
    "amounts [.inf]": (_changed(amounts=[float("inf")]), "amounts[0]"),
    "amounts negative": (_changed(amounts=[-1]), "amounts"),
    "amounts zero": (_changed(amounts=[0]), "amounts"),
    "amounts empty": (_changed(amounts=[]), "amounts"),
    "amounts a string": (_changed(amounts="abc"), "amounts"),
    "amounts of strings": (_changed(amounts=["one"]), "amounts[0]"),
    "amounts repeated": (_changed(amounts=[1, 1]), "amounts"),
    "amounts not whole with split paths": (_changed(amounts=[1.5]), "amounts"),
    "amounts over 1 with split fraction": (_changed(split="fraction", amounts=[1.5]), "amounts"),
    "amounts as many as the target's episodes": (_changed(amounts=[4]), "amounts"),
    "seeds 0": (_changed(seeds=0), "seeds"),
    "seeds -1": (_changed(seeds=-1), "seeds"),
    "seeds 1.5": (_changed(seeds=1.5), "seeds"),
    "seeds a string": (_changed(seeds="two"), "seeds"),
    "seeds true": (_changed(seeds=True), "seeds"),
    "seeds 1000000000": (_changed(seeds=1_000_000_000), "seeds"),
    "test_fraction 1.5": (_changed(test_fraction=1.5), "test_fraction"),
    "test_fraction nan": (_changed(test_fraction=float("nan")), "test_fraction"),
    "epsilon_mm -1": (_changed(epsilon_mm=-1), "epsilon_mm"),
    "lyapunov_steps 0": (_changed(lyapunov_steps=0), "lyapunov_steps"),
    "horizon 0": (_changed(horizon=0), "horizon"),
    "start_offsets [-1]": (_changed(start_offsets=[-1]), "start_offsets"),
    "split bogus": (_changed(split="bogus"), "split"),
    "methods empty": (_changed(methods=[]), "methods"),
    "methods a string": (_changed(methods="direct"), "methods"),
    "methods unknown": (_changed(methods=["magic"]), "methods"),
    "methods repeated": (_changed(methods=["direct", "direct"]), "methods"),
    "workers 0": (_changed(workers=0), "workers"),
    "workers 1000000": (_changed(workers=1_000_000), "workers"),
    "unknown setting": (_changed(sedes=3), "sedes"),
    "source a number": (_changed(source=5), "source"),
    "source empty": (_changed(source={}), "source"),
    "source two kinds": (_changed(source={"hand": "source", "bag": str(BAG)}), "source"),
    "source hand unknown": (_changed(source={"hand": "bogus"}), "bogus"),
    "source real C": (_changed(source={"real": "C"}), "source.real"),
    "source episodes 0": (_changed(source={"hand": "source", "episodes": 0}), "source.episodes"),
    "source steps 1e8": (_changed(source={"hand": "source", "steps": 100_000_000}), "source.steps"),
    "source episodes x steps": (_changed(source={"hand": "source", "episodes": 100_000, "steps": 100_000}),
                                "transitions"),
    "source seed -1": (_changed(source={"hand": "source", "seed": -1}), "source.seed"),
    "source bag missing": (_changed(source={"bag": "/nonexistent/bag"}), "/nonexistent/bag"),
    "source_training lr nan": (_changed(source_training={"lr": float("nan")}), "source_training.lr"),
    "source_training epochs -1": (_changed(source_training={"epochs": -1}), "source_training.epochs"),
    "source_training epochs a string": (_changed(source_training={"epochs": "x"}), "source_training.epochs"),
    "source_training a list": (_changed(source_training=[1]), "source_training"),
    "transfer gamma 2": (_changed(transfer={"cumulative_residual": {"gamma": 2}}), "gamma"),
    "transfer a number": (_changed(transfer=5), "transfer"),
    "transfer unknown method": (_changed(transfer={"magic": {}}), "magic"),
    "no name": (_changed(name=None), "needs name"),
}


def _experiment(config_text: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> str:
    (tmp_path / "cfg").mkdir()
    config = tmp_path / "cfg" / "config.yaml"
    config.write_text(config_text)
    deep = tmp_path / "a" / "b" / "c" / "d"
    deep.mkdir(parents=True)
    before = sorted(p for p in tmp_path.rglob("*"))
    line = refused(["experiment", str(config), "--out", str(deep / "out"), "--quiet"], capsys)
    assert sorted(p for p in tmp_path.rglob("*")) == before, "the refused run wrote files"
    return line


@pytest.mark.parametrize("case", list(CONFIG_CASES))
def test_a_bad_experiment_config_is_refused_before_anything_is_written(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config, expected = CONFIG_CASES[case]
    assert expected in _experiment(yaml.safe_dump(config), tmp_path, capsys)


@pytest.mark.parametrize("text, expected", [
    ("name: [unclosed\nsource: {bag: x}\n", "not valid YAML"),
    ("name: tiny\n  source: {bag: x}\n", "not valid YAML"),
    ("name: tiny\nsource: !!python/object:os.system x\n", "not valid YAML"),
    ("- a list\n- of things\n", "needs name, source and target"),
    ("", "needs name, source and target"),
    ("name: 2001-13-45\n", "not valid YAML"),
    ("name: a\nsource: {bag: x}\nname: b\n", "not valid YAML: key 'name' given twice at line 3, column 1"),
    ("base: &b {epochs: 1}\nsource_training: {<<: *b, epochs: 2, epochs: 3}\n", "key 'epochs' given twice"),
    (f"name: {'9' * 5000}\n", "not valid YAML"),
], ids=["unclosed", "indentation", "python tag", "a list", "empty", "bad date", "a key twice",
        "a key twice beside a merge", "5000 digits"])
def test_yaml_that_cannot_be_read_is_one_line(text: str, expected: str, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    assert expected in _experiment(text, tmp_path, capsys)


def test_a_config_that_is_not_utf8_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "c.yaml"
    config.write_bytes(b"name: \xff\xfe tiny\n")
    assert "not UTF-8" in refused(["experiment", str(config), "--out", str(tmp_path / "out")], capsys)


def test_a_run_directory_in_use_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import fcntl

    config = tmp_path / "c.yaml"
    config.write_text(yaml.safe_dump(CONFIG))
    run_dir = tmp_path / "out" / "tiny"
    run_dir.mkdir(parents=True)
    with open(run_dir / ".lock", "w") as held:  # what a running `t42 experiment` holds
        held.write("pid 12345\n")
        held.flush()
        fcntl.flock(held, fcntl.LOCK_EX)
        line = refused(["experiment", str(config), "--out", str(tmp_path / "out"), "--quiet"], capsys)
    assert f"{run_dir}: in use by another run (pid 12345)" in line
    assert sorted(p.name for p in run_dir.rglob("*")) == [".lock", "cells"]


# ------------------------------------------------------------------ t42 up params files

PARAMS_CASES = {
    "YAML syntax error": ("/**/recorder: [unclosed\n", "not valid YAML"),
    "tab indentation": ("/**/recorder:\n\tros__parameters: {}\n", "not valid YAML"),
    "a list": ("- recorder\n- planner\n", "mapping of node sections"),
    "a scalar": ("recorder\n", "mapping of node sections"),
    "section a number": ("/**/recorder: 5\n", "/**/recorder"),
    "section empty": ("/**/recorder:\n", "/**/recorder"),
    "ros__parameters a number": ("/**/recorder:\n  ros__parameters: 5\n", "ros__parameters"),
    "ros__parameters empty": ("/**/recorder:\n  ros__parameters:\n", "ros__parameters"),
    "beside ros__parameters": ("/**/recorder:\n  ros__parameters: {mode: episode}\n  other: 1\n", "other"),
    "parameters without ros__parameters": ("/**/recorder:\n  mode: episode\n", "/**/recorder.mode"),
    "node name a number": ("1:\n  ros__parameters: {mode: episode}\n", "node section 1"),
    "mixed list": ("/**/recorder:\n  ros__parameters:\n    topics: [1, x]\n", "topics"),
    "list of lists": ("/**/recorder:\n  ros__parameters:\n    topics: [[1]]\n", "topics"),
    "alias": ("/**/recorder:\n  ros__parameters:\n    a: &x 1\n    b: *x\n", "aliases"),
    "unknown node": ("/**/toaster:\n  ros__parameters: {}\n", "toaster"),
    "no sections": ("", "no node sections"),
    "not UTF-8": (b"/**/recorder: \xff\n", "not UTF-8"),
}


@pytest.mark.parametrize("case", list(PARAMS_CASES))
def test_up_refuses_a_bad_params_file_in_one_line(case: str, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    content, expected = PARAMS_CASES[case]
    params = tmp_path / "suite.yaml"
    params.write_bytes(content if isinstance(content, bytes) else content.encode())
    line = refused(["up", str(params)], capsys)
    assert str(params) in line and expected in line


def test_up_only_a_node_the_file_lacks(capsys: pytest.CaptureFixture[str]) -> None:
    assert "--only toaster: not in" in refused(["up", str(REPO / "configs" / "suite.yaml"), "--only", "toaster"],
                                               capsys)


# ------------------------------------------------------------------ OS errors on the user's paths


@pytest.mark.parametrize("error", [
    PermissionError(errno.EACCES, "Permission denied", "/data/run/report"),
    IsADirectoryError(errno.EISDIR, "Is a directory", "/data/run/report"),
    NotADirectoryError(errno.ENOTDIR, "Not a directory", "/data/run/report"),
    OSError(errno.ENOSPC, "No space left on device", "/data/run/report"),
    OSError(errno.ENAMETOOLONG, "File name too long", "/data/run/report"),
], ids=lambda e: type(e).__name__ + f"-{e.errno}")
def test_an_os_error_is_one_line_naming_the_file(error: OSError, paths: dict[str, str],
                                                 monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from t42_transfer.evaluation import report

    def fail(*args: object, **kwargs: object) -> None:
        raise error

    monkeypatch.setattr(report, "write_report", fail)
    assert refused(["report", paths["run"]], capsys) == f"t42: error: /data/run/report: {error.strerror}"


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads and writes everything")
def test_unreadable_and_unwritable_paths(paths: dict[str, str], capsys: pytest.CaptureFixture[str]) -> None:
    locked = Path(paths["tmp"]) / "locked"
    locked.mkdir()
    (locked / "c.yaml").write_text("name: x\n")
    locked.chmod(0)
    try:
        assert "Permission denied" in refused(["experiment", str(locked / "c.yaml")], capsys)
        plan = PLAN.replace("{out}", str(locked / "plan")).format(**paths)
        assert "Permission denied" in refused(shlex.split(plan), capsys)
    finally:
        locked.chmod(0o700)


@pytest.mark.parametrize("argv", [
    ["model", "train", str(BAG), "--out", "{ro}/m.safetensors"],  # before an hour's training, not after it
    ["view", "--snapshot", "{ro}/new/s.png", "--object", "0", "80"],
], ids=["model train", "view --snapshot under a new folder"])
def test_an_output_that_cannot_be_written_is_refused_before_any_work(argv: list[str], tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """As root, the command runs without the capabilities that let root write anywhere (setpriv)."""
    import shutil
    import subprocess
    import sys

    ro = tmp_path / "ro"
    ro.mkdir(mode=0o555)
    argv = [a.format(ro=ro) for a in argv]
    if os.geteuid() != 0:
        line = refused(argv, capsys)
    elif shutil.which("setpriv") is None:
        pytest.skip("running as root, and no setpriv to drop root's right to write anywhere")
    else:
        done = subprocess.run(["setpriv", "--bounding-set", "-dac_override,-dac_read_search", "--",
                               sys.executable, "-m", "t42_transfer.cli", *argv],
                              capture_output=True, text=True, timeout=TIMEOUT_S)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2 and len(lines) == 1, done.stderr
        line = lines[0]
    assert line.startswith("t42: error: ") and f"{ro} cannot be written (permission denied)" in line, line
    assert list(ro.iterdir()) == []


_TRIAL = {"model": "a", "steps": 20, "trial": 0, "status": "ok", "end_reason": "length", "goal_distance_mm": 20.0,
          "final_error_mm": 2.0, "progress_mm": 18.0, "predicted_error_mm": 1.0, "plan_steps": 20, "plans": 1,
          "plan_seconds": 0.1}


@pytest.mark.parametrize("content, expected", [
    (b"", "not valid JSON"),
    (b'{"config": {', "not valid JSON"),
    (b"\xff\xfe{}", "not UTF-8"),
    (b"{}", "no 'config' object"),
    (b"[]", "no 'config' object"),
    (json.dumps({"config": {"tolerances_mm": [10.0]}, "trials": []}).encode(), "no 'trials'"),
    (json.dumps({"config": {"tolerances_mm": [-1]}, "trials": [_TRIAL]}).encode(), "tolerances_mm"),
    (json.dumps({"config": {"tolerances_mm": [10.0]}, "trials": [{"model": "a"}]}).encode(), "trial 0 is not"),
    (json.dumps({"config": {"tolerances_mm": [10.0]},
                 "trials": [{**_TRIAL, "goal_distance_mm": "far"}]}).encode(), "goal_distance_mm 'far'"),
], ids=["empty", "truncated", "not utf8", "no config", "a list", "no trials", "negative tolerance",
        "missing fields", "a string for a number"])
def test_a_bad_stored_peg_in_hole_json_is_one_line_and_nothing_is_rewritten(
        content: bytes, expected: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    stored = tmp_path / "peg_in_hole.json"
    stored.write_bytes(content)
    (tmp_path / "peg_in_hole.md").write_text("the earlier report")
    line = refused(["peg-in-hole", "--from-json", str(stored)], capsys)
    assert str(stored) in line and expected in line, line
    assert (tmp_path / "peg_in_hole.md").read_text() == "the earlier report"


def _results(**changes: object) -> bytes:
    row = {"method": "direct", "amount": 1, "divergence_mean": 10.0, "position_mse_mean": 1.0,
           "lyapunov_mean": 0.01, "covering_radius": 1.0, "train_error_normalised": 0.1, "train_error_xy_mm": 0.5,
           "train_transitions": 100}
    content = {"config": {"name": "x", "source": {}, "target": {}, "split": "paths", "seeds": 1, "epsilon_mm": 10},
               "rows": [row]}
    for key, value in changes.items():
        if key in row:
            row[key] = value
        else:
            content[key] = value
    return json.dumps(content).encode()


@pytest.mark.parametrize("content, expected", [
    (b"", "not valid JSON"),
    (b"\x00\xff", "not UTF-8"),
    (b"{}", "no 'config' object"),
    (_results(config={}), "its config lacks name"),
    (_results(rows=[]), "no 'rows'"),
    (_results(rows=[{"a": 1}]), "row 0 is not a cell's row"),
    (_results(divergence_mean="long"), "'divergence_mean' is 'long'"),
], ids=["empty", "not utf8", "no config", "config without keys", "no rows", "a row without method",
        "a string for a number"])
def test_a_bad_results_json_is_one_line_and_no_figure_is_replaced(
        content: bytes, expected: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "results.json").write_bytes(content)
    figure = tmp_path / "report" / "divergence_mean.png"
    figure.parent.mkdir()
    figure.write_bytes(b"the earlier figure")
    line = refused(["report", str(tmp_path)], capsys)
    assert "results.json" in line and expected in line, line
    assert figure.read_bytes() == b"the earlier figure"


def test_the_programs_warnings_are_one_line_like_its_errors(tmp_path: Path) -> None:
    """A salvaged bag's warning reads ``t42: warning: ...``, without the Python source line behind it."""
    import shutil
    import subprocess
    import sys

    bag = tmp_path / "bag"
    shutil.copytree(BAG, bag)
    mcap = next(bag.glob("*.mcap"))
    os.truncate(mcap, mcap.stat().st_size - 3000)  # the end cut off: the prefix is recovered, with a warning
    done = subprocess.run([sys.executable, "-m", "t42_transfer.cli", "bag", "info", str(bag)], capture_output=True,
                          text=True, timeout=TIMEOUT_S, cwd=REPO)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.strip().splitlines()
    assert lines and all(line.startswith("t42: warning: ") for line in lines), done.stderr
    assert "recovered the readable prefix" in done.stderr and ".py:" not in done.stderr


@pytest.mark.parametrize("stored", ["box", {"lower": [0.0], "upper": [1.0, 2.0]}],
                         ids=["not an object", "one bound"])
def test_a_models_bad_stored_workspace_is_named_with_the_model_file(
        stored: object, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    norm = Normalisation(state_mean=np.zeros(4, np.float32), state_std=np.ones(4, np.float32),
                         delta_mean=np.zeros(4, np.float32), delta_std=np.ones(4, np.float32))
    model = save_model(TransitionModel(norm), tmp_path / "m.safetensors", method="new_model",
                       extra={"workspace": stored})
    line = refused(["plan", str(model), "--start", "0", "90", "100", "100", "--goal", "0", "95", "--out",
                    str(tmp_path / "plan")], capsys)
    assert f"{model}: a stored workspace" in line, line
    assert not (tmp_path / "plan").exists()
