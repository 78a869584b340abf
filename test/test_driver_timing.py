"""The drivers' step-timing rule against the bag reader's bounds."""

from __future__ import annotations

import pytest

from t42_transfer.conventions import CONTROL_PERIOD_NS, LATE_STEP_NS, MIN_STEP_NS
from t42_transfer.driver.timing import StepTiming, step_timing


@pytest.mark.parametrize("since_ns, rate, expected", [
    (None, 1.0, StepTiming.ON_TIME),  # the episode's first step
    (0, 1.0, StepTiming.TOO_SOON),  # the same stamp twice is not two steps
    (MIN_STEP_NS - 1, 1.0, StepTiming.TOO_SOON),
    (MIN_STEP_NS, 1.0, StepTiming.ON_TIME),
    (CONTROL_PERIOD_NS, 1.0, StepTiming.ON_TIME),
    (LATE_STEP_NS, 1.0, StepTiming.ON_TIME),
    (LATE_STEP_NS + 1, 1.0, StepTiming.LATE),
    (-CONTROL_PERIOD_NS, 1.0, StepTiming.TOO_SOON),  # a clock that went back
    (CONTROL_PERIOD_NS // 4, 4.0, StepTiming.ON_TIME),  # 4x real time: a period is 25 ms
    (CONTROL_PERIOD_NS // 2, 4.0, StepTiming.LATE),
    (MIN_STEP_NS // 4 - 1, 4.0, StepTiming.TOO_SOON),
])
def test_a_step_is_judged_by_its_stamp_against_the_readers_bounds(since_ns: int | None, rate: float,
                                                                   expected: StepTiming) -> None:
    assert step_timing(since_ns, rate) is expected
