"""The paper authors' own saved models as project models: every family they published, and the import.

The files are read by :mod:`~t42_transfer.models.legacy_torch` (no code of theirs
runs); the object tree then maps onto the project's model kinds (``FAMILIES``):

- ``TrajNet`` without ``res`` (the authors' source, new and fine-tuned models): a
  :class:`~t42_transfer.models.TransitionModel` with the start state as input and
  the file's own normalisation;
- ``TrajNet`` with ``res`` (recurrent residual, ``out = net_S(u) + coeff res(u)``):
  :class:`~t42_transfer.models.start_state.StartStateRecurrentResidualModel`;
- ``TimeIndepLatentDeltaNet`` (cumulative residual): a
  :class:`~t42_transfer.models.start_state.StartStateCumulativeResidualModel` of the
  frozen source with its own (B's) normalisation and the decoder ``g`` with the
  outer (A's); the GRU encoder in those files is never used by their rollout and is
  dropped.

``negate_actions`` flips the sign of the action columns of every first layer
(exact in floating point), so the imported model takes hand A's actions as
recorded while computing what the authors' model computed on negated ones.

The residual weight ``alpha`` defaults to the file's ``coeff`` (1) and the
cumulative residual's decay ``gamma`` to :data:`AUTHORS_GAMMA`; both are rollout-time
settings (the files do not store gamma), so the import takes them as options.
Rollouts equal the authors' forward pass with dropout off (test_authors_models
checks it to 1e-3 mm over whole paths), except that the cumulative residual keeps
the paper's alignment of the residual sum (see
:class:`~t42_transfer.models.start_state.StartStateCumulativeResidualModel`).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from t42_transfer.conventions import ACTION_DIM, AUTHORS_ACTION_UNIT_RAD, STATE_DIM
from t42_transfer.models.checkpoint import save_model
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.models.legacy_torch import (
    AuthorsModelError,
    LegacyFile,
    ModuleObject,
    Refused,
    TensorRef,
    load_legacy,
    quoted,
)
from t42_transfer.models.network import Normalisation, TransitionModel
from t42_transfer.models.start_state import StartStateCumulativeResidualModel, StartStateRecurrentResidualModel

FAMILIES = {
    "mlp": "TrajNet without res: the source, new and fine-tuned models -> transition (start state as input)",
    "recurrent_residual": "TrajNet with res: net_S(u) + coeff res(u) -> start_state_recurrent_residual",
    "cumulative_residual": "TimeIndepLatentDeltaNet: frozen source (its own norm) + decoder g (outer norm) "
                           "-> start_state_cumulative_residual",
}
"""Every family the published files hold and the project model kind it becomes."""

AUTHORS_GAMMA = 0.993
"""The cumulative residual's decay, hard-coded in the authors' rollout at the commit the files come from
(fed5d81); it is not stored in the files."""

_INPUTS = 2 * STATE_DIM + ACTION_DIM
_LAYERS = (("0", "torch.nn.modules.linear.Linear"), ("1", "torch.nn.modules.activation.SELU"),
           ("2", "torch.nn.modules.dropout.AlphaDropout"), ("3", "torch.nn.modules.linear.Linear"),
           ("4", "torch.nn.modules.activation.Tanh"), ("5", "torch.nn.modules.dropout.Dropout"),
           ("6", "torch.nn.modules.linear.Linear"))
"""The authors' pt_build_model('1', 10, 4): the project's MLP, layer for layer."""


def _field(obj: Any, name: str, what: str, cls: str | None = None) -> Any:
    if not (isinstance(obj, ModuleObject) and isinstance(obj.state, dict)):
        raise Refused(f"{what} is not a module object")
    if cls is not None and obj.cls != cls:
        raise Refused(f"{what} is a {obj.cls}, not a {cls}")
    if name not in obj.state:
        raise Refused(f"{what} ({obj.cls}) has no {name!r}")
    return obj.state[name]


def _modules(obj: Any, what: str) -> dict[str, Any]:
    modules = _field(obj, "_modules", what)
    if type(modules) is not dict:
        raise Refused(f"{what} has no submodule table")
    return modules


def _child(obj: Any, name: str, what: str, cls: str | None = None) -> Any:
    modules = _modules(obj, what)
    if name not in modules:
        raise Refused(f"{what} has no submodule {name!r}")
    child = modules[name]
    if cls is not None and not (isinstance(child, ModuleObject) and child.cls == cls):
        raise Refused(f"{what}.{name} is not a {cls}")
    return child


@dataclass(frozen=True)
class _AuthorsNorm:
    """TrajNet.norm: input mean/std over [state, action, start state] and output (state change) mean/std."""

    x_mean: np.ndarray
    x_std: np.ndarray
    y_mean: np.ndarray
    y_std: np.ndarray

    def project(self, delta_mean: np.ndarray | None = None, delta_std: np.ndarray | None = None) -> Normalisation:
        """The project's normalisation: state statistics from the input's first 4, changes from the output's."""
        return Normalisation(self.x_mean[:STATE_DIM].astype(np.float32), self.x_std[:STATE_DIM].astype(np.float32),
                             (self.y_mean if delta_mean is None else delta_mean).astype(np.float32),
                             (self.y_std if delta_std is None else delta_std).astype(np.float32))


def _norm(legacy: LegacyFile, obj: Any, what: str) -> _AuthorsNorm:
    norm = _field(obj, "norm", what)
    if not (type(norm) is tuple and len(norm) == 4):
        raise Refused(f"{what}.norm must be (x_mean, x_std, y_mean, y_std)")
    shapes = ((_INPUTS,), (_INPUTS,), (STATE_DIM,), (STATE_DIM,))
    arrays = [legacy.tensor(t, f"{what}.norm[{i}]", s).numpy().astype(np.float64)
              for i, (t, s) in enumerate(zip(norm, shapes, strict=True))]
    result = _AuthorsNorm(*arrays)
    if not ((result.x_std > 0).all() and (result.y_std > 0).all()):
        raise Refused(f"{what}.norm has a standard deviation that is not positive")
    action = slice(STATE_DIM, STATE_DIM + ACTION_DIM)
    if not (np.all(result.x_mean[action] == 0) and np.all(result.x_std[action] == 1)):
        raise Refused(f"{what}.norm normalises actions (the authors' models leave them raw)")
    return result


def _sequential(legacy: LegacyFile, seq: Any, what: str) -> tuple[list[torch.Tensor], float, int]:
    """The MLP's weights and biases (layers 0, 3, 6), its dropout probability and hidden width."""
    if not (isinstance(seq, ModuleObject) and seq.cls == "torch.nn.modules.container.Sequential"):
        raise Refused(f"{what} is not a Sequential")
    modules = _modules(seq, what)
    if list(modules) != [name for name, _ in _LAYERS]:
        raise Refused(f"{what} is not the authors' 7-layer MLP")
    for name, cls in _LAYERS:
        _child(seq, name, what, cls)
    first = _field(modules["0"], "_parameters", f"{what}.0")
    bias = first.get("bias") if type(first) is dict else None
    hidden = bias.shape[0] if isinstance(bias, TensorRef) and len(bias.shape) == 1 else 0
    if not 1 <= hidden <= 4096:
        raise Refused(f"{what} has a hidden width of {hidden}")
    dropouts = {_field(modules[n], "p", f"{what}.{n}") for n in ("2", "5")}
    if len(dropouts) != 1 or type(p := dropouts.pop()) is not float or not 0.0 <= p < 1.0:
        raise Refused(f"{what} has dropout probabilities other than one shared value in [0, 1)")
    tensors = []
    for name, shape_w in (("0", (hidden, _INPUTS)), ("3", (hidden, hidden)), ("6", (STATE_DIM, hidden))):
        params = _field(modules[name], "_parameters", f"{what}.{name}")
        if type(params) is not dict:
            raise Refused(f"{what}.{name} has no parameters")
        tensors.append(legacy.tensor(params.get("weight"), f"{what}.{name}.weight", shape_w))
        tensors.append(legacy.tensor(params.get("bias"), f"{what}.{name}.bias", (shape_w[0],)))
    return tensors, p, hidden


def _transition(weights: list[torch.Tensor], norm: _AuthorsNorm, model_norm: Normalisation, dropout: float,
                hidden: int, negate_actions: bool) -> TransitionModel:
    """A start-state transition model computing the authors' MLP on ``norm``-normalised inputs.

    The project's model z-scores the start state with the state statistics; the authors used the start
    states' own (``x_mean[6:]``), so the difference is folded into the first layer: exact in real arithmetic,
    a float32 rounding in practice.  Negating actions flips the sign of their two columns (exact).
    """
    model = TransitionModel(model_norm, grasp_input=True, hidden=hidden, dropout=dropout)
    w0 = weights[0].double().clone()
    b0 = weights[1].double().clone()
    start = slice(STATE_DIM + ACTION_DIM, _INPUTS)
    state_mean, state_std = (torch.from_numpy(a.astype(np.float64)) for a in (model_norm.state_mean,
                                                                               model_norm.state_std))
    start_mean, start_std = torch.from_numpy(norm.x_mean[start]), torch.from_numpy(norm.x_std[start])
    # authors: (s - start_mean)/start_std = f * state_std/start_std + (state_mean - start_mean)/start_std
    # for the project's feature f = (s - state_mean)/state_std
    b0 += w0[:, start] @ ((state_mean - start_mean) / start_std)
    w0[:, start] *= state_std / start_std
    # the state columns: authors' and project's statistics are the same numbers (cast to float32 alike)
    if negate_actions:
        w0[:, STATE_DIM:STATE_DIM + ACTION_DIM] *= -1
    layers = [w0.float(), b0.float(), *weights[2:]]
    with torch.no_grad():
        for param, value in zip([model.net[i].weight if k == 0 else model.net[i].bias
                                 for i in (0, 3, 6) for k in (0, 1)], layers, strict=True):
            param.copy_(value)
    return model


@dataclass(frozen=True)
class AuthorsModel:
    """An imported model and what the file said about it."""

    model: LatentDynamics
    family: str
    task: str
    alpha: float | None
    gamma: float | None


def _trajnet(legacy: LegacyFile, obj: Any, what: str, negate_actions: bool) -> tuple[TransitionModel, _AuthorsNorm]:
    """A TrajNet's own MLP with its own normalisation."""
    norm = _norm(legacy, obj, what)
    weights, dropout, hidden = _sequential(legacy, _child(obj, "model", what), f"{what}.model")
    return _transition(weights, norm, norm.project(), dropout, hidden, negate_actions), norm


def _task(obj: Any, what: str) -> str:
    """The TrajNet's ``task`` (``real_B``, ``transferB2A``): informative, kept short."""
    task = _field(obj, "task", what)
    if not (type(task) is str and task.isprintable() and len(task) <= 40):
        raise Refused(f"{what}.task must be a short name, not {quoted(task)[:60]}")
    return task


def convert(legacy: LegacyFile, *, negate_actions: bool = False, gamma: float | None = None,
            alpha: float | None = None) -> AuthorsModel:
    """The project model of an authors' file's object tree; :class:`Refused` for anything else.

    ``alpha`` (default: the file's ``coeff``) weighs the residual of both residual families; ``gamma``
    (default :data:`AUTHORS_GAMMA`) is the cumulative residual's decay.
    """
    root = legacy.root
    if not isinstance(root, ModuleObject):
        raise Refused(f"holds a {type(root).__name__}, not an authors' model object")
    if root.cls == "common.TrajNet.TrajNet":
        task = _task(root, "the model")
        res = _modules(root, "the model").get("res")
        model, norm = _trajnet(legacy, root, "the model", negate_actions)
        if res is None:
            if gamma is not None or alpha is not None:
                raise Refused("is a plain model: alpha and gamma apply to residual families only")
            return AuthorsModel(model, "mlp", task, None, None)
        if gamma is not None:
            raise Refused("is a recurrent residual: gamma applies to the cumulative residual only")
        weight = _coeff(root, alpha, "the model")
        res_weights, res_dropout, res_hidden = _sequential(legacy, res, "the model.res")
        residual_norm = norm.project(np.zeros(STATE_DIM), norm.y_std)  # res(u) scaled like net_S's output
        residual = _transition(res_weights, norm, residual_norm, res_dropout, res_hidden, negate_actions)
        return AuthorsModel(StartStateRecurrentResidualModel(model, residual, weight), "recurrent_residual",
                            task, weight, None)
    if root.cls == "common.TrajNet.TimeIndepLatentDeltaNet":
        source_obj = _child(root, "model", "the model", "common.TrajNet.TrajNet")
        decoder_obj = _child(root, "decoder", "the model", "common.TrajNet.TrajNet")
        for inner, name in ((source_obj, "model"), (decoder_obj, "decoder")):
            if _modules(inner, f"the model.{name}").get("res") is not None:
                raise Refused(f"the model.{name} has a res net, which a cumulative residual never has")
        source, _ = _trajnet(legacy, source_obj, "the model.model", negate_actions)
        outer = _norm(legacy, root, "the model")  # the decoder's input and output use the outer (target) norm
        weights, dropout, hidden = _sequential(legacy, _child(decoder_obj, "model", "the model.decoder"),
                                               "the model.decoder.model")
        decoder = _transition(weights, outer, outer.project(), dropout, hidden, negate_actions)
        weight = _coeff(root, alpha, "the model")
        decay = AUTHORS_GAMMA if gamma is None else gamma
        return AuthorsModel(StartStateCumulativeResidualModel(source, decoder, weight, decay), "cumulative_residual",
                            _task(source_obj, "the model.model"), weight, decay)
    raise Refused(f"holds a {quoted(root.cls)}, a family this project cannot represent (known: {sorted(FAMILIES)})")


def _coeff(obj: Any, alpha: float | None, what: str) -> float:
    if alpha is not None:
        return float(alpha)
    coeff = _field(obj, "coeff", what)
    if type(coeff) not in (int, float) or not np.isfinite(coeff):
        raise Refused(f"{what}.coeff must be a finite number")
    return float(coeff)


def import_authors_model(path: str | os.PathLike[str], *, negate_actions: bool = False, gamma: float | None = None,
                         alpha: float | None = None) -> tuple[AuthorsModel, LegacyFile]:
    """Read and convert an authors' file; :class:`AuthorsModelError` (one line naming it) for anything else."""
    file = Path(path)
    legacy = load_legacy(file)
    try:
        converted = convert(legacy, negate_actions=negate_actions, gamma=gamma, alpha=alpha)
    except Refused as err:
        raise AuthorsModelError(file, str(err)) from None
    except MemoryError:
        raise
    except Exception as err:  # a crafted object tree trips whatever it trips: still the file's fault
        raise AuthorsModelError(file, f"does not hold a model this project can represent ({type(err).__name__}: "
                                f"{str(err)[:200]})") from None
    converted.model.eval()
    return converted, legacy


_FILE_NAME = re.compile(r"(?:real_(?P<hand>[AB])|transferB2A_(?P<method>[a-z_]+?))_heldout(?P<heldout>[0-9.]+)_"
                        r"(?P<repeat>[0-9]+)\.pkl")
"""The published files' names: the authors' method, held-out fraction and repeat (informative only)."""


def describe_name(name: str) -> dict[str, Any]:
    """What a published file's name says (``{}`` for another name): method, held-out fraction, repeat."""
    match = _FILE_NAME.fullmatch(name)
    if match is None:
        return {}
    method = f"real_{match['hand']}" if match["hand"] else match["method"]
    return {"authors_method": method, "heldout": float(match["heldout"]), "repeat": int(match["repeat"])}


def save_authors_model(path: str | os.PathLike[str], out: str | os.PathLike[str], *, negate_actions: bool = False,
                       gamma: float | None = None, alpha: float | None = None) -> tuple[Path, AuthorsModel]:
    """Import ``path`` and write it as a project model file ``out``; the metadata names the source file,
    its sha256 and the authors' family, and the actions' unit is the authors' (``AUTHORS_ACTION_UNIT_RAD``)."""
    converted, legacy = import_authors_model(path, negate_actions=negate_actions, gamma=gamma, alpha=alpha)
    source = Path(path)
    authors = {"source_file": source.name, "source_sha256": legacy.sha256, "family": converted.family,
               "task": converted.task, "negate_actions": negate_actions, **describe_name(source.name)}
    settings = {"negate_actions": negate_actions}
    if converted.alpha is not None:
        settings["alpha"] = converted.alpha
    if converted.gamma is not None:
        settings["gamma"] = converted.gamma
    saved = save_model(converted.model, out, method=f"authors_{authors.get('authors_method', converted.family)}",
                       hyperparameters=settings, data={"source_sha256": legacy.sha256}, extra={"authors": authors},
                       action_unit_rad=AUTHORS_ACTION_UNIT_RAD)
    return saved, converted
