"""Transition models: the one dynamics contract, the paper's MLP, training, checkpoints."""

from t42_transfer.models.dynamics import MODEL_KINDS, LatentDynamics
from t42_transfer.models.network import Normalisation, TransitionModel

__all__ = ["MODEL_KINDS", "LatentDynamics", "Normalisation", "TransitionModel"]
