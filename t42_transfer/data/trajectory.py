"""Trajectories of one hand: the in-memory unit every layer exchanges.

A :class:`Trajectory` is one episode: ``T + 1`` states and the ``T`` actions
between them (``states[k + 1]`` followed ``actions[k]`` applied at ``states[k]``).
Arrays are float32, which is what the networks consume and what makes the trip
through SI units on the ROS wire (float64) exact.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from t42_transfer.conventions import ACTION_DIM, CONTROL_PERIOD_NS, END_REASONS, LATE_STEP_NS, STATE_DIM


def _as_f32(name: str, value: np.ndarray | Sequence, cols: int) -> np.ndarray:
    arr = np.ascontiguousarray(np.asarray(value, dtype=np.float32))
    if arr.ndim != 2 or arr.shape[1] != cols:
        raise ValueError(f"{name} must have shape [n, {cols}], got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.argwhere(~np.isfinite(arr))[0, 0])
        raise ValueError(f"{name} has a non-finite value at row {bad}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Trajectory:
    """One episode: ``states[T+1, 4]``, ``actions[T, 2]`` (float32, read-only).

    ``actuator_angles[T+1, 2]`` (rad) is optional: simulated hands know it, the
    public real-hand files do not.  ``start_ns`` is the stamp of ``states[0]``.

    ``step_ns[T]`` (int64, optional) is each transition's real duration when it was not exactly one control
    period: a recording whose driver ran late (a stall, a busy machine, a jittery servo bus) keeps those steps
    and says how long each took (a transfer leaves them out: ``quality.usable_stretches``); ``None`` means every
    step took one period.
    """

    states: np.ndarray
    actions: np.ndarray
    actuator_angles: np.ndarray | None = None
    start_ns: int = 0
    end_reason: str = ""
    hand: str = ""
    step_ns: np.ndarray | None = None

    def __post_init__(self) -> None:
        states = _as_f32("states", self.states, STATE_DIM)
        actions = _as_f32("actions", self.actions, ACTION_DIM)
        if len(states) != len(actions) + 1:
            raise ValueError(
                f"a trajectory needs one more state than actions: {len(states)} states, {len(actions)} actions"
            )
        object.__setattr__(self, "states", states)
        object.__setattr__(self, "actions", actions)
        if self.actuator_angles is not None:
            angles = _as_f32("actuator_angles", self.actuator_angles, ACTION_DIM)
            if len(angles) != len(states):
                raise ValueError(f"actuator_angles has {len(angles)} rows, states {len(states)}")
            object.__setattr__(self, "actuator_angles", angles)
        if self.end_reason not in END_REASONS:
            raise ValueError(f"unknown end_reason {self.end_reason!r}; expected one of {END_REASONS}")
        if self.step_ns is not None:
            steps = np.array(self.step_ns, dtype=np.int64)
            if steps.shape != (len(actions),) or not (steps > 0).all():
                raise ValueError(f"step_ns must hold one positive duration per action ({len(actions)}), "
                                 f"got shape {steps.shape}")
            steps.setflags(write=False)
            object.__setattr__(self, "step_ns", steps)

    def __len__(self) -> int:
        """Number of transitions (actions)."""
        return len(self.actions)

    @property
    def durations_ns(self) -> np.ndarray:
        """Each transition's duration (int64 ns): ``step_ns``, or one control period each."""
        return self.step_ns if self.step_ns is not None else np.full(len(self), CONTROL_PERIOD_NS, np.int64)

    @property
    def late_steps(self) -> np.ndarray:
        """Indices of the transitions that took longer than ``LATE_STEP_NS`` (kept, marked)."""
        return np.flatnonzero(self.durations_ns > LATE_STEP_NS)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Trajectory):
            return NotImplemented
        same_angles = (self.actuator_angles is None) == (other.actuator_angles is None) and (
            self.actuator_angles is None or np.array_equal(self.actuator_angles, other.actuator_angles)
        )
        return (
            np.array_equal(self.states, other.states)
            and np.array_equal(self.actions, other.actions)
            and same_angles
            and self.start_ns == other.start_ns
            and self.end_reason == other.end_reason
            and self.hand == other.hand
            and np.array_equal(self.durations_ns, other.durations_ns)
        )

    __hash__ = None  # type: ignore[assignment]  # mutable-looking arrays: not hashable

    def transitions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x_k, a_k, x_{k+1})`` arrays for single-step training."""
        return self.states[:-1], self.actions, self.states[1:]

    def fingerprint(self) -> str:
        """Content hash of the numbers (sha256 hex), for checkpoints and caches."""
        h = hashlib.sha256()
        h.update(self.states.tobytes())
        h.update(self.actions.tobytes())
        return h.hexdigest()


class TrajectorySet:
    """An ordered, immutable collection of episodes from one hand."""

    def __init__(self, trajectories: Iterable[Trajectory] = (), hand: str = "") -> None:
        self.trajectories: tuple[Trajectory, ...] = tuple(trajectories)
        self.hand = hand

    def __repr__(self) -> str:
        return f"TrajectorySet(hand={self.hand!r}, episodes={len(self)}, transitions={self.num_transitions})"

    def __len__(self) -> int:
        return len(self.trajectories)

    def __iter__(self) -> Iterator[Trajectory]:
        return iter(self.trajectories)

    def __getitem__(self, index: int) -> Trajectory:
        return self.trajectories[index]

    @property
    def num_transitions(self) -> int:
        return sum(len(t) for t in self.trajectories)

    def subset(self, indices: Iterable[int]) -> TrajectorySet:
        return TrajectorySet((self.trajectories[i] for i in indices), hand=self.hand)

    def transitions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stacked ``(x, a, x_next)`` over every episode; empty arrays when there are none."""
        if not self.trajectories:
            return (
                np.zeros((0, STATE_DIM), np.float32),
                np.zeros((0, ACTION_DIM), np.float32),
                np.zeros((0, STATE_DIM), np.float32),
            )
        parts = [t.transitions() for t in self.trajectories]
        return tuple(np.concatenate(p) for p in zip(*parts, strict=True))  # type: ignore[return-value]

    def start_states(self) -> np.ndarray:
        """Each transition's episode's first state, row for row with :meth:`transitions` (the grasp input of
        models that read it)."""
        if not self.trajectories:
            return np.zeros((0, STATE_DIM), np.float32)
        return np.concatenate([np.repeat(t.states[:1], len(t), axis=0) for t in self.trajectories])

    def fingerprint(self) -> str:
        h = hashlib.sha256()
        for t in self.trajectories:
            h.update(t.fingerprint().encode())
        return h.hexdigest()


def grasp_centre(data: TrajectorySet) -> np.ndarray:
    """Object x, y (mm) where the hand holds it at rest: the median of the episodes' first positions.

    Every episode starts from the grasp the closing routine made; the median ignores a start whose
    tracking was stale (hand B's cylinder path 0).
    """
    if not len(data):
        raise ValueError("an empty trajectory set has no grasp")
    return np.median(np.stack([t.states[0, :2] for t in data]).astype(np.float64), axis=0)


SAME_SEQUENCE_OVERLAP = 0.9
"""Two episodes ran the same action sequence when the shorter, at least this share of the longer, agrees with
the longer's start: a hand that dropped the object stopped early (hand B's cylinder path 4 ran 795 of 817)."""


def same_action_sequence(a: Trajectory, b: Trajectory) -> bool:
    """True when ``a`` and ``b`` ran one action sequence, up to sign (the mirrored hands' actions are negated)."""
    n = min(len(a), len(b))
    if n == 0 or n < SAME_SEQUENCE_OVERLAP * max(len(a), len(b)):
        return False
    head_a, head_b = a.actions[:n], b.actions[:n]
    return bool(np.array_equal(head_a, head_b) or np.array_equal(head_a, -head_b))


def split_by_fraction(
    data: TrajectorySet, fraction: float, seed: int
) -> tuple[TrajectorySet, TrajectorySet]:
    """Split whole episodes into ``(train, held_out)`` holding ``fraction`` of the transitions.

    Episodes are shuffled with ``seed`` and taken until the training part holds at
    least ``fraction`` of all transitions (never fewer than one episode, never all
    of them unless ``fraction`` is 1), so 0.3 % of a 300-episode set is one episode,
    as in the paper.
    """
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    if len(data) == 0:
        raise ValueError("cannot split an empty trajectory set")
    order = np.random.default_rng(seed).permutation(len(data))
    if fraction == 1.0:
        return data.subset(order), TrajectorySet((), hand=data.hand)
    target = fraction * data.num_transitions
    taken, count = [], 0
    for i in order:
        if count >= target and taken:
            break
        taken.append(int(i))
        count += len(data[int(i)])
    if len(taken) == len(data) > 1:
        taken.pop()
    chosen = set(taken)
    rest = [int(i) for i in order if int(i) not in chosen]
    return data.subset(taken), data.subset(rest)
