"""The recorder's bag changes without ROS: each waits for the step in progress and for every change asked before it,
and comes due in order once the steps up to its border are written."""

from __future__ import annotations

from t42_transfer.nodes.recorder_changes import BagChanges, Change


def test_a_change_is_never_due_before_one_asked_earlier() -> None:
    changes = BagChanges()
    assert changes.add(Change("split", 100)).after == 100
    assert changes.add(Change("split", 50)).after == 100  # behind the first: waits for its border
    assert changes.add(Change("stop", None, "why", "word")) == Change("stop", 100, "why", "word")
    assert changes.add(Change("start", 300)).after == 300
    assert len(changes) == 4


def test_a_change_with_no_border_after_one_with_none_stays_without() -> None:
    changes = BagChanges()
    changes.add(Change("start", None))
    assert changes.add(Change("stop", None)).after is None


def test_changes_come_due_in_order_before_the_step_after_their_border() -> None:
    changes = BagChanges()
    for kind, after in (("split", 100), ("snapshot", 200), ("stop", 300)):
        changes.add(Change(kind, after))
    assert [c.kind for c in changes.due(100)] == []  # the step stamped 100 is not written yet
    assert [c.kind for c in changes.due(201)] == ["split", "snapshot"]
    assert len(changes) == 1 and changes.waiting("stop") == [300]
    assert [c.kind for c in changes.due(None)] == ["stop"] and len(changes) == 0


def test_a_change_without_a_border_is_due_at_once() -> None:
    changes = BagChanges()
    changes.add(Change("start", None))
    assert [c.kind for c in changes.due(0)] == ["start"]


def test_changes_are_taken_out_one_at_a_time_as_each_is_carried_out() -> None:
    changes = BagChanges()
    changes.add(Change("split", 1))
    changes.add(Change("split", 2))
    due = changes.due(None)
    next(due)
    assert len(changes) == 1


def test_will_record_follows_the_last_start_or_stop_asked() -> None:
    changes = BagChanges()
    assert not changes.will_record
    changes.add(Change("start", None))
    changes.add(Change("split", None))
    assert changes.will_record
    changes.add(Change("stop", None))
    assert not changes.will_record
    list(changes.due(None))
    assert not changes.will_record  # carrying them out changes nothing of it


def test_shutting_down_keeps_only_the_changes_that_open_no_bag() -> None:
    changes = BagChanges()
    for kind in ("start", "split", "episode", "snapshot", "stop"):
        changes.add(Change(kind, 5))
    changes.shutting_down()
    assert changes.waiting("episode") == []
    assert [c.kind for c in changes.due(None)] == ["snapshot", "stop"]
