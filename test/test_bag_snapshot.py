"""data.bag.snapshot: the last S seconds of whole steps in a bounded ring, written as a bag read_bag reads, and the
rule for automatic snapshots on status words (no ROS)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import msg_adapters as ma
from msg_adapters import names
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.data.bag import read_bag
from t42_transfer.data.bag.snapshot import SnapshotBuffer, wants_snapshot, write_snapshot
from t42_transfer.data.bag.steps import Step

POSE, JOINTS, ACTION = ma.OBJECT_POSE_TOPIC, ma.JOINT_STATES_TOPIC, ma.APPLIED_ACTION_TOPIC
STATUS = ma.HAND_STATUS_TOPIC
STATE = (POSE, JOINTS)
T0 = 1_000_000_000_000


def _cdr(msg: object) -> bytes:
    return bytes(ma.TYPESTORE.serialize_cdr(msg, msg.__msgtype__))


def make_step(k: int, topics: tuple[str, ...] = (POSE, JOINTS, ACTION)) -> Step:
    """Step ``k`` (stamp T0 + k periods, logged 1 ms later); its numbers are k: they say which step they are."""
    stamp = T0 + k * CONTROL_PERIOD_NS
    msgs = {POSE: ma.object_pose_msg((k, -k), stamp), JOINTS: ma.joint_state_msg((k, 2 * k), (0.1, 0.2), stamp),
            ACTION: ma.applied_action_msg((0.5, -0.5), stamp)}
    return Step(stamp, 0.0, [(t, stamp + 1_000_000, _cdr(msgs[t])) for t in topics])


def status_cdr(text: str) -> bytes:
    return _cdr(ma.TYPESTORE.types[ma.STRING](data=text))


def test_the_buffer_holds_exactly_the_last_window_of_steps_and_the_bag_reads_them(tmp_path: Path) -> None:
    buf = SnapshotBuffer(2.0, 1 << 30)
    for k in range(50):  # 5 s of steps
        buf.add_step(make_step(k))
        if k == 44:
            done = ma.status_message(names.TRAJECTORY_DONE, "", T0 + 44 * CONTROL_PERIOD_NS)
            buf.add_loose(STATUS, T0 + 44 * CONTROL_PERIOD_NS + 2_000_000, status_cdr(done), ma.STRING)
        if k == 10:  # long gone when the snapshot is taken
            buf.add_loose(STATUS, T0 + 10 * CONTROL_PERIOD_NS + 2_000_000, status_cdr("reset: old"), ma.STRING)
    # (newest - 2 s, newest]: steps 30..49, not 29
    assert [s.stamp for s in buf.steps] == [T0 + k * CONTROL_PERIOD_NS for k in range(30, 50)]
    assert buf.forgotten_steps == 30 and len(buf.loose) == 1
    snap = buf.snapshot(STATE)
    assert buf.covered == T0 + 49 * CONTROL_PERIOD_NS and snap.messages == 61
    bag = tmp_path / "snapshot_000"
    count, first, last = write_snapshot(bag, ma.HAND_TOPICS, snap)
    logged = [T0 + k * CONTROL_PERIOD_NS + 1_000_000 for k in (30, 49)]
    assert (count, first, last) == (61, *logged)
    (episode,) = read_bag(bag)
    assert len(episode) == 19  # 20 states; the last action has no next state
    np.testing.assert_allclose(episode.states[:, 0], np.arange(30, 50), atol=1e-4)
    np.testing.assert_allclose(episode.states[:, 3], 2 * np.arange(30, 50), atol=1e-3)


def test_memory_is_bounded_by_the_window_and_the_byte_cap() -> None:
    step_bytes = sum(len(d) for _, _, d in make_step(0).messages)
    buf = SnapshotBuffer(3600.0, 5 * step_bytes)  # the cap binds first
    for k in range(2000):
        buf.add_step(make_step(k))
        assert buf.bytes <= 5 * step_bytes
    assert [s.stamp for s in buf.steps] == [T0 + k * CONTROL_PERIOD_NS for k in range(1995, 2000)]
    assert buf.forgotten_steps == 1995
    for i in range(1000):  # a status flood: the oldest go first, steps or not
        buf.add_loose(STATUS, T0 + 2000 * CONTROL_PERIOD_NS + i, status_cdr("late: x"), ma.STRING)
    assert buf.bytes <= 5 * step_bytes and not buf.steps
    buf.resize(0.2, 1 << 30)  # a narrower window forgets at once
    buf.clear()
    for k in range(10):
        buf.add_step(make_step(k))
    assert [s.stamp for s in buf.steps] == [T0 + k * CONTROL_PERIOD_NS for k in (8, 9)]
    with pytest.raises(ValueError, match="window_s"):
        SnapshotBuffer(0.0, 10)
    with pytest.raises(ValueError, match="max_bytes"):
        buf.resize(1.0, 0)


def test_a_snapshot_begins_with_a_whole_state_and_a_clock_restart_starts_over() -> None:
    buf = SnapshotBuffer(10.0, 1 << 30)
    buf.add_step(make_step(0, (ACTION,)))  # the state was received before the window began
    buf.add_step(make_step(1, (POSE, ACTION)))
    buf.add_loose(STATUS, T0 + CONTROL_PERIOD_NS, status_cdr("late: before the first whole step"), ma.STRING)
    for k in range(2, 6):
        buf.add_step(make_step(k))
    snap = buf.snapshot(STATE, until=T0 + 4 * CONTROL_PERIOD_NS)
    assert [s.stamp for s in snap.steps] == [T0 + k * CONTROL_PERIOD_NS for k in (2, 3, 4)] and snap.loose == []
    assert buf.covered == T0 + 4 * CONTROL_PERIOD_NS
    assert buf.snapshot(STATE, until=T0).steps == [] and buf.covered == T0 + 4 * CONTROL_PERIOD_NS
    buf.add_step(make_step(-100))  # stamped before what is held: the publisher's clock restarted
    assert [s.stamp for s in buf.steps] == [T0 - 100 * CONTROL_PERIOD_NS] and buf.forgotten_steps == 6


def test_automatic_snapshots_fire_on_the_listed_words_once_per_border() -> None:
    on = (names.DROPPED, names.RESET)
    border = T0 + 15 * CONTROL_PERIOD_NS
    assert wants_snapshot(names.DROPPED, border, on, waiting=[], covered=None)
    assert not wants_snapshot(names.LATE, border, on, waiting=[], covered=None)
    assert not wants_snapshot(names.OVERLOAD, border, on, waiting=[], covered=None)  # not listed
    assert not wants_snapshot(names.RESET, border, on, waiting=[border], covered=None)  # the drop's, still waiting
    assert not wants_snapshot(names.RESET, border, on, waiting=[], covered=border)  # the drop's, taken
    assert wants_snapshot(names.RESET, border + CONTROL_PERIOD_NS, on, waiting=[], covered=border)  # a new step
    assert wants_snapshot(names.RESET, None, on, waiting=[], covered=border)  # a driver that names no border
    assert not wants_snapshot(names.RESET, None, on, waiting=[border], covered=None)
    assert not wants_snapshot(names.DROPPED, border, (), waiting=[], covered=None)
