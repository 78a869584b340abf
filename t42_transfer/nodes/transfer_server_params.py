"""The transfer server's ROS parameters (:class:`TransferServerParams`), checked in the dataclass as every node's
are."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from t42_transfer.ros.dirs import claim, in_namespace
from t42_transfer.ros.params import param, torch_threads_param

if TYPE_CHECKING:  # the science is imported on first use (node start-up time)
    from t42_transfer.transfer.config import TransferConfig
    from t42_transfer.transfer.online import OnlineTransferSpec


def method_names() -> list[str]:
    """The transfer methods' registry (imports the science)."""
    from t42_transfer.transfer.methods import METHODS

    return sorted(METHODS)


@dataclass(frozen=True)
class TransferServerParams:
    """The transfer server's ROS parameters."""

    source_model: Path = param(description="the source hand's model (a transition model checkpoint); "
                                           "read at every call")
    model_dir: Path = param(description="where transferred_<NNN>.safetensors, current.safetensors and the state "
                                        "file live; a relative one is taken under the node's namespace",
                            read_only=True)
    bag_dir: str = param("", "finished bags here not used by an earlier transfer are the target data "
                             "(empty: use bags); a relative one is taken under the node's namespace, as the "
                             "recorder's out_dir", read_only=True)
    bags: tuple[str, ...] = param((), "explicit target bags instead of bag_dir; those used by an earlier "
                                      "transfer are skipped too", read_only=True)
    share_dirs: bool = param(False, "use model_dir and bag_dir even when a suite under another namespace holds "
                                    "them (two suites sharing files on purpose)", read_only=True)
    new_bags_only: bool = param(True, "train on the bags no earlier transfer used; false: on every bag, once one "
                                      "is new (the suite keeps learning from all it recorded)")
    method: str = param("l2_finetune", "transfer method, one of new_model, direct, naive_finetune, "
                                       "trajectory_finetune, cumulative_residual, recurrent_residual, l2_finetune, "
                                       "multistep_l2_finetune, anchored_finetune, auto (default: the evaluations' "
                                       "choice, docs/evaluation.md; auto: train the candidates, keep the best on "
                                       "held-out episodes, report all); a t42/transfer goal may name another")
    config: str = param("", "YAML file of overrides of the methods' settings, e.g. "
                                 "'cumulative_residual: {train: {epochs: 50}}' (empty: the paper's defaults); "
                                 "checked when set, read at every call")
    holdout_fraction: float = param(0.25, "share of the new episodes held out (at least one) to score the model, "
                                    "of exploration and of executed plans apart",
                                    min=0.0, max=1.0, constraints="strictly between 0 and 1")
    min_episodes: int = param(2, "fewer new episodes than this are refused as too little data", min=2)
    seed: int = param(0, "seed of the hold-out split and the training", min=0)
    progress_period_s: float = param(0.5, "diagnostics are re-published this often while a transfer runs",
                                     min=0.001, max=3600.0)
    auto_transfer_after_bags: int = param(0, "transfer by itself after this many new bags closed by the recorder "
                                             "(recorder/bag_closed, bags holding an episode); 0: off", min=0)
    torch_threads: int = torch_threads_param()

    def __post_init__(self) -> None:
        if not self.bag_dir and not self.bags:
            raise ValueError("set bag_dir or bags: the transfer needs target bags")
        if self.method not in method_names():
            raise ValueError(f"method must be one of {method_names()}, got {self.method!r}")
        self.transfer_config()  # ValueError for an unreadable file, an unknown key or a wrong type
        if not 0.0 < self.holdout_fraction < 1.0:
            raise ValueError(f"holdout_fraction must be in (0, 1), got {self.holdout_fraction!r}")
        if not isinstance(self.min_episodes, int) or self.min_episodes < 2:
            raise ValueError(f"min_episodes must be an int >= 2 (one to train on, one held out), "
                             f"got {self.min_episodes!r}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative int, got {self.seed!r}")
        if not (math.isfinite(self.progress_period_s) and self.progress_period_s > 0):
            raise ValueError(f"progress_period_s must be positive, got {self.progress_period_s!r}")
        if not isinstance(self.auto_transfer_after_bags, int) or self.auto_transfer_after_bags < 0:
            raise ValueError(f"auto_transfer_after_bags must be an int >= 0 (0: off), "
                             f"got {self.auto_transfer_after_bags!r}")

    def transfer_config(self) -> TransferConfig:
        """The :class:`~t42_transfer.transfer.config.TransferConfig` of the ``config`` file (read now)."""
        from t42_transfer.transfer.online import config_from_file

        return config_from_file(self.config)

    def spec(self, namespace: str = "") -> OnlineTransferSpec:
        """What one call runs on, built per call so the files are looked at afresh; ValueError for a bad config.
        Relative directories are taken under ``namespace``'s own folder (``models/left``); a directory another
        namespace's suite holds is refused (ValueError) unless ``share_dirs``."""
        from t42_transfer.transfer.online import OnlineTransferSpec

        model_dir = in_namespace(self.model_dir, namespace)
        bag_dir = in_namespace(self.bag_dir, namespace) if self.bag_dir else None
        for directory in (model_dir, bag_dir):
            if directory is not None:
                claim(directory, namespace, self.share_dirs)
        return OnlineTransferSpec(
            source_model=Path(self.source_model), model_dir=model_dir, bag_dir=bag_dir,
            bags=tuple(Path(b) for b in self.bags),
            new_bags_only=self.new_bags_only, method=self.method, config=self.transfer_config(),
            holdout_fraction=self.holdout_fraction,
            min_episodes=self.min_episodes, seed=self.seed,
        )
