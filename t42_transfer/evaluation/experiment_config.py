"""An experiment's config: the data of each side, the grid of cells, and reading both from YAML.

Every setting's range is its dataclass's own (``__post_init__``, with :func:`t42_transfer.config.check`),
so a config built in code keeps the rules of a config file; :func:`load_config` reads a file through the
one config layer (:func:`t42_transfer.config.from_mapping`) and :func:`check_config` adds the rules that
span settings (one data source per side, cells that fit the split).
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from t42_transfer.config import (
    FRACTION,
    MAX_EVAL_STEPS,
    POSITIVE,
    SEED,
    SEED_RANGE,
    STEPS,
    Rule,
    between,
    check,
    from_mapping,
    inline_mapping,
    one_of,
    show,
)
from t42_transfer.conventions import ACTION_UNIT_RAD, AUTHORS_ACTION_UNIT_RAD, MAX_ACTION_UNIT_RAD
from t42_transfer.data.quality import HANDLING
from t42_transfer.data.t42_real import REAL_HANDS, REAL_OBJECT
from t42_transfer.evaluation.metrics import METRIC_DEFINITIONS
from t42_transfer.hand.collect import MAX_EPISODES, MAX_STEPS, MAX_WORKERS, POLICIES, check_collection
from t42_transfer.models.training import TrainConfig
from t42_transfer.transfer.config import DEFINITIONS, SOURCE_TRAINING, TransferConfig
from t42_transfer.transfer.methods import METHODS
from t42_transfer.yaml_files import read_yaml

__all__ = [
    "MAX_EVAL_STEPS", "SEED_RANGE", "DataSpec", "ExperimentConfig", "TrainConfig", "TransferConfig", "check_config",
    "check_spec", "config_dict", "load_config", "parse_data_spec", "sides",
]

SAFE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]{0,99}")
SAFE_OBJECT = re.compile(r"[a-z][a-z0-9]{0,39}")
"""The public files' object names (cyl35, egg50, poly6, sqr30...): part of a file name, so nothing else."""
MIRRORS = ("origin", "grasp")
MAX_SEEDS = 1000
MAX_CELLS = 100_000
SPLITS = ("fraction", "paths")
MAX_PATH_CHARS = 4096
AUTHORS_SUFFIX = ".pkl"
"""A source ``model`` of this suffix is one of the paper authors' legacy torch files (imported on the fly);
any other is a project model file."""
_ORIGINAL_SPEC = ("hand", "episodes", "steps", "seed", "bag", "real", "mirror_x")

DATA_RULES: dict[str, Rule] = {
    "episodes": between(1, MAX_EPISODES), "steps": between(1, MAX_STEPS), "seed": SEED, "real": one_of(REAL_HANDS),
    "real_object": ((lambda v: bool(SAFE_OBJECT.fullmatch(v))), "an object name such as cyl35 or egg50"),
    "mirror_about": one_of(MIRRORS), "flagged": one_of(HANDLING), "policy": one_of(POLICIES),
    "paths": ((lambda v: v >= 0), "a path number (0 or more)"),
    "model": ((lambda v: isinstance(v, str) and 0 < len(v) <= MAX_PATH_CHARS and "\0" not in v),
              f"a file path (at most {MAX_PATH_CHARS} characters)"),
    "action_unit_rad": between(0, MAX_ACTION_UNIT_RAD, True),
}
"""What each :class:`DataSpec` setting must be beyond its type."""
EXPERIMENT_RULES: dict[str, Rule] = {
    "seeds": between(1, MAX_SEEDS), "amounts": between(0, MAX_EPISODES, True), "test_fraction": FRACTION,
    "epsilon_mm": POSITIVE, "start_offsets": between(0, MAX_EVAL_STEPS), "horizon": STEPS, "lyapunov_steps": STEPS,
    "workers": between(1, MAX_WORKERS), "split": one_of(SPLITS), "methods": one_of(METHODS),
    "definition": one_of(DEFINITIONS),
}
"""What each :class:`ExperimentConfig` setting must be beyond its type (every element of a list setting)."""
_REGISTERED: Rule = ((lambda v: v in METHODS and v != "auto"), "a method other than auto")
AUTO_RULES: dict[str, Rule] = {"candidates": _REGISTERED, "fallback": _REGISTERED,
                               "min_episodes": between(2, MAX_EPISODES)}
"""An experiment's ``transfer.auto`` beyond :class:`AutoConfig`'s own: registered methods, a bounded size."""


@dataclass(frozen=True)
class DataSpec:
    """Where a hand's data comes from (a simulated hand, a bag, or a public real-hand file) and what is done to it."""

    hand: str | None = None
    episodes: int = 300
    steps: int = 1000
    seed: int = 0
    bag: str | None = None
    real: str | None = None
    """``A`` or ``B``: the public T42 test paths of that hand, of the object ``real_object``."""
    mirror_x: bool = False
    """Mirror x (the real hands are mirror images of each other), about ``mirror_about``."""
    real_object: str = REAL_OBJECT
    """The object of ``real``'s file (``testpaths_<object>[_red]_d_v0.pkl`` in ``$T42_REAL_DATA``): ``cyl35`` lies
    beside the project; the public repository also holds ``egg50`` and ``poly6`` for both hands."""
    mirror_about: str = "origin"
    """``origin``: x -> -x, about the camera's origin.  ``grasp``: about the axis halfway between this side's
    and the other side's grasp centres, with y shifted by their difference, so both grasps coincide."""
    negate_actions: bool = False
    """Negate every action: the authors' B -> A runs gave hand A its actions negated (the hands are mirrored)."""
    flagged: str = "keep"
    """Episodes with frozen tracking, jumps or late steps (:mod:`t42_transfer.data.quality`): ``keep`` them as they are,
    ``drop`` them, or ``split`` them at each flagged stretch.  Found stretches are recorded in any case."""
    exclude_test_sequences: bool = False
    """Source only: leave out of the source model's training every episode that ran the action sequence of one
    of the cell's test episodes (both real hands ran the same six), training a source per test set."""
    policy: str = "random"
    """``hand`` only: how the simulated hand is driven (:data:`t42_transfer.hand.collect.POLICIES`): ``random``,
    the paper's training data, or ``sustained``, test paths like the real hands' (long holds of discrete moves)."""
    paths: tuple[int, ...] | None = None
    """The episodes of ``real``'s or ``bag``'s data to use, by number in the file, in this order (e.g. the
    authors' test paths 0-3 as a test set, the others as target data); None: all of them."""
    model: str | None = None
    """Source only, instead of data: a trained model used as the source as it is, so the source needs no data
    and no training.  A project model file (``.safetensors``, e.g. from ``t42 model import-authors``) or one of
    the paper authors' files (``.pkl``), imported on the fly; ``negate_actions`` then negates the actions inside
    the imported model (the authors' B model on hand A's actions as recorded), as it would negate source data."""
    action_unit_rad: float | None = None
    """``bag`` only: the unit its actions are read in (a bag holds the actuators' steps), e.g. the authors' 0.00388
    rad for a bag recorded for their models; None: the one the bag declares (``t42 bag import-t42`` declares
    theirs, ``t42 sim collect`` the suite's), else the suite's (a recorder's bag declares none)."""

    def describe(self) -> dict:
        """The settings, without those still at defaults added after runs were cached (their keys stay valid)."""
        values = dataclasses.asdict(self)
        return {k: v for k, v in values.items() if k in _ORIGINAL_SPEC or v != _SPEC_DEFAULTS[k]}

    def __post_init__(self) -> None:
        check(self, DATA_RULES)

    def unit_rad(self) -> float | None:
        """The unit of the data's actions: the authors' for their real-hand files (recorded by their driver), the
        suite's for simulated hands, a bag's ``action_unit_rad`` or else the one it declares (its metadata is read);
        None for a model, whose file says."""
        from t42_transfer.data.bag import declared_bag_unit

        if self.model is not None:
            return None
        if self.real is not None:
            return AUTHORS_ACTION_UNIT_RAD
        if self.bag is not None:
            return self.action_unit_rad or declared_bag_unit(self.bag) or ACTION_UNIT_RAD
        return ACTION_UNIT_RAD


_SPEC_DEFAULTS = {f.name: f.default for f in dataclasses.fields(DataSpec)}


@dataclass(frozen=True)
class ExperimentConfig:
    """Methods x amounts of target data x seeds on one source and one target hand."""

    config_kind = "experiment"
    """How messages name these settings ("unknown experiment settings ...")."""
    name: str
    """The run directory's name under ``--out``: one plain path component."""
    source: DataSpec
    target: DataSpec
    methods: tuple[str, ...] = tuple(m for m in METHODS if m != "auto")
    split: str = "fraction"
    """``fraction``: amounts are fractions of the target pool, a fixed test split held out;
    ``paths``: amounts are numbers of target episodes, the others are the test set."""
    amounts: tuple[float, ...] = (0.005, 0.01, 0.02, 0.05, 0.1)
    seeds: int = 5
    test_fraction: float = 0.2
    definition: str = "paper"
    """Where the paper's text and its authors' code differ, which one this run follows (``paper`` or
    ``authors``): the transfer settings, the source training, the threshold and how divergence and MSE count."""
    epsilon_mm: float | None = None
    """None: the definition's (paper 4 mm, authors 10 mm)."""
    start_offsets: tuple[int, ...] = (0,)
    horizon: int | None = None
    lyapunov_steps: int = 100
    source_training: TrainConfig | None = None
    """None: the definition's; settings given in a file apply on top of it.  Stays None for a source that is a
    trained model (``source.model``), which is not trained."""
    transfer: TransferConfig | None = None
    """None: ``TransferConfig.for_definition(definition)``; settings given in a file apply on top of it."""
    workers: int | None = None
    test: DataSpec | None = None
    """Test episodes of the target hand from their own data set (e.g. sustained-action paths) instead of the
    held-out target episodes; the training subsets stay those without it, so cells pair across test sets."""

    def __post_init__(self) -> None:
        # The run directory is ``out / name``: anything but one plain component could leave ``out``.
        if not (isinstance(self.name, str) and SAFE_NAME.fullmatch(self.name)):
            raise ValueError(f"name must be one plain path component (letters, digits, '.', '_', '-'; "
                             f"not starting with '.'; at most 100 characters), got {show(self.name)}")
        trained = isinstance(self.source, DataSpec) and self.source.model is not None
        for key, value in _definition_defaults(self.definition).items():
            if getattr(self, key) is None and not (trained and key == "source_training"):
                object.__setattr__(self, key, value)
        check(self, EXPERIMENT_RULES)
        try:
            if isinstance(self.transfer, TransferConfig):  # another type is check_config's to refuse
                check(self.transfer.auto, AUTO_RULES)
        except ValueError as err:
            raise ValueError(f"transfer.auto.{err}") from None

    @classmethod
    def config_bases(cls, values: Mapping[Any, Any]) -> dict[str, Any]:
        """What a file's ``transfer`` and ``source_training`` apply on top of: its definition's settings."""
        return _definition_defaults(values.get("definition", "paper"))


def _definition_defaults(definition: Any) -> dict[str, Any]:
    """The settings ``definition`` decides unless a config gives them (ValueError for an unknown definition)."""
    if not isinstance(definition, str) or definition not in DEFINITIONS:
        raise ValueError(f"definition must be one of {DEFINITIONS}, got {show(definition)}")
    return {"epsilon_mm": METRIC_DEFINITIONS[definition].epsilon_mm, "source_training": SOURCE_TRAINING[definition],
            "transfer": TransferConfig.for_definition(definition)}


def load_config(path: str | os.PathLike[str]) -> ExperimentConfig:
    """Read an experiment YAML; ValueError naming the file and the offending setting, before anything runs."""
    file = Path(path)
    raw = read_yaml(file, "experiment config")
    if not isinstance(raw, dict) or "name" not in raw or "source" not in raw or "target" not in raw:
        raise ValueError(f"{file}: an experiment config needs name, source and target")
    try:
        cfg = from_mapping(ExperimentConfig, raw)
        check_config(cfg)
    except ValueError as err:
        raise ValueError(f"{file}: {err}") from None
    return cfg


def check_config(cfg: ExperimentConfig) -> None:
    """ValueError unless ``cfg`` keeps every rule of a config file, also when built in code.

    Beyond each setting's type and range: one data source per side, no repeated or too many
    cells, amounts that fit the split.
    """
    from_mapping(ExperimentConfig, config_dict(cfg))
    for side in sides(cfg):
        check_spec(getattr(cfg, side), side, model_allowed=side == "source")
    if cfg.source.model is not None and cfg.source_training is not None:
        raise ValueError("source_training trains the source on its data; source.model is a trained model")
    for side in sides(cfg)[1:]:
        spec = getattr(cfg, side)
        if cfg.source.model is not None and spec.mirror_about == "grasp":
            raise ValueError(f"{side}.mirror_about: grasp mirrors onto the source's grasp, and source.model has "
                             f"no source data")
        if cfg.source.mirror_x and spec.mirror_x and "grasp" in (cfg.source.mirror_about, spec.mirror_about):
            raise ValueError("mirror_about: grasp mirrors one side onto the other: mirror_x on one side only")
        if spec.exclude_test_sequences:
            raise ValueError(f"{side}.exclude_test_sequences: only the source's training leaves test sequences out")
    for key in ("methods", "amounts"):
        values = getattr(cfg, key)
        if len(set(values)) != len(values):
            raise ValueError(f"{key} repeat an entry: {show(values)}")
    cells = len(cfg.methods) * len(cfg.amounts) * cfg.seeds
    if cells > MAX_CELLS:
        raise ValueError(f"{cells} cells (methods x amounts x seeds) is over {MAX_CELLS}")
    if cfg.split == "fraction" and max(cfg.amounts) > 1:
        raise ValueError(f"amounts are fractions of the target pool with split: fraction, got {max(cfg.amounts)}")
    if cfg.split == "paths" and not all(float(a).is_integer() for a in cfg.amounts):
        raise ValueError(f"amounts are numbers of episodes with split: paths, got {show(cfg.amounts)}")


def check_spec(spec: DataSpec, where: str, model_allowed: bool = False) -> None:
    """ValueError unless ``spec`` names exactly one data source (or, ``model_allowed``, a model) and settings that
    fit it; ``where`` names the spec in messages (``source``, ``--on``)."""
    given = [k for k in ("hand", "bag", "real", "model") if getattr(spec, k) is not None]
    if len(given) != 1:
        allowed = "hand, bag, real or model" if model_allowed else "hand, bag or real"
        raise ValueError(f"{where} needs exactly one of {allowed}, got {given or 'none'}")
    if spec.model is not None:
        if not model_allowed:
            raise ValueError(f"{where}.model: only an experiment's source can be a model; {where} is data")
        unused = [k for k, v in dataclasses.asdict(spec).items()
                  if k not in ("model", "negate_actions") and v != _SPEC_DEFAULTS[k]]
        if unused:
            raise ValueError(f"{where}.model is a trained model, so {where} has no data for {unused} to apply to")
        if spec.negate_actions and not spec.model.endswith(AUTHORS_SUFFIX):
            raise ValueError(f"{where}.negate_actions applies to an authors' {AUTHORS_SUFFIX} file imported on the "
                             f"fly; a model file's actions are as it was saved (import it with t42 model "
                             f"import-authors --negate-actions)")
        return
    if spec.hand is not None:
        check_collection(spec.hand, spec.episodes, spec.steps, hold_max=POLICIES[spec.policy]().hold_max)
    elif spec.policy != _SPEC_DEFAULTS["policy"]:
        raise ValueError(f"{where}.policy drives a simulated hand: it needs {where}.hand")
    if spec.paths is not None:
        if spec.hand is not None:
            raise ValueError(f"{where}.paths picks episodes of a file: it needs {where}.real or {where}.bag")
        if not spec.paths or len(set(spec.paths)) != len(spec.paths):
            raise ValueError(f"{where}.paths must name distinct episodes, got {list(spec.paths)}")
    if spec.action_unit_rad is not None and spec.bag is None:
        raise ValueError(f"{where}.action_unit_rad is the unit a bag is read in: it needs {where}.bag")
    if spec.real_object != REAL_OBJECT and spec.real is None:
        raise ValueError(f"{where}.real_object names the object of a real-hand file: it needs {where}.real")
    if spec.mirror_about != "origin" and not spec.mirror_x:
        raise ValueError(f"{where}.mirror_about: {spec.mirror_about} needs {where}.mirror_x: true")


def parse_data_spec(text: str, where: str) -> DataSpec:
    """A data spec written as a YAML/JSON mapping (``{real: A, negate_actions: true}``), checked as an
    experiment's sides are; ValueError naming ``where`` otherwise.  Never a model: this is data."""
    raw = inline_mapping(text, where, "data settings", "{real: A}", MAX_PATH_CHARS)
    spec = from_mapping(DataSpec, raw, where)
    check_spec(spec, where)
    return spec


def sides(cfg: ExperimentConfig) -> tuple[str, ...]:
    """The data sets ``cfg`` names: source, target, and test when it has its own."""
    return ("source", "target") if cfg.test is None else ("source", "target", "test")


def config_dict(cfg: ExperimentConfig) -> dict[str, Any]:
    """``cfg`` as plain JSON types: what ``config.yaml`` and ``results.json`` hold, and a file would give."""
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=str))
