"""The demo's sizes (quick and full), the rule's tolerance, and the names of the suite it starts."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace
from typing import Any

from msg_adapters import names

HARDWARE = {
    "sim": ("mock_driver",),
    "emulated": ("hw_emulator", "dynamixel_driver"),
    "camera": ("mock_driver", "object_tracker"),
}
"""The hand's nodes per ``--hardware``: the mock driver's simulated hand; the Dynamixel driver on the
emulator's servo bus (the same simulated hand behind two XM430s on a pty, seen by an emulated tracker); or the
mock driver's hand seen by a camera: rendered frames, the object tracker on them, and the tracked pose as the
hand's (``pose_source: topic``)."""
DRIVER = {"sim": "mock_driver", "emulated": "dynamixel_driver", "camera": "mock_driver"}
SUITE_NODES = ("recorder", "transfer_server", "planner")
"""The suite's nodes after the hand's."""
POSE_SOURCE = {"sim": "the simulator (mock_driver)", "emulated": "the emulated tracker on tracker/object_pose",
               "camera": "the object tracker on the mock driver's rendered camera (tracker/object_pose)"}
CAMERA = {"camera_rate_hz": 10.0, "camera_width": 640, "camera_height": 480}
"""The rendered camera of ``--hardware camera``: a frame per step."""


def suite_nodes(hardware: str) -> tuple[str, ...]:
    """Every node process of the suite on ``hardware``, the hand's first."""
    return (*HARDWARE[hardware], *SUITE_NODES)


TRANSFER_STATUS = "t42_transfer: transfer"
"""The transfer server's status name on ``/diagnostics``."""
RECORDER_START = names.private_of("recorder", names.RECORDER_START)
RECORDER_STOP = names.private_of("recorder", names.RECORDER_STOP)
SERVICES = (names.HAND_RESET, RECORDER_START, RECORDER_STOP)
"""The Trigger services the demo calls; goals and transfers go to the actions ``t42/reach`` and ``t42/transfer``."""


@dataclass(frozen=True)
class DemoSize:
    source_episodes: int
    source_steps: int
    source_epochs: int
    target_episodes: int
    """Episodes the explorer collects from the target hand (a quarter is held out for scoring)."""
    target_steps: int
    goal_steps: tuple[int, ...]
    """One peg-in-hole goal per entry, that many control steps from the grasp."""
    rate_factor: float
    rounds: int = 2
    """Transfer-then-goals rounds; from the second on, the transfer also learns from the executed plans."""
    heldout_episodes: int = 6
    """Random-policy target episodes collected apart (never recorded by the suite) to score each round's model."""
    transfer: dict[str, Any] = field(default_factory=dict)
    """Overrides of the transfer server's TransferConfig (nested; written to the YAML file its ``config`` names)."""


FULL = DemoSize(source_episodes=80, source_steps=400, source_epochs=40, target_episodes=12, target_steps=150,
                goal_steps=(30, 40, 50, 60, 30, 40, 50, 60), rate_factor=5.0)
QUICK = DemoSize(source_episodes=10, source_steps=150, source_epochs=5, target_episodes=4, target_steps=60,
                 goal_steps=(30, 40), rate_factor=10.0, heldout_episodes=3,
                 transfer={"l2_finetune": {"train": {"epochs": 10}}})


def demo_size(quick: bool = False, rounds: int | None = None, goals: int | None = None) -> DemoSize:
    """:data:`QUICK` or :data:`FULL`, with ``rounds`` rounds and ``goals`` goals a round (None: the size's own),
    the goals' lengths cycling through the size's."""
    size = QUICK if quick else FULL
    steps = itertools.islice(itertools.cycle(size.goal_steps), goals or len(size.goal_steps))
    return replace(size, rounds=rounds or size.rounds, goal_steps=tuple(steps))


TOLERANCE_MM = 10.0
"""The paper's peg-in-hole tolerance."""
MIN_GOAL_DISTANCE_MM = 2 * TOLERANCE_MM
"""Goals lie at least this far from the start and from where holding still ends: doing nothing scores 0."""
HELDOUT_SEED = 99
HOLD_STEPS = (5, 40)
SETTLE_STEPS = 80
"""Steps of holding still after a grasp: the simulated object has stopped sinking by then."""
TRIES_PER_GRASP = 10
"""Action sequences tried from one settled grasp of a hand copy for a goal, before it grasps anew."""
GRASP_MATCH_MM = 1.0
