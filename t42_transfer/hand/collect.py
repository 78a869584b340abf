"""Data collection on simulated hands, parallel across processes.

Two policies (:data:`POLICIES`): ``random``, the paper's training data, and
``sustained``, test paths like the real hands' (long holds of the discrete moves).
Episode ``e`` of a run with seed ``s`` depends only on ``(s, e)`` (grasp jitter,
sensor noise and actions), so the data set is the same whatever the number of
worker processes.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from t42_transfer.conventions import (
    ACTION_DIM,
    DROP_REASONS,
    MIN_EPISODE_STEPS,
    RANDOM_POLICY_LIMIT,
    REAL_HAND_ACTIONS,
)
from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.hand.sim import GraspFailed, HandSnapshot, SimulatedHand

MAX_EPISODES = 100_000
MAX_STEPS = 100_000
MAX_TRANSITIONS = 10_000_000
"""Episodes x steps requested at most: 33x the paper's data set, a few GB of trajectories."""
MAX_WORKERS = 256
MAX_HOLD = 10_000


@dataclass(frozen=True)
class RandomPolicy:
    """Uniform actions in [-1, 1]^2, each held for 1..``hold_max`` steps.

    Holding an action lets the servos travel far enough to explore the whole
    workspace; ``hold_max=1`` gives i.i.d. actions per step.
    """

    hold_max: int = 5
    limit: float = RANDOM_POLICY_LIMIT

    def sample(self, rng: np.random.Generator, steps: int) -> np.ndarray:
        actions = np.empty((steps, ACTION_DIM))
        k = 0
        while k < steps:
            hold = int(rng.integers(1, self.hold_max + 1))
            actions[k : k + hold] = rng.uniform(-self.limit, self.limit, size=ACTION_DIM)
            k += hold
        return actions


REAL_PATH_MOVE_WEIGHTS = (4.0, 1.0, 5.5, 5.5, 1.0, 1.0, 1.0, 1.0)
"""How often the real test paths hold each of ``REAL_HAND_ACTIONS`` (same order): of their 20
holds, 11 move the fingers against each other, 4 move one finger, 3 close both and 2 open both (the weights
give those two 4 and 1, one hold off, as the stored sustained data sets were drawn)."""


@dataclass(frozen=True)
class SustainedPolicy:
    """Test paths like the real hands': one of their eight discrete moves held for a long time.

    Each hold picks a move other than the one just held, with probabilities in proportion
    to ``weights`` (by default the real paths' mix, :data:`REAL_PATH_MOVE_WEIGHTS`), for a
    length log-uniform in ``[hold_min, hold_max]`` steps (rounded down; the last hold is cut
    at the episode's end).  The defaults span the real paths' complete holds (120-700
    steps, quartiles about 200, 225 and 375-400); log-uniform keeps short holds common
    (quartiles about 185, 290 and 450).
    """

    hold_min: int = 120
    hold_max: int = 700
    weights: tuple[float, ...] = REAL_PATH_MOVE_WEIGHTS

    def __post_init__(self) -> None:
        if not (isinstance(self.hold_min, int) and isinstance(self.hold_max, int)
                and 1 <= self.hold_min <= self.hold_max <= MAX_HOLD):
            raise ValueError(f"need integers 1 <= hold_min <= hold_max <= {MAX_HOLD}, "
                             f"got {self.hold_min!r}, {self.hold_max!r}")
        w = np.asarray(self.weights, dtype=float)
        if w.shape != (len(REAL_HAND_ACTIONS),) or not np.all(np.isfinite(w)) or np.any(w < 0) or np.sum(w > 0) < 2:
            raise ValueError(f"weights must be {len(REAL_HAND_ACTIONS)} non-negative numbers, two or more positive, "
                             f"got {self.weights!r}")

    def sample(self, rng: np.random.Generator, steps: int) -> np.ndarray:
        moves = np.array(REAL_HAND_ACTIONS)
        actions = np.empty((steps, ACTION_DIM))
        k, last = 0, -1
        while k < steps:
            p = np.array(self.weights, dtype=float)
            if last >= 0:
                p[last] = 0.0  # a hold ends with a change of move
            move = int(rng.choice(len(moves), p=p / p.sum()))
            hold = int(np.exp(rng.uniform(np.log(self.hold_min), np.log(self.hold_max + 1))))
            actions[k : k + hold] = moves[move]
            k, last = k + hold, move
        return actions


Policy = RandomPolicy | SustainedPolicy
POLICIES: dict[str, type[Policy]] = {"random": RandomPolicy, "sustained": SustainedPolicy}
"""Collection policies by name, each with its default settings: ``POLICIES[name]()``."""


@dataclass(frozen=True)
class CollectionStats:
    requested: int
    kept: int
    too_short: int
    grasp_failed: int
    end_reasons: dict[str, int]


_HANDS: dict[str, SimulatedHand] = {}


def _hand(name: str) -> SimulatedHand:
    if name not in _HANDS:
        _HANDS[name] = SimulatedHand(name)
    return _HANDS[name]


def run_episode(hand: SimulatedHand, actions: np.ndarray, seed: int) -> Trajectory:
    """Execute ``actions`` open loop from a fresh grasp; stop early when the episode ends.

    A drop's last transition (the object falling) is not hand dynamics and is cut.
    """
    start = hand.reset(seed)
    return _run_on(hand, [start], [hand.actuator_angles], [], actions)


@dataclass(frozen=True)
class Settled:
    """A grasp held still for a while (:func:`settle`): its steps, and the hand's state after them."""

    prefix: Trajectory
    snapshot: HandSnapshot | None
    """None: the episode ended while the hand held still (every continuation is the prefix)."""


def settle(hand: SimulatedHand, seed: int, steps: int) -> Settled:
    """The grasp made with ``seed``, then ``steps`` of holding still (the object sinks into the fingers)."""
    prefix = run_episode(hand, np.zeros((steps, ACTION_DIM)), seed)
    return Settled(prefix, hand.snapshot() if len(prefix) == steps and not hand.done else None)


def run_settled(hand: SimulatedHand, settled: Settled, actions: np.ndarray) -> Trajectory:
    """Exactly ``run_episode(hand, [zeros(settle steps), actions], seed)``, from the settled snapshot: many
    continuations of one grasp pay for its settling once."""
    if settled.snapshot is None:
        return settled.prefix
    hand.restore(settled.snapshot)
    p = settled.prefix
    assert p.actuator_angles is not None
    return _run_on(hand, list(p.states), list(p.actuator_angles), list(p.actions), actions)


def _run_on(hand: SimulatedHand, states: list[np.ndarray], angles: list[np.ndarray], applied: list[np.ndarray],
            actions: np.ndarray) -> Trajectory:
    """Step ``hand`` through ``actions`` after the steps already in ``states``, ``angles`` and ``applied``."""
    for action in actions:
        info = hand.step_info(action)
        if info.end_reason in DROP_REASONS:
            break
        applied.append(np.asarray(action))
        states.append(hand.state)
        angles.append(hand.actuator_angles)
        if info.done:
            break
    end_reason = hand.end_reason or "length"
    return Trajectory(
        states=np.array(states),
        actions=np.array(applied).reshape(-1, ACTION_DIM),
        actuator_angles=np.array(angles),
        end_reason=end_reason,
        hand=hand.params.name,
    )


def _episode_task(args: tuple[str, int, int, int, Policy]) -> Trajectory | None:
    name, seed, episode, steps, policy = args
    episode_seed = int(np.random.SeedSequence([seed, episode]).generate_state(1)[0])
    rng = np.random.default_rng([seed, episode, 1])
    try:
        return run_episode(_hand(name), policy.sample(rng, steps), episode_seed)
    except GraspFailed:
        return None


def check_collection(hand: str, episodes: int, steps: int, workers: int | None = None, hold_max: int = 1) -> None:
    """ValueError for settings :func:`collect` cannot honour, before any work or allocation.

    Bounded so that a typo (``--episodes 1000000000``) is refused instead of filling memory.
    """
    from t42_transfer.hand.params import variant

    variant(hand)  # ValueError for an unknown name
    for name, value, high in (("episodes", episodes, MAX_EPISODES), ("steps", steps, MAX_STEPS),
                              ("hold_max", hold_max, MAX_HOLD)):
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= high:
            raise ValueError(f"{name} must be an integer from 1 to {high}, got {value!r}")
    if episodes * steps > MAX_TRANSITIONS:
        raise ValueError(f"{episodes} episodes x {steps} steps is over {MAX_TRANSITIONS} transitions")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)
                                or not 1 <= workers <= MAX_WORKERS):
        raise ValueError(f"workers must be an integer from 1 to {MAX_WORKERS} (or unset: all cores), got {workers!r}")


def collect(
    hand: str,
    episodes: int,
    steps: int,
    seed: int = 0,
    workers: int | None = None,
    policy: Policy = RandomPolicy(),
    progress: bool = True,
) -> tuple[TrajectorySet, CollectionStats]:
    """Collect ``episodes`` episodes of at most ``steps`` steps on ``hand`` under ``policy``.

    Episodes shorter than ``MIN_EPISODE_STEPS`` are discarded (the paper's rule) and
    counted in the returned stats.
    """
    from t42_transfer.progress import progress_bar

    check_collection(hand, episodes, steps, workers, policy.hold_max)
    workers = workers or os.cpu_count() or 1
    tasks = [(hand, seed, e, steps, policy) for e in range(episodes)]
    with progress_bar(total=episodes, desc=f"collect {hand}", unit="ep", disable=not progress) as bar:
        if workers == 1:
            results = []
            for task in tasks:
                results.append(_episode_task(task))
                bar.update()
        else:
            # fork: workers need nothing but this module, and scripts need no __main__ guard.
            methods = multiprocessing.get_all_start_methods()
            ctx = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
                results = []
                for result in pool.map(_episode_task, tasks, chunksize=max(1, episodes // (8 * workers))):
                    results.append(result)
                    bar.update()
    kept = [t for t in results if t is not None and len(t) >= MIN_EPISODE_STEPS]
    reasons: dict[str, int] = {}
    for t in results:
        if t is not None:
            reasons[t.end_reason] = reasons.get(t.end_reason, 0) + 1
    stats = CollectionStats(
        requested=episodes,
        kept=len(kept),
        too_short=sum(1 for t in results if t is not None and len(t) < MIN_EPISODE_STEPS),
        grasp_failed=sum(1 for t in results if t is None),
        end_reasons=reasons,
    )
    return TrajectorySet(kept, hand=hand), stats
