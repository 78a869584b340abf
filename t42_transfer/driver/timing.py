"""Whether a step is taken, and whether it is late: one rule for every driver, judged on the stamps it publishes.

The bag reader splits an episode between two states stamped under half a control period apart, and between two
more than 1.5 periods apart unless the driver said ``late`` for the second (nothing was lost, the step just took
longer).  So a driver judges each step by its stamp against the last step's: too soon (a timer catching up after
a late tick) and it does not step; late and it steps and says so.  The stamp judged must be the one published:
a driver that judged its tick's time and stamped after the servo read split episodes whenever a read was held
up.  Nothing here needs ROS.
"""

from __future__ import annotations

from enum import Enum, auto

from t42_transfer.conventions import LATE_STEP_NS, MIN_STEP_NS


class StepTiming(Enum):
    ON_TIME = auto()
    LATE = auto()
    """Taken, and said ``late`` on ``hand/status`` with its stamp."""
    TOO_SOON = auto()
    """Not taken: the hand keeps its goals until the next tick."""


def step_timing(since_ns: int | None, rate_factor: float = 1.0) -> StepTiming:
    """How a step stamped ``since_ns`` after the last published one stands (None: the episode's first step).

    ``rate_factor``: the driver steps that many times faster than real time (its periods that much shorter)."""
    if since_ns is None:
        return StepTiming.ON_TIME
    if since_ns < MIN_STEP_NS / rate_factor:
        return StepTiming.TOO_SOON
    return StepTiming.LATE if since_ns > LATE_STEP_NS / rate_factor else StepTiming.ON_TIME
