"""Transfer methods: source model + a little target data -> target model (one registry)."""

from t42_transfer.transfer.config import TransferConfig
from t42_transfer.transfer.methods import METHODS, PAPER_METHODS, transfer

__all__ = ["METHODS", "PAPER_METHODS", "TransferConfig", "transfer"]
