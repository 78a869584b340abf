"""Transition models: the one dynamics contract, the paper's MLP, residual models, training, checkpoints."""

from t42_transfer.models.dynamics import MODEL_KINDS, LatentDynamics
from t42_transfer.models.network import Normalisation, TransitionModel
from t42_transfer.models.residual import AdjustedStateResidualModel, CumulativeResidualModel, RecurrentResidualModel
from t42_transfer.models.start_state import StartStateCumulativeResidualModel, StartStateRecurrentResidualModel

__all__ = [
    "MODEL_KINDS",
    "AdjustedStateResidualModel",
    "CumulativeResidualModel",
    "LatentDynamics",
    "Normalisation",
    "RecurrentResidualModel",
    "StartStateCumulativeResidualModel",
    "StartStateRecurrentResidualModel",
    "TransitionModel",
]
