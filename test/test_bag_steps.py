"""data.bag.steps: messages of interleaved topics become whole steps, released in stamp order."""

from __future__ import annotations

from t42_transfer.data.bag.steps import CLOCK_RESTART_NS, HOLD_CAP, StepBuffer, WrittenSteps


def test_step_buffer_releases_whole_steps_in_stamp_order() -> None:
    """Each topic delivers in stamp order; topics interleave in any order."""
    buf = StepBuffer(["p", "j", "a"], hold_s=1.0)
    assert buf.add("p", 10, 0, b"p10", 0.0) == ([], False)
    assert buf.add("p", 20, 0, b"p20", 0.0) == ([], False)
    assert buf.add("a", 10, 0, b"a10", 0.1) == ([], False)  # step 10 still lacks its joint states
    released, late = buf.add("j", 10, 0, b"j10", 0.2)
    assert not late and [(s.stamp, [m[2] for m in s.messages]) for s in released] == [(10, [b"p10", b"a10", b"j10"])]
    assert buf.add("j", 10, 0, b"again", 0.3) == ([], True)  # its step was released: too late
    assert buf.add("j", 20, 0, b"j20", 0.4) == ([], False)  # step 20 waits for an action
    assert buf.release(0.9) == []
    (final,) = buf.release(1.0)  # held hold_s (from its first message), and quiet: released without one
    assert final.stamp == 20 and final.topics == {"p", "j"}
    buf.add("p", 25, 0, b"p25", 1.0)
    buf.add("j", 25, 0, b"j25", 1.0)
    for k in range(1, 30):  # messages keep coming (a backlog, or a topic gone silent): step 25 waits ...
        assert buf.add("p", 25 + k, 0, b"p", 1.0 + k / 10) == ([], False)
    assert HOLD_CAP == 4
    released, _ = buf.add("p", 55, 0, b"p", 5.0)  # ... HOLD_CAP hold_s at most
    assert [s.stamp for s in released] == [25] and buf.oldest_pending == 26
    buf = StepBuffer(["p", "j", "a"], hold_s=1.0)
    buf.add("a", 30, 0, b"a30", 1.1)  # the state of step 30 is lost ...
    assert buf.add("p", 40, 0, b"p40", 1.1) == ([], False)
    released, _ = buf.add("j", 40, 0, b"j40", 1.1)  # ... which the later messages of both state topics prove
    assert [(s.stamp, s.topics) for s in released] == [(30, {"a"})]
    released, _ = buf.add("a", 40, 0, b"a40", 1.1)
    assert [(s.stamp, s.topics) for s in released] == [(40, {"p", "j", "a"})]
    assert buf.latest_stamp == 40 and buf.oldest_pending is None
    released, late = buf.add("p", 40 - 2 * CLOCK_RESTART_NS, 0, b"restart", 2.0)  # the publisher's clock restarted
    assert released == [] and not late and buf.released_stamp is None
    assert buf.oldest_pending == 40 - 2 * CLOCK_RESTART_NS


def test_a_duplicate_in_a_waiting_step_is_refused_and_the_first_stands() -> None:
    """Filed twice, a step would hold two joint states of one stamp, and the bag reader refuses the whole bag."""
    buf = StepBuffer(["p", "j"], hold_s=1.0)
    assert buf.add("p", 10, 0, b"p10", 0.0) == ([], False)
    assert buf.add("p", 10, 1, b"p10 again", 0.1) == ([], True)  # (the recorder drops it with a warning)
    (step,) = buf.add("j", 10, 0, b"j10", 0.2)[0]
    assert step.messages == [("p", 0, b"p10"), ("j", 0, b"j10")]


def test_a_message_just_older_than_the_released_step_is_late_not_a_clock_restart() -> None:
    buf = StepBuffer(["p"], hold_s=1.0)
    (step,) = buf.add("p", CLOCK_RESTART_NS, 0, b"p", 0.0)[0]
    assert buf.add("p", 1, 0, b"old", 0.1) == ([], True)  # within CLOCK_RESTART_NS of the newest: late
    assert buf.released_stamp == step.stamp


def test_a_step_missing_part_of_its_state_waits_out_a_stalled_publisher() -> None:
    """The soak's lost step: the driver published a step's pose, then stalled (a loaded machine) before its
    joint states and action. Silence alone must not write the pose on its own and drop the rest as late."""
    buf = StepBuffer(["p", "j", "a"], hold_s=1.0, required=["p", "j"])
    buf.add("p", 10, 0, b"p10", 0.0)
    assert buf.release(1.0) == [] and buf.release(3.9) == []  # silent for up to HOLD_CAP hold_s: still waiting
    assert buf.add("j", 10, 0, b"j10", 3.9) == ([], False)  # the driver runs again: nothing late
    (step,), late = buf.add("a", 10, 0, b"a10", 3.9)
    assert not late and step.topics == {"p", "j", "a"}
    buf.add("p", 20, 0, b"p20", 4.0)
    buf.add("j", 20, 0, b"j20", 4.0)
    (final,) = buf.release(5.0)  # the whole state, no action (an episode's final state): released on silence
    assert final.stamp == 20 and final.topics == {"p", "j"}
    buf.add("p", 30, 0, b"p30", 6.0)
    assert buf.release(6.0 + HOLD_CAP - 0.01) == []
    (given_up,) = buf.release(6.0 + HOLD_CAP)  # a state topic that went silent for good: HOLD_CAP hold_s at most
    assert given_up.topics == {"p"}
    buf.add("p", 40, 0, b"p40", 11.0)
    assert buf.add("a", 50, 0, b"a50", 11.1) == ([], False)
    released, _ = buf.add("j", 50, 0, b"j50", 11.1)  # the topics' next stamps prove j40 and a40 lost: no wait
    assert [(s.stamp, s.topics) for s in released] == [(40, {"p"})]


def test_a_late_message_joins_its_step_only_in_the_same_open_bag_and_once() -> None:
    buf = StepBuffer(["p", "j", "a"], hold_s=1.0)
    written = WrittenSteps(size=2)
    first_bag, second_bag = object(), object()
    buf.add("p", 10, 0, b"p10", 0.0)
    buf.add("j", 10, 0, b"j10", 0.0)
    (step,) = buf.release(2.0)  # held long enough, and quiet: written without its action
    written.add(step, first_bag)
    assert written.join(10, "a", first_bag)  # the action of a step written without it
    assert not written.join(10, "a", first_bag)  # a duplicate
    assert not written.join(10, "p", first_bag)  # the step has it
    assert not written.join(10, "j", second_bag)  # the step's bag is closed: another is open
    assert not written.join(11, "a", first_bag)  # no such step written
    for stamp in (20, 30):
        buf.add("p", stamp, 0, b"p", 3.0)
        (later,) = buf.release(10.0)
        written.add(later, first_bag)
    assert not written.join(10, "j", first_bag) and written.join(30, "a", first_bag)  # only the last `size` steps
