"""Transfer action and model announcements <-> plain Python: ``t42_interfaces/action/Transfer`` (the transfer
server's ``t42/transfer``) and ``t42_interfaces/msg/ModelUpdated`` (``t42/model_updated``).

The science layer's results stay out of this module (it imports nothing of ``t42_transfer``): the node hands
over plain values, :class:`TransferOutcome` for a result and the stage and progress mapping its transfer reports
for feedback.  rclpy's classes, as for Reach: ``t42_interfaces`` is ours, not in rosbags' Jazzy typestore.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

from msg_adapters.hand import ns_to_stamp, stamp_to_ns
from msg_adapters.kit import RCLPY, MessageKit, rclpy_class

TRANSFER = "t42_interfaces/action/Transfer"
MODEL_UPDATED_MSG = "t42_interfaces/msg/ModelUpdated"


def transfer_type() -> Any:
    """rclpy's ``Transfer`` action class (imported on first use: t42_interfaces is built by scripts/bootstrap.sh)."""
    return rclpy_class(TRANSFER)


@dataclass(frozen=True)
class TransferRequest:
    """A Transfer goal as the server reads it: ``method`` ``""`` means the server's parameter, no ``bags`` the
    bags closed since the last transfer."""

    method: str
    bags: tuple[str, ...]

    @property
    def problem(self) -> str | None:
        """Why the goal cannot be run as sent, else None: a blank bag path (as a path, "" is "." and the
        server's working directory would be read as a bag)."""
        blank = next((i for i, bag in enumerate(self.bags) if not bag.strip()), None)
        if blank is None:
            return None
        return f"bags[{blank}] is an empty path; name bag directories, or send no bags for the new ones"


def transfer_request(goal: Any) -> TransferRequest:
    """The server's view of a ``Transfer.Goal`` (blanks around the method dropped)."""
    return TransferRequest(str(goal.method).strip(), tuple(str(b) for b in goal.bags))


class Scores(NamedTuple):
    """Held-out scores of one model: steps until the prediction diverges, position MSE (mm^2)."""

    divergence_steps: float = math.nan
    mse_mm2: float = math.nan


@dataclass(frozen=True)
class TransferOutcome:
    """What a Transfer goal's result says; NaN scores and empty lists where nothing was scored or saved."""

    success: bool
    message: str
    model_path: str = ""
    model: Scores = Scores()
    source: Scores = Scores()
    hold_still: Scores = Scores()
    candidates: tuple[tuple[str, float], ...] = ()
    """``auto``'s candidates and their held-out divergence steps (NaN for one that failed)."""
    skipped: tuple[tuple[str, str], ...] = ()
    """Each bag not used, with why."""


def transfer_result(outcome: TransferOutcome) -> Any:
    """``Transfer.Result`` of ``outcome``."""
    return transfer_type().Result(
        success=bool(outcome.success), message=str(outcome.message), model_path=str(outcome.model_path),
        model_divergence_steps=float(outcome.model.divergence_steps), model_mse_mm2=float(outcome.model.mse_mm2),
        source_divergence_steps=float(outcome.source.divergence_steps), source_mse_mm2=float(outcome.source.mse_mm2),
        hold_still_divergence_steps=float(outcome.hold_still.divergence_steps),
        hold_still_mse_mm2=float(outcome.hold_still.mse_mm2),
        candidates=[str(name) for name, _ in outcome.candidates],
        candidate_scores=[float(score) for _, score in outcome.candidates],
        skipped_bags=[str(bag) for bag, _ in outcome.skipped],
        skipped_reasons=[str(why) for _, why in outcome.skipped],
    )


def transfer_feedback(stage: str, info: Mapping[str, object]) -> Any:
    """``Transfer.Feedback`` of one progress report (a stage change, or a training epoch with ``phase``,
    ``epoch``, ``epochs``, ``train_loss`` and ``val_loss`` when validated).

    ``phase`` is the stage, and while training ``training: <what the method trains>`` once an epoch named it;
    epoch and epochs are 0 outside training, the losses NaN when not known.
    """
    training = stage == "training"
    phase = f"{stage}: {info['phase']}" if training and info.get("phase") else stage
    return transfer_type().Feedback(
        phase=phase,
        epoch=_count(info.get("epoch")) if training else 0,
        epochs=_count(info.get("epochs")) if training else 0,
        train_loss=_float(info.get("train_loss")) if training else math.nan,
        val_loss=_float(info.get("val_loss")) if training else math.nan,
    )


def model_updated_msg(stamp_ns: int, path: str, method: str, episodes: int, kit: MessageKit = RCLPY) -> Any:
    """The ``ModelUpdated`` announcement of a saved model file; ValueError for a count that does not fit."""
    if not 0 <= int(episodes) < 2**32:
        raise ValueError(f"episodes must fit a uint32, got {episodes}")
    return kit.make(MODEL_UPDATED_MSG, stamp=ns_to_stamp(stamp_ns, kit), path=str(path), method=str(method),
                    episodes=int(episodes))


class ModelAnnouncement(NamedTuple):
    """A ``ModelUpdated`` message's content."""

    stamp_ns: int
    path: str
    method: str
    episodes: int


def model_announcement(msg: Any) -> ModelAnnouncement:
    """What a ``ModelUpdated`` message announces (the path with surrounding blanks dropped)."""
    return ModelAnnouncement(stamp_to_ns(msg.stamp), str(msg.path).strip(), str(msg.method), int(msg.episodes))


def _count(value: object) -> int:
    try:
        number = int(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return 0
    return min(max(number, 0), 2**32 - 1)


def _float(value: object) -> float:
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


def skipped_pairs(skipped: Sequence[tuple[object, str]]) -> tuple[tuple[str, str], ...]:
    """The ``(bag, why)`` pairs as strings, each ``why`` without the ``"<bag>: "`` it starts with when it names its
    bag."""
    pairs = []
    for bag, why in skipped:
        prefix = f"{bag}: "
        pairs.append((str(bag), why[len(prefix):] if why.startswith(prefix) else why))
    return tuple(pairs)


def transfer_goal(method: str = "", bags: Sequence[object] = ()) -> Any:
    """A ``Transfer.Goal`` (a client's side): ``""`` = the server's method, no bags = those closed since the last
    transfer."""
    return transfer_type().Goal(method=str(method), bags=[str(b) for b in bags])


class TransferProgress(NamedTuple):
    """A ``Transfer.Feedback``: the phase, epoch / epochs (0 outside training), the epoch's losses (NaN: unknown)."""

    phase: str
    epoch: int
    epochs: int
    train_loss: float
    val_loss: float


def transfer_progress(feedback: Any) -> TransferProgress:
    return TransferProgress(str(feedback.phase), int(feedback.epoch), int(feedback.epochs),
                            float(feedback.train_loss), float(feedback.val_loss))


def transfer_outcome(result: Any) -> TransferOutcome:
    """The :class:`TransferOutcome` a ``Transfer.Result`` carries (the inverse of :func:`transfer_result`)."""
    return TransferOutcome(
        bool(result.success), str(result.message), str(result.model_path),
        Scores(float(result.model_divergence_steps), float(result.model_mse_mm2)),
        Scores(float(result.source_divergence_steps), float(result.source_mse_mm2)),
        Scores(float(result.hold_still_divergence_steps), float(result.hold_still_mse_mm2)),
        tuple(zip(map(str, result.candidates), map(float, result.candidate_scores), strict=False)),
        tuple(zip(map(str, result.skipped_bags), map(str, result.skipped_reasons), strict=False)),
    )
