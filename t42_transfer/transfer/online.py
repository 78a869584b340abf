"""Online transfer: the bags recorded since the last transfer + a source model file -> a scored, saved model.

The logic behind the transfer server node, without ROS, so it is tested like
the rest of the science.  One :func:`run_transfer`:

1. takes the candidate bags (a configured list, or every finished bag in
   ``bag_dir``: a non-hidden directory with a ``metadata.yaml``) minus those a
   previous successful transfer used, as recorded in ``model_dir/transfer_state.json``;
2. loads the source model (a plain transition model) and reads the new bags,
   skipping (and naming, with why) any it cannot read; it trains and scores on 0.1 s transitions of a hand
   holding the object only: late steps are left out and each episode ends at its first drop (:func:`read_target`);
3. holds out whole target episodes (``holdout_fraction`` of each kind,
   exploration and executed plans, at least one, never all) and transfers with
   the rest; method ``auto`` trains every
   candidate on part of the rest, scores each on other whole episodes of it and
   keeps the best (:func:`~t42_transfer.transfer.methods.select_method`), so the
   held-out episodes still score a model they did not help choose;
4. scores the transferred model and, for reference, the source alone and the
   hold-still baseline on the held-out episodes (divergence time at 4 mm, position MSE),
   all of them and each kind apart;
5. saves ``model_dir/transferred_<NNN>.safetensors``, then replaces
   ``model_dir/current.safetensors``, then records the bags as used.

A caller may name the bags instead (``exact_bags``): exactly those are read, used before or not.

Every refusal (no new bags, too little data in the readable ones, a missing or
incompatible source model) raises :class:`TransferRefused` before anything is
written.  A caller may stop a transfer (``cancel``): it is checked at each stage
change and after every training epoch, and until the save begins raises
:class:`TransferCancelled` with nothing written.  An unreadable bag is not recorded as used, so once repaired it is
offered again.  Files are written atomically (:func:`save_model`, the state file by
rename), and ``current.safetensors`` is the commit point: when replacing it fails
the new ``transferred_<NNN>`` file is removed again, so a failed call leaves the
model directory as it was.  The state file is written last, so a crash after the
commit can only leave it behind (the bags are offered again), never ahead of the
models.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import re
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from t42_transfer.config import FRACTION, Rule, between, check, from_mapping
from t42_transfer.data.bag import list_bags, read_bag
from t42_transfer.data.errors import DataFileError
from t42_transfer.data.quality import usable_stretches
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.evaluation.metrics import evaluate_model
from t42_transfer.evaluation.online_loop import EPISODE_KINDS, episode_kind
from t42_transfer.files import write_atomic
from t42_transfer.models.baselines import HoldStill
from t42_transfer.models.checkpoint import UNIT_ASSUMED_KEY, UNIT_KEY, load_model, save_model
from t42_transfer.models.network import TransitionModel
from t42_transfer.models.training import Progress
from t42_transfer.planning.workspace import Workspace
from t42_transfer.transfer.config import TransferConfig
from t42_transfer.transfer.methods import METHODS, Selection, select_method, transfer
from t42_transfer.yaml_files import read_yaml

STATE_FILE = "transfer_state.json"
CURRENT_MODEL = "current.safetensors"
MODEL_PREFIX = "transferred"

_MODEL_NAME = re.compile(rf"^{MODEL_PREFIX}_(\d{{3,}})\.safetensors$")

Report = Callable[[str, Mapping[str, object]], None]
"""``report(stage, info)``: called at each stage change (``loading``, ``training``, ``evaluating``, ``saving``)
with what is known so far, and while ``training``
after every epoch with :func:`epoch_info` (``phase``, ``epoch``, ``epochs``, ``train_loss``, ``val_loss``)."""


class TransferRefused(Exception):
    """A transfer that cannot run on what it was given; the message says why.  Nothing was written.

    ``skipped``: the bags read and skipped as unreadable before the refusal, each ``(bag, why)`` (``why`` names the
    bag too), as :attr:`TransferResult.skipped_bags` gives them.
    """

    def __init__(self, message: str, skipped: Sequence[tuple[Path, str]] = ()) -> None:
        super().__init__(message)
        self.skipped = tuple(skipped)


class TransferCancelled(Exception):
    """A transfer stopped on its caller's request before its save began; the message says when.  Nothing was
    written: the current model, the numbered models and the state file are as they were."""


@dataclass(frozen=True)
class OnlineTransferSpec:
    """What one transfer call runs on."""

    source_model: Path
    model_dir: Path
    bag_dir: Path | None = None
    bags: tuple[Path, ...] = ()
    """Candidate bags; empty means every finished bag in ``bag_dir``."""
    new_bags_only: bool = True
    """Train on the bags no earlier transfer used (True), or on every candidate bag once at least one is new
    (False: the suite keeps learning from all it recorded, e.g. the episodes of executed plans)."""
    exact_bags: bool = False
    """Train on exactly ``bags``, used by an earlier transfer or not (a caller named them); ``new_bags_only`` and
    ``bag_dir`` are not looked at.  They are recorded as used all the same."""
    method: str = "l2_finetune"
    """The evaluations' choice (docs/evaluation.md, section 6): best or tied best on most settings and on both real
    pairs; ``auto`` is the hedge where fine-tuning can fall below no adaptation."""
    config: TransferConfig = TransferConfig()
    holdout_fraction: float = 0.25
    min_episodes: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        check(self, SPEC_RULES)  # the method's name is run_transfer's to check: the registry can grow


SPEC_RULES: dict[str, Rule] = {"holdout_fraction": FRACTION, "min_episodes": between(2, math.inf),
                               "seed": between(0, math.inf)}
"""What each :class:`OnlineTransferSpec` setting must be beyond its type."""


@dataclass(frozen=True)
class TransferResult:
    """What a successful transfer did and how well the model predicts held-out target episodes."""

    method: str
    bags: tuple[Path, ...]
    episodes: int
    transitions: int
    held_out_episodes: int
    divergence_steps: float
    position_mse_mm2: float
    source_divergence_steps: float
    source_position_mse_mm2: float
    model_path: Path
    seconds: float
    skipped_bags: tuple[tuple[Path, str], ...] = ()
    """Each new bag that could not be read, with why it was skipped (``why`` names the bag), as
    :attr:`TransferRefused.skipped` gives them."""
    hold_still_divergence_steps: float = math.nan
    """The hold-still baseline (predicts no motion) on the same held-out episodes: what a model must beat."""
    hold_still_position_mse_mm2: float = math.nan
    notes: tuple[str, ...] = ()
    """What the reader dropped or salvaged in the bags read (each names its bag)."""
    late_steps: int = 0
    """Steps the driver ran late, left out of the training and held-out episodes."""
    selection: Selection | None = None
    """What ``auto`` picked and every candidate's score (None for a named method)."""
    held_out_by_kind: Mapping[str, Mapping[str, float]] = dataclasses.field(default_factory=dict)
    """:func:`scores_by_kind` of the held-out episodes: exploration and executed plans apart."""

    @property
    def skipped(self) -> tuple[str, ...]:
        """Why each skipped bag was skipped (each names its bag)."""
        return tuple(why for _, why in self.skipped_bags)

    def summary(self) -> str:
        """The one-line answer of the transfer service."""
        picked = "" if self.selection is None else f" ({self.selection.describe()})"
        return (
            f"{self.method}{picked}: trained on {self.episodes} episodes / {self.transitions} transitions from "
            f"{len(self.bags)} bag(s){f' ({self.late_steps} late steps left out)' if self.late_steps else ''}; on "
            f"{self.held_out_episodes} held-out episode(s): divergence "
            f"{self.divergence_steps:.1f} steps, MSE {self.position_mse_mm2:.2f} mm^2 (source alone "
            f"{self.source_divergence_steps:.1f} steps, {self.source_position_mse_mm2:.2f} mm^2; hold-still "
            f"{self.hold_still_divergence_steps:.1f} steps, {self.hold_still_position_mse_mm2:.2f} mm^2); "
            f"model {self.model_path}{self._kinds_note()}{skipped_note(self.skipped)}{reading_note(self.notes)}"
        )

    def _kinds_note(self) -> str:
        if len(self.held_out_by_kind) < 2:
            return ""
        parts = [f"{kind} ({int(s['episodes'])}): {s['model_divergence_steps']:.1f} steps, source "
                 f"{s['source_divergence_steps']:.1f}, {s['model_position_mse_mm2']:.2f} mm^2"
                 for kind, s in self.held_out_by_kind.items()]
        return "; held out by kind: " + ", ".join(parts)


# ---------------------------------------------------------------- configuration
def config_with_overrides(overrides: Mapping[str, Any]) -> TransferConfig:
    """:class:`TransferConfig` defaults with nested ``overrides``
    (e.g. ``{"cumulative_residual": {"train": {"epochs": 5}}}``).

    Built by the one config layer (:func:`~t42_transfer.config.from_mapping`), so a setting an experiment's
    ``transfer`` section refuses is refused here with the same message: ValueError naming the dotted key.
    """
    return from_mapping(TransferConfig, overrides, "transfer")


def config_from_file(path: str | Path) -> TransferConfig:
    """:class:`TransferConfig` defaults with the nested overrides of a YAML file; ``""`` (or an empty file): defaults.

    The file holds what :func:`config_with_overrides` takes, e.g.
    ``cumulative_residual: {train: {epochs: 50}}``.  ValueError (one line naming the
    file) when it cannot be read, is not YAML, or has an unknown key, a wrong type or a value out of range.
    """
    if not str(path):
        return TransferConfig()
    doc = read_yaml(path, "transfer config")
    try:
        return config_with_overrides({} if doc is None else doc)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


def epoch_budget(method: str, cfg: TransferConfig) -> int:
    """Most training epochs ``method`` runs under ``cfg`` (0 for ``direct``)."""
    section = getattr(cfg, method, None)
    train = getattr(section, "train", None)
    return 0 if train is None else int(train.epochs)


def epoch_info(progress: Progress) -> dict[str, object]:
    """A training epoch as :data:`Report` info; ``val_loss`` only when the phase validates."""
    info: dict[str, object] = {
        "phase": progress.phase, "epoch": progress.epoch, "epochs": progress.epochs, "train_loss": progress.train_loss,
    }
    if progress.val_loss is not None:
        info["val_loss"] = progress.val_loss
    return info


# ---------------------------------------------------------------- bags and state
def bag_key(bag: Path) -> str:
    """How the state file names a bag: its resolved path."""
    return str(Path(bag).resolve())


def read_state(model_dir: Path) -> dict[str, Any]:
    """The state file's content (``used_bags``, ``transfers``); empty when there is none yet."""
    file = model_dir / STATE_FILE
    if not file.exists():
        return {"used_bags": [], "transfers": []}
    try:
        state = json.loads(file.read_text())
        if not isinstance(state.get("used_bags"), list) or not isinstance(state.get("transfers"), list):
            raise ValueError("expected lists 'used_bags' and 'transfers'")
    except (OSError, ValueError, AttributeError) as err:
        raise TransferRefused(f"state file {file} is unreadable ({err}); fix or remove it") from None
    return state


def write_state(model_dir: Path, state: Mapping[str, Any]) -> None:
    """Replace the state file atomically (written beside it, fsynced, renamed)."""
    model_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(model_dir / STATE_FILE, json.dumps(state, indent=2) + "\n")


def latest_transfer(model_dir: Path) -> tuple[Path, dict[str, Any]] | None:
    """The model the last recorded transfer saved, if it is still there, and its record in the state file
    (``method``, ``made_by``, ``train_episodes``, ``time_utc``...; older records lack some)."""
    try:
        transfers = read_state(model_dir)["transfers"]
    except TransferRefused:
        return None
    if not transfers or not isinstance(transfers[-1], dict):
        return None
    path = model_dir / str(transfers[-1].get("model", ""))
    return (path, transfers[-1]) if path.is_file() else None


def next_model_path(model_dir: Path) -> Path:
    """``model_dir/transferred_<NNN>.safetensors``, one past the highest index there (000 when none)."""
    taken = [int(m.group(1)) for p in model_dir.iterdir() if (m := _MODEL_NAME.match(p.name))] \
        if model_dir.is_dir() else []
    return model_dir / f"{MODEL_PREFIX}_{max(taken, default=-1) + 1:03d}.safetensors"


# ---------------------------------------------------------------- inputs
def load_source(path: Path) -> tuple[TransitionModel, dict[str, Any]]:
    """The source model and its metadata; TransferRefused when it is missing, damaged or not a transition model."""
    try:
        model, meta = load_model(path)
    except DataFileError as err:
        raise TransferRefused(f"source model unusable: {err}") from None
    if not isinstance(model, TransitionModel):
        raise TransferRefused(
            f"source model unusable: {path} holds a {meta.get('kind')!r} model; transfer starts from a "
            f"plain transition model trained on the source hand"
        )
    return model, meta


@dataclass(frozen=True)
class TargetData:
    """What :func:`read_target` made of the new bags."""

    data: TrajectorySet
    read: list[Path]
    skipped: list[tuple[Path, str]]
    """Each unreadable bag, with why (``why`` names the bag)."""
    notes: list[str]
    """What the reader dropped or salvaged in the bags read (each names its bag), the episodes the drop rule cut
    and those split at late steps."""
    late_steps: int
    episodes: tuple[int, ...] = ()
    """The recorded episode (counted over the bags read) each of ``data`` comes from: a split one gives several."""

    @property
    def recorded_episodes(self) -> int:
        """Recorded episodes with a stretch in ``data``."""
        return len(set(self.episodes))


def read_target(bags: Sequence[Path], action_unit_rad: float | None = None) -> TargetData:
    """Every episode of the readable ``bags``, in order, ended at its first drop (the paper's 8 mm rule; a late step
    may move 8 mm a period it lasted: the object moves on during one) and then split at its late steps
    (``quality.usable_stretches``), its actions in ``action_unit_rad`` (the model's: a bag stepped further than that
    unit allows is skipped, with why; None: each bag's own, ``read_bag``'s default).  The notes count episodes as
    the reader gave them."""
    sets, read, skipped, notes = [], [], [], []
    for bag in bags:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                sets.append(read_bag(bag, action_unit_rad))
                read.append(bag)
            except DataFileError as err:  # one bad bag leaves the others usable
                skipped.append((bag, str(err)))
        notes += [str(w.message) for w in caught]
    hand = next((s.hand for s in sets if s.hand), "")
    usable, cut = usable_stretches(TrajectorySet(itertools.chain.from_iterable(sets), hand=hand))
    late = sum(len(found) for found in usable.findings.values())
    return TargetData(usable.data, read, skipped, notes + cut, late, usable.origins)


def skipped_note(skipped: Sequence[str]) -> str:
    """``"; skipped N unreadable bag(s): <bag: why>; ..."`` for an answer, or ``""``."""
    return f"; skipped {len(skipped)} unreadable bag(s): {'; '.join(skipped)}" if skipped else ""


def reading_note(notes: Sequence[str]) -> str:
    """``"; while reading: <bag: what was dropped or salvaged>; ..."`` for an answer, or ``""``."""
    return f"; while reading: {'; '.join(notes)}" if notes else ""


def merged_workspace(source_meta: Mapping[str, Any], target: TrajectorySet) -> Workspace:
    """The source model's stored workspace widened to cover the target training states.

    The planner trusts a prediction inside the workspace; the transferred model
    keeps the source model's knowledge and adds the target's, so both count.
    """
    try:
        source = Workspace.from_metadata(source_meta)
    except (KeyError, TypeError, ValueError) as err:
        raise TransferRefused(f"source model unusable: its stored workspace is invalid ({err})") from None
    if source is None:
        return Workspace.from_trajectories(target)
    own = Workspace.from_trajectories(target, directions=source.directions, load_limit=source.load_limit)
    return Workspace(np.minimum(source.lower, own.lower), np.maximum(source.upper, own.upper), source.load_limit)


def hold_out(data: TrajectorySet, fraction: float, seed: int,
             episodes: Sequence[int] = ()) -> tuple[TrajectorySet, TrajectorySet]:
    """``(train, held_out)``: ``fraction`` of the episodes (rounded down, at least one, never all) held out, of
    each kind apart (:func:`~t42_transfer.evaluation.online_loop.episode_kind`).

    ``episodes``: the recorded episode each of ``data`` comes from (:attr:`TargetData.episodes`): the stretches
    of an episode split at its late steps are held out or trained on together, as one episode (its kind is its
    first stretch's).  Counted in episodes, not transitions: the score is one open-loop rollout per
    held-out episode, and with the few episodes of one session a transition
    count would hold out more than asked.  Per kind: once the loop has recorded
    executed plans beside exploration, a share of each is held out (a kind with
    one episode trains), so the score covers the regime the planner uses as well
    as random actions, which predict it badly (docs/evaluation.md, section 9).
    """
    origin = list(episodes) or list(range(len(data)))
    if len(origin) != len(data):
        raise ValueError(f"episodes names {len(origin)} origins for {len(data)} episodes")
    recorded = list(dict.fromkeys(origin))  # each recorded episode once, in order
    if len(recorded) < 2:
        raise ValueError(f"need at least 2 episodes to hold one out, got {len(recorded)}")
    kinds = [episode_kind(data[origin.index(r)]) for r in recorded]
    groups = [[r for r, k in zip(recorded, kinds, strict=True) if k == kind] for kind in EPISODE_KINDS]
    groups = [g for g in groups if len(g) >= 2] or [recorded]
    rng, held = np.random.default_rng(seed), set()
    for group in groups:
        order = np.asarray(group)[rng.permutation(len(group))]
        held.update(order[: min(max(1, int(fraction * len(group))), len(group) - 1)].tolist())
    out = [i for i, r in enumerate(origin) if r in held]
    return data.subset([i for i, r in enumerate(origin) if r not in held]), data.subset(out)


def scores_by_kind(model: Any, source: Any, held_out: TrajectorySet) -> dict[str, dict[str, float]]:
    """Per episode kind among ``held_out``: its count and the model's, the source's and hold-still's divergence
    (4 mm, steps) and position MSE (mm²): random actions and executed plans are predicted differently."""
    out = {}
    for kind in EPISODE_KINDS:
        episodes = TrajectorySet([t for t in held_out if episode_kind(t) == kind], hand=held_out.hand)
        if not len(episodes):
            continue
        out[kind] = {"episodes": len(episodes)}
        for name, scored in (("model", model), ("source", source), ("hold_still", HoldStill())):
            result = evaluate_model(scored, episodes)
            out[kind][f"{name}_divergence_steps"] = float(result["divergence_mean"])
            out[kind][f"{name}_position_mse_mm2"] = float(result["position_mse_mean"])
    return out


# ---------------------------------------------------------------- the transfer
def bags_to_read(spec: OnlineTransferSpec, state: Mapping[str, Any]) -> list[Path]:
    """The bags a transfer reads: exactly those named (``exact_bags``), else the candidates (``bags``, or the
    finished bags in ``bag_dir``) no earlier transfer used, or all of them once one is new (not ``new_bags_only``).
    TransferRefused when there are none, or when a bag is named twice (its episodes would be held out and trained
    on at once, and the held-out score flatter the model)."""
    named: dict[str, list[Path]] = {}
    for bag in spec.bags:
        named.setdefault(bag_key(bag), []).append(bag)
    twice = [str(paths[0]) for paths in named.values() if len(paths) > 1]
    if twice:
        raise TransferRefused(f"bags named more than once: {', '.join(twice)}")
    if spec.exact_bags:
        if not spec.bags:
            raise TransferRefused("no bags named")
        return list(spec.bags)
    if spec.bags:
        candidates, where = list(spec.bags), "the configured bags"
    elif spec.bag_dir is not None:
        if not spec.bag_dir.is_dir():
            raise TransferRefused(f"bag_dir {spec.bag_dir} is not a directory")
        candidates, where = list_bags(spec.bag_dir), str(spec.bag_dir)
    else:
        raise TransferRefused("no bags configured: set bag_dir or bags")
    if not candidates:  # (none ever came: "all used already" would send the user looking for earlier transfers)
        raise TransferRefused(f"no finished bags in {where} yet (a bag is finished once its metadata.yaml is "
                              "written: the recorder closes it at the episode's end)")
    used = set(state["used_bags"])
    new = [b for b in candidates if bag_key(b) not in used]
    if not new:
        raise TransferRefused(
            f"no new bags in {where} since the last transfer ({len(candidates)} bag(s), all used already)"
        )
    return new if spec.new_bags_only else candidates


def run_transfer(spec: OnlineTransferSpec, report: Report = lambda stage, info: None,
                 cancel: Callable[[], bool] = lambda: False) -> TransferResult:
    """One transfer on the bags not used before (or exactly the bags named, with ``spec.exact_bags``); see the
    module docstring.  TransferRefused on bad input.

    ``cancel()`` (e.g. a :class:`threading.Event`'s ``is_set``) is asked at each stage change and after every
    training epoch; once it is true, :class:`TransferCancelled` is raised there, until the save begins (from then
    the transfer completes: its files are written atomically and it is then the current model).
    """
    start = time.monotonic()
    epochs_done = [0]

    def check_cancel(where: str) -> None:
        if cancel():
            done = f" after {epochs_done[0]} training epoch(s)" if epochs_done[0] else ""
            raise TransferCancelled(f"cancelled while {where}{done}; nothing was saved, the previous model stays")

    report("loading", {"method": spec.method})
    if spec.method not in METHODS:
        raise TransferRefused(f"unknown transfer method {spec.method!r}; expected one of {sorted(METHODS)}")
    state = read_state(spec.model_dir)
    new = bags_to_read(spec, state)
    source, source_meta = load_source(spec.source_model)
    target = read_target(new, source_meta[UNIT_KEY])  # the source's unit: its transfer learns the same actions
    data, readable, skipped_pairs, notes = target.data, target.read, target.skipped, target.notes
    if source_meta.get(UNIT_ASSUMED_KEY):
        notes = [f"{spec.source_model} was saved before model files stored their action unit: its actions, and the "
                 f"bags', are taken as {source_meta[UNIT_KEY]:.3g} rad a step", *notes]
    skipped = [why for _, why in skipped_pairs]
    if target.recorded_episodes < spec.min_episodes:  # (a split episode is held out whole)
        raise TransferRefused(
            f"too little data: {target.recorded_episodes} episode(s) ({data.num_transitions} transitions) in "
            f"{len(readable)} readable {'named' if spec.exact_bags else 'new'} bag(s); need at least "
            f"{spec.min_episodes} (some to train on, one held out){skipped_note(skipped)}{reading_note(notes)}",
            skipped_pairs,
        )
    check_cancel("reading the bags")
    train, held_out = hold_out(data, spec.holdout_fraction, spec.seed, target.episodes)
    workspace = merged_workspace(source_meta, train)
    report("training", {
        "bags": ",".join(b.name for b in readable), "skipped_bags": len(skipped), "episodes": len(train),
        "transitions": train.num_transitions, "held_out_episodes": len(held_out), "epoch": 0,
        "epochs": epoch_budget(spec.method, spec.config),
    })
    def on_epoch(progress: Progress) -> None:
        epochs_done[0] += 1
        report("training", epoch_info(progress))
        check_cancel(f"training ({progress.phase}, epoch {progress.epoch}/{progress.epochs})")

    selection = None
    try:
        if spec.method == "auto":
            selection = select_method(source, train, spec.config, seed=spec.seed, on_epoch=on_epoch)
            model = selection.model
        else:
            model = transfer(spec.method, source, train, spec.config, seed=spec.seed, on_epoch=on_epoch)
    except ValueError as err:  # the method refuses data it cannot use, with the reason
        raise TransferRefused(f"{spec.method} cannot use this data: {err}", skipped_pairs) from None
    check_cancel("training")
    report("evaluating", {})
    scores = evaluate_model(model, held_out)
    baseline = evaluate_model(source, held_out)
    still = evaluate_model(HoldStill(), held_out)
    by_kind = scores_by_kind(model, source, held_out)
    check_cancel("evaluating")
    report("saving", {})
    path = _commit(model, spec, state, readable, source_meta, train, held_out, workspace,
                   {**scores, "by_kind": by_kind}, selection)
    return TransferResult(
        method=spec.method, bags=tuple(readable), episodes=len(train), transitions=train.num_transitions,
        held_out_episodes=len(held_out), divergence_steps=scores["divergence_mean"],
        position_mse_mm2=scores["position_mse_mean"], source_divergence_steps=baseline["divergence_mean"],
        source_position_mse_mm2=baseline["position_mse_mean"], model_path=path, seconds=time.monotonic() - start,
        skipped_bags=tuple(skipped_pairs),
        hold_still_divergence_steps=still["divergence_mean"], hold_still_position_mse_mm2=still["position_mse_mean"],
        notes=tuple(notes), late_steps=target.late_steps, selection=selection,
        held_out_by_kind=by_kind,
    )


def _commit(
    model: Any, spec: OnlineTransferSpec, state: Mapping[str, Any], bags: Sequence[Path],
    source_meta: Mapping[str, Any], train: TrajectorySet, held_out: TrajectorySet, workspace: Workspace,
    scores: Mapping[str, Any], selection: Selection | None = None,
) -> Path:
    """Save the numbered model, replace ``current`` (the commit point), then record the bags as used.

    A model ``auto`` picked is saved under the method that made it, with the pick and every candidate's
    score in its metadata (``extra.selection``) and in the state file.
    """
    evaluation = {
        "held_out": held_out.fingerprint(), "episodes": len(held_out),
        "divergence_steps": scores["divergence_mean"], "position_mse_mm2": scores["position_mse_mean"],
        "by_kind": scores.get("by_kind", {}),
    }
    made_by = spec.method if selection is None else selection.best
    section = getattr(spec.config, made_by, None)
    picked = {} if selection is None else {"selection": selection.to_dict()}
    kwargs: dict[str, Any] = {
        "method": made_by,
        "hyperparameters": dataclasses.asdict(section) if dataclasses.is_dataclass(section) else {},
        "data": {
            "target": train.fingerprint(), "bags": [bag_key(b) for b in bags],
            "source_model": str(spec.source_model), "source_data": source_meta.get("data", {}),
        },
        "extra": {"workspace": workspace.to_dict(), "evaluation": evaluation, **picked},
        "action_unit_rad": source_meta[UNIT_KEY],  # the target data were read in it
    }
    path = next_model_path(spec.model_dir)
    save_model(model, path, **kwargs)
    try:
        save_model(model, spec.model_dir / CURRENT_MODEL, **kwargs)
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    record = {
        "model": path.name, "method": spec.method, "made_by": made_by, "train_episodes": len(train),
        "bags": [bag_key(b) for b in bags],
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **evaluation, **picked,
    }
    try:
        write_state(spec.model_dir, {
            **state, "used_bags": list(dict.fromkeys([*state["used_bags"], *(bag_key(b) for b in bags)])),
            "transfers": [*state["transfers"], record],
        })
    except OSError as err:
        raise OSError(
            f"{path} is the current model, but recording its bags in {STATE_FILE} failed ({err}); "
            "they will be offered to the next transfer again"
        ) from err
    return path
