"""Saved models as experiments and evaluations take them: a project model file, or one of the paper authors'
files (``.pkl``) imported on the fly, and a source that is a model (``source: {model: PATH}``) kept in a run's
``sources/`` under its content's digest."""

from __future__ import annotations

import functools
import hashlib
import os
import shutil
from pathlib import Path
from typing import Any

from t42_transfer.conventions import AUTHORS_ACTION_UNIT_RAD, same_action_unit
from t42_transfer.evaluation.experiment_config import AUTHORS_SUFFIX, DataSpec, ExperimentConfig, sides
from t42_transfer.models.checkpoint import UNIT_ASSUMED_KEY, UNIT_KEY, load_model
from t42_transfer.models.dynamics import LatentDynamics


def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes (a source model's identity: its name alone could be reused for other weights)."""
    file = Path(path)
    info = file.stat()
    return _sha256_of(str(file.resolve()), info.st_mtime_ns, info.st_size)


@functools.lru_cache(maxsize=16)
def _sha256_of(path: str, mtime_ns: int, size: int) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def load_model_file(path: str | os.PathLike[str], negate_actions: bool = False
                    ) -> tuple[LatentDynamics, dict[str, Any]]:
    """A saved model and its metadata: a project model file as saved, or one of the paper authors' files
    (``.pkl``) imported now, its actions negated inside it with ``negate_actions``.

    ValueError ``<file>: <problem>`` (one line) for a missing file, a file that is no model, an authors' family
    this project cannot represent, or ``negate_actions`` for a project model file (its actions are as saved).
    """
    from t42_transfer.models.authors import import_authors_model

    file = Path(path)
    if not str(file).endswith(AUTHORS_SUFFIX):
        if negate_actions:
            raise ValueError(f"{file}: negating actions applies to an authors' {AUTHORS_SUFFIX} file imported on the "
                             f"fly; a model file's actions are as it was saved")
        return load_model(file)
    converted, legacy = import_authors_model(file, negate_actions=negate_actions)
    authors = {"source_file": file.name, "source_sha256": legacy.sha256, "family": converted.family,
               "negate_actions": negate_actions}
    return converted.model, {"method": f"authors_{converted.family}", UNIT_KEY: AUTHORS_ACTION_UNIT_RAD,
                             "extra": {"authors": authors}}


def check_action_unit(file: str | os.PathLike[str], meta: dict[str, Any], unit_rad: float, data: str) -> None:
    """ValueError unless the model in ``file`` (``meta``: its metadata) learnt actions in ``unit_rad``, the unit of
    ``data``'s actions (the same action then steps the actuators as far as in its training data).  A file saved
    before units were stored is taken as in ``data``'s (it cannot say)."""
    if not meta.get(UNIT_ASSUMED_KEY) and not same_action_unit(meta[UNIT_KEY], unit_rad):
        raise ValueError(f"{file}: its actions are in steps of {meta[UNIT_KEY]:.3g} rad at an action of 1, the "
                         f"actions of {data} in {unit_rad:.3g} rad (the authors' models and real-hand files are in "
                         "their driver's unit, simulated hands in the suite's, a bag in the one it declares or its "
                         "data spec's action_unit_rad)")


def check_action_units(cfg: ExperimentConfig) -> None:
    """ValueError unless every side's actions are in one unit (a model learns one); loads a source model file."""
    units = {side: getattr(cfg, side).unit_rad() for side in sides(cfg)}
    if cfg.source.model is not None:
        meta = load_source_model(cfg.source)[1]
        units["source"] = units["target"] if meta.get(UNIT_ASSUMED_KEY) else meta[UNIT_KEY]  # (it cannot say)
    if not all(same_action_unit(unit, units["target"]) for unit in units.values()):
        shown = ", ".join(f"{side} {unit:.3g} rad" for side, unit in units.items())
        raise ValueError(f"the sides' actions are in different units ({shown} a step at an action of 1: the "
                         "authors' real-hand files and models in their driver's, simulated hands in the suite's, a bag "
                         "in the one it declares or its spec's action_unit_rad): a model learns one")


def load_source_model(spec: DataSpec) -> tuple[LatentDynamics, dict[str, Any]]:
    """The model a ``source: {model: PATH}`` names, with its metadata (:func:`load_model_file`, actions negated
    inside an authors' model when the spec negates them); ValueError ``source.model: <file>: <problem>``."""
    if spec.model is None:
        raise ValueError("the source is data, not a model")
    try:
        return load_model_file(spec.model, spec.negate_actions)
    except ValueError as err:  # CheckpointError and AuthorsModelError name the file
        raise ValueError(f"source.model: {err}") from None


def put_source_model(spec: DataSpec, path: Path) -> None:
    """Put the source model ``spec`` names at ``path``: an authors' file imported, a model file copied as it is
    (atomically: a run that stops halfway leaves no file under the final name)."""
    from t42_transfer.models.authors import save_authors_model

    if spec.model is None:
        raise ValueError("the source is data, not a model")
    if spec.model.endswith(AUTHORS_SUFFIX):
        save_authors_model(spec.model, path, negate_actions=spec.negate_actions)
        return
    load_source_model(spec)  # a model file, checked whole before it is kept
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        shutil.copyfile(spec.model, tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
