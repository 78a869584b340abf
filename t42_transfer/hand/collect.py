"""Random-policy data collection on simulated hands, parallel across processes.

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

from t42_transfer.conventions import ACTION_DIM, MIN_EPISODE_STEPS, RANDOM_POLICY_LIMIT
from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.hand.sim import GraspFailed, SimulatedHand

DROP_REASONS = ("dropped", "lost_contact")

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
    states = [hand.reset(seed)]
    angles = [hand.actuator_angles]
    applied: list[np.ndarray] = []
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


def _episode_task(args: tuple[str, int, int, int, RandomPolicy]) -> Trajectory | None:
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
    policy: RandomPolicy = RandomPolicy(),
    progress: bool = True,
) -> tuple[TrajectorySet, CollectionStats]:
    """Collect ``episodes`` random-policy episodes of at most ``steps`` steps on ``hand``.

    Episodes shorter than ``MIN_EPISODE_STEPS`` are discarded (the paper's rule) and
    counted in the returned stats.
    """
    from tqdm.auto import tqdm

    check_collection(hand, episodes, steps, workers, policy.hold_max)
    workers = workers or os.cpu_count() or 1
    tasks = [(hand, seed, e, steps, policy) for e in range(episodes)]
    bar = tqdm(total=episodes, desc=f"collect {hand}", unit="ep", disable=not progress)
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
    bar.close()
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
