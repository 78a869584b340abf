"""Episodes from a bag's hand messages: align the three topics by header stamp, find borders, drop cut steps.

A bag holds, per control step ``k`` of an episode, an object pose, a joint state and (except after the
last state) the applied action, all stamped ``start_ns + k * CONTROL_PERIOD_NS``.  Episodes lie at least
``EPISODE_GAP_S`` apart, or a recorded ``reset`` status names the last state before a new grasp (a simulated
hand is grasped anew between two steps), so their borders come from stamps and statuses.  A step the driver
ran late is kept, with its real duration in the episode's ``step_ns``: the driver's ``late`` status in the bag
says no step is missing before it.  A driver's end status (``dropped``, ``lost_contact``, ``overload``) names an
episode's last state and gives the episode its end reason; a state it says the object fell into or slipped out of
is left out, as a simulated collection leaves it out (the fall is no transition of a hand holding the object).
Aligning by header stamp, not log time or order, also makes bags of a real
``ros2 bag record`` readable; the hand topics may lie under one namespace, found by suffix, or under the names
the recorder wrote down (``hand_topics.py``).  A step that lost
a message is left out with a warning naming it.
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import msg_adapters as ma
from msg_adapters import names
from t42_transfer.conventions import (
    ACTION_LIMIT,
    ACTION_UNIT_RAD,
    CONTROL_PERIOD_NS,
    DROP_REASONS,
    LATE_STEP_NS,
    MIN_EPISODE_STEPS,
    MIN_STEP_NS,
    checked_action_unit,
)
from t42_transfer.data.bag.hand_topics import hand_topic_names
from t42_transfer.data.bag.metadata import EPISODES_KEY, HAND_KEY
from t42_transfer.data.bag.storage import RawBag
from t42_transfer.data.errors import BagError
from t42_transfer.data.trajectory import END_REASONS, Trajectory, TrajectorySet

EPISODE_GAP_S = 1.0
"""A stamp gap at least this long separates episodes; a shorter one is a late step or lost steps."""
EPISODE_GAP_NS = round(EPISODE_GAP_S * 1e9)
_HALF_PERIOD_NS = CONTROL_PERIOD_NS // 2
_WITHIN = f"within {_HALF_PERIOD_NS / 1e6:g} ms"
_POSE, _JOINTS, _ACTION = ma.OBJECT_POSE_TOPIC, ma.JOINT_STATES_TOPIC, ma.APPLIED_ACTION_TOPIC
_CONVERTERS: dict[str, Callable[[Any], Any]] = {
    _POSE: ma.object_xy_mm,
    _JOINTS: ma.joint_state_arrays,
}


UNIT_SLACK = 1e-3
"""An action may pass ``ACTION_LIMIT`` by this share in the unit asked for: a unit written to three figures
(``same_action_unit``) reads the largest actions of the unit it stands for a little larger."""


def _action_in(unit_rad: float, checked: bool) -> Callable[[Any], np.ndarray]:
    """The applied action of a message in ``unit_rad``; with ``checked``, ValueError for one past ``ACTION_LIMIT``
    there: no hand driven in that unit steps so far, so the bag was recorded in a larger one."""
    unit = checked_action_unit(unit_rad)

    def convert(msg: Any) -> np.ndarray:
        action = ma.applied_action(msg, unit_rad=unit)
        largest = float(np.abs(action).max())
        if checked and largest > ACTION_LIMIT * (1 + UNIT_SLACK):
            raise ValueError(f"an action of {largest:.4g} in units of {unit:.4g} rad a step, past {ACTION_LIMIT:g}: "
                             f"the hand stepped {largest * unit:.3g} rad, further than one driven in that unit (read "
                             "the bag in the unit its hand was driven in: the explorer's action_unit_rad)")
        return action

    return convert


@dataclasses.dataclass
class _Stream:
    stamps: np.ndarray
    """Header stamps (int64 ns), strictly increasing."""
    values: list[Any]


def decode_streams(bag: Path, raw: RawBag, action_unit_rad: float = ACTION_UNIT_RAD,
                   checked: bool = False) -> dict[str, _Stream]:
    """Hand topics as header-stamped numpy values (actions in ``action_unit_rad``), checked for type, finiteness,
    order and, with ``checked`` (a unit the caller needs the actions in), range."""
    converters = {**_CONVERTERS, _ACTION: _action_in(action_unit_rad, checked)}
    recorded = hand_topic_names(bag, raw.custom, raw.topics)
    _check_topics(bag, raw, recorded)
    streams = {}
    for topic, msgtype in ma.HAND_TOPICS.items():
        stamps: list[int] = []
        values = []
        name = recorded[topic]
        for log_ns, data in raw.messages.get(name, []):
            try:
                msg = ma.TYPESTORE.deserialize_cdr(data, msgtype)
            except Exception as err:  # corrupt CDR raises whatever the decoder trips over
                raise BagError(bag, f"{name}: the message logged at {log_ns} ns cannot be decoded ({err})") from None
            stamp = ma.stamp_to_ns(msg.header.stamp)
            try:
                values.append(converters[topic](msg))
            except ValueError as err:
                raise BagError(bag, f"{name} at stamp {stamp} ns: {err}") from None
            if stamps and stamp <= stamps[-1]:
                raise BagError(
                    bag,
                    f"{name}: header stamps must increase, but {stamp} ns (logged at {log_ns} ns) "
                    f"follows {stamps[-1]} ns",
                )
            stamps.append(stamp)
        streams[topic] = _Stream(np.array(stamps, dtype=np.int64), values)
    return streams


def missing_hand_topics(raw: RawBag, recorded: dict[str, str]) -> list[str]:
    """The hand's step topics (with their types) ``raw`` lacks under their ``recorded`` names: why it holds no
    episodes.

    Such a bag is readable (``bag info`` lists it, as ``ros2 bag info`` does); :func:`decode_streams` refuses it.
    """
    return [f"{recorded[topic]} ({msgtype})" for topic, msgtype in ma.HAND_TOPICS.items()
            if recorded[topic] not in raw.topics]


def _check_topics(bag: Path, raw: RawBag, recorded: dict[str, str]) -> None:
    topics = raw.topics
    missing = missing_hand_topics(raw, recorded)
    if missing:
        present = ", ".join(f"{name} ({t.msgtype})" for name, t in sorted(topics.items())) or "no topics"
        raise BagError(bag, f"required topic {missing[0]} is missing; the bag has {present}")
    for hand, expected in ma.HAND_TOPICS.items():
        topic = recorded[hand]
        info = topics[topic]
        if info.msgtype != expected:
            raise BagError(bag, f"topic {topic} has type {info.msgtype}, expected {expected}")
        jazzy = ma.TYPESTORE.hash_rihs01(expected)
        if info.digest and info.digest != jazzy:
            raise BagError(
                bag, f"topic {topic} declares {expected} with type hash {info.digest}, not ROS 2 Jazzy's {jazzy}"
            )


def _nearest(stamps: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the stamp nearest each target, and whether it lies within half a control period."""
    if len(stamps) == 0:
        return np.zeros(len(targets), np.int64), np.zeros(len(targets), bool)
    right = np.searchsorted(stamps, targets).clip(0, len(stamps) - 1)
    left = (right - 1).clip(0, len(stamps) - 1)
    pick = np.where(np.abs(stamps[right] - targets) < np.abs(stamps[left] - targets), right, left)
    return pick, np.abs(stamps[pick] - targets) < _HALF_PERIOD_NS


def _drop_cut_tail(streams: dict[str, _Stream]) -> None:
    """In a recovered prefix the last step may be cut after any of its messages; that step is cut, not lost."""
    poses, joints = streams[_POSE], streams[_JOINTS]
    last_pose = poses.stamps[-1] if len(poses.stamps) else -1
    keep = int(np.searchsorted(joints.stamps, last_pose + _HALF_PERIOD_NS))
    streams[_JOINTS] = _Stream(joints.stamps[:keep], joints.values[:keep])
    last_state = joints.stamps[keep - 1] if keep else -1
    for topic in (_POSE, _ACTION):
        cut = streams[topic]
        keep = int(np.searchsorted(cut.stamps, last_state + _HALF_PERIOD_NS))
        streams[topic] = _Stream(cut.stamps[:keep], cut.values[:keep])


def _any_between(stamps: np.ndarray, after: int, before: int) -> bool:
    """Whether a stamp lies strictly between ``after`` and ``before``."""
    return bool(np.searchsorted(stamps, after, "right") < np.searchsorted(stamps, before, "left"))


def status_texts(bag: Path, raw: RawBag) -> list[str]:
    """The bag's ``hand/status`` messages, if it recorded them (the driver's late steps and resets are there)."""
    topic = hand_topic_names(bag, raw.custom, raw.topics)[ma.HAND_STATUS_TOPIC]
    info = raw.topics.get(topic)
    if info is None:
        return []
    if info.msgtype != ma.STRING:
        raise BagError(bag, f"topic {topic} (the hand's status) has type {info.msgtype}, expected {ma.STRING}")
    texts = []
    for log_ns, data in raw.messages.get(topic, []):
        try:
            texts.append(str(ma.TYPESTORE.deserialize_cdr(data, ma.STRING).data))
        except Exception as err:  # corrupt CDR raises whatever the decoder trips over
            raise BagError(bag, f"{topic}: the message logged at {log_ns} ns cannot be decoded ({err})") from None
    return texts


def _episode_bounds(bag: Path, streams: dict[str, _Stream], late: set[int]) -> list[tuple[int, int]]:
    """``(first, last)`` state indices of each run of states that follow each other as steps.

    A step more than ``LATE_STEP_NS`` after the one before is kept when the driver said it was late (a stall,
    a jittery bus: nothing is missing, the step just took longer).  Otherwise states are missing there and
    the episode splits: states whose poses or actions were left behind were lost (the salvage drops those
    messages), and a hole with no hand message at all is named in a warning.  Two states closer than
    ``MIN_STEP_NS`` are not one step apart either: the episode splits between them, with a warning.
    """
    stamps = streams[_JOINTS].stamps
    if len(stamps) == 0:
        return []
    cuts = []
    steps = np.diff(stamps)
    for i in np.flatnonzero((steps < MIN_STEP_NS) | (steps > LATE_STEP_NS)):
        step, before, after = int(steps[i]), int(stamps[i]), int(stamps[i + 1])
        if step >= EPISODE_GAP_NS:
            cuts.append(i + 1)
            continue
        if step < MIN_STEP_NS:
            why = f"less than half the {CONTROL_PERIOD_NS / 1e6:g} ms control period"
        elif any(_any_between(streams[t].stamps, before + _HALF_PERIOD_NS, after - _HALF_PERIOD_NS)
                 for t in (_POSE, _ACTION)):
            cuts.append(i + 1)  # lost states: their left-behind messages are named among the dropped
            continue
        elif after in late:
            continue
        else:
            why = f"with no hand message between and no {names.LATE!r} status for the step after: steps are missing"
        warnings.warn(f"{bag}: {_JOINTS} stamps {before} and {after} ns are {step / 1e6:g} ms apart, {why}; "
                      "split the episode there", stacklevel=4)
        cuts.append(i + 1)
    starts = [0, *cuts]
    ends = [c - 1 for c in cuts] + [len(stamps) - 1]
    return list(zip(starts, ends, strict=True))


def _complete_runs(posed: np.ndarray, acted: np.ndarray) -> list[tuple[int, int]]:
    """``(first, last)`` runs of states with a pose in which every state but the last has an action."""
    runs, start = [], None
    for k in range(len(posed)):
        if not posed[k]:
            if start is not None:
                runs.append((start, k - 1))
            start = None
            continue
        start = k if start is None else start
        if not acted[k] and k < len(posed) - 1:
            runs.append((start, k))
            start = None
    if start is not None:
        runs.append((start, len(posed) - 1))
    return runs


def _dropped(what: str, stamps: np.ndarray) -> list[str]:
    """``[what was dropped, with its first stamps]``, or ``[]`` when nothing was."""
    if not len(stamps):
        return []
    shown = ", ".join(str(s) for s in stamps[:3].tolist()) + (", ..." if len(stamps) > 3 else "")
    return [f"{what}: {len(stamps)} (stamp{'s' if len(stamps) > 1 else ''} {shown} ns)"]


def _episode_records(bag: Path, custom: dict[str, str]) -> dict[int, dict[str, Any]]:
    """The writer's per-episode facts by start stamp."""
    if EPISODES_KEY not in custom:
        return {}
    try:
        records = json.loads(custom[EPISODES_KEY])
        by_start = {}
        for r in records:
            if not (
                isinstance(r["start_ns"], int)
                and isinstance(r["transitions"], int)
                and r["end_reason"] in END_REASONS
                and isinstance(r["hand"], str)
            ):
                raise ValueError(f"bad entry {r!r}")
            by_start[r["start_ns"]] = r
    except (ValueError, TypeError, KeyError, RecursionError) as err:
        raise BagError(bag, f"custom_data {EPISODES_KEY} is malformed ({type(err).__name__}: {err})") from None
    return by_start


def assemble_episodes(bag: Path, streams: dict[str, _Stream], raw: RawBag) -> TrajectorySet:
    """Episodes of whole steps; a step missing a message is dropped (and named in one warning)."""
    if raw.cut:
        _drop_cut_tail(streams)
    poses, joints, actions = streams[_POSE], streams[_JOINTS], streams[_ACTION]
    hand = raw.custom.get(HAND_KEY, "")
    pose_of, has_pose = _nearest(poses.stamps, joints.stamps)
    state_of, has_state = _nearest(joints.stamps, actions.stamps)
    acting = np.flatnonzero(has_state)
    taken, counts = np.unique(state_of[acting], return_counts=True)
    if (counts > 1).any():
        stamp = joints.stamps[taken[np.argmax(counts > 1)]]
        raise BagError(bag, f"several {_ACTION} messages match the state at stamp {stamp} ns")
    action_of = np.full(len(joints.stamps), -1)
    action_of[state_of[acting]] = acting
    posed = np.zeros(len(poses.stamps), bool)
    posed[pose_of[has_pose]] = True
    dropped = [
        *_dropped(f"{_ACTION} messages with no {_JOINTS} {_WITHIN}", actions.stamps[~has_state]),
        *_dropped(f"{_POSE} messages with no {_JOINTS} {_WITHIN}", poses.stamps[~posed]),
        *_dropped(f"{_JOINTS} messages with no {_POSE} {_WITHIN}, with their actions", joints.stamps[~has_pose]),
    ]
    records = _episode_records(bag, raw.custom)
    texts = status_texts(bag, raw)
    # A reset names the last state of the grasp before it: the hand was grasped anew after it, so the action
    # published from that state leads to no recorded state (a simulated hand's next step is the new grasp's first).
    reset_stamps = dict.fromkeys(ma.event_stamps(texts, names.RESET), names.RESET)
    reset = _state_at(joints.stamps, set(reset_stamps))
    action_of[reset] = -1
    end_stamps = _end_stamps(texts)
    ended = _ended_states(joints.stamps, end_stamps)
    action_of[list(ended)] = -1  # the driver stopped there: no transition leaves an episode's end
    borders = np.union1d(reset, list(ended))
    episodes = []
    for first, last in _episode_bounds(bag, streams, ma.late_step_stamps(texts)):
        inner = first + np.flatnonzero(has_pose[first:last] & (action_of[first:last] < 0))
        inner = inner[~np.isin(inner, borders)]
        lacking = f"the transitions from {_JOINTS} messages with no {_ACTION} {_WITHIN}"
        dropped += _dropped(lacking, joints.stamps[inner])
        for a, b in _complete_runs(has_pose[first : last + 1], action_of[first : last + 1] >= 0):
            end_reason = ended.get(first + b, "")
            if end_reason in DROP_REASONS:
                if a == b:
                    continue  # the fall alone: nothing of the episode was in this run
                b -= 1  # the state the driver saw the object fall into: no state of a hand holding it
            elif not end_reason and first + b in reset:
                end_reason = names.RESET
            elif not end_reason:  # the step after ended it, or was the grasp's last, but lost a message or its pose
                end_reason = _next_end(joints.stamps[first + b], end_stamps) or _next_end(
                    joints.stamps[first + b], reset_stamps)
            start, steps = int(joints.stamps[first + a]), b - a
            if steps < MIN_EPISODE_STEPS:
                warnings.warn(
                    f"{bag}: dropped the episode starting at {start} ns: {steps} transitions, "
                    f"fewer than MIN_EPISODE_STEPS = {MIN_EPISODE_STEPS}",
                    stacklevel=3,
                )
                continue
            episodes.append(_episode(bag, streams, first + a, first + b, pose_of, action_of, records.get(start), hand,
                                     end_reason))
    if dropped:
        warnings.warn(f"{bag}: kept the whole steps only; dropped {'; '.join(dropped)}", stacklevel=3)
    if raw.cut and not episodes:
        raise BagError(bag, "its readable prefix holds no complete episode")
    return TrajectorySet(episodes, hand=hand)


_END_PRECEDENCE = names.END_EVENTS
"""Which end word a state named by several gets, in ``END_EVENTS``' order: a fall first (its state is left out),
then an overload."""


def _end_stamps(texts: list[str]) -> dict[int, str]:
    """The stamps the driver's end statuses name (``dropped``, ``lost_contact``, ``overload``), with the word."""
    found: dict[int, str] = {}
    for event in _END_PRECEDENCE:
        for stamp in sorted(ma.event_stamps(texts, event)):
            found.setdefault(stamp, event)
    return found


def _ended_states(stamps: np.ndarray, end_stamps: dict[int, str]) -> dict[int, str]:
    """The states the end statuses name, with the word (:data:`_END_PRECEDENCE` for a state named twice)."""
    found: dict[int, str] = {}
    for stamp, event in sorted(end_stamps.items(), key=lambda item: _END_PRECEDENCE.index(item[1])):
        for k in _state_at(stamps, {stamp}):
            found.setdefault(int(k), event)
    return found


def _next_end(stamp: int, end_stamps: dict[int, str]) -> str:
    """The word of a status in ``end_stamps`` naming the step right after ``stamp`` (within a late step's time),
    or ""."""
    after = [s for s in end_stamps if stamp + _HALF_PERIOD_NS < s <= stamp + LATE_STEP_NS]
    return end_stamps[min(after)] if after else ""


def _state_at(stamps: np.ndarray, wanted: set[int]) -> np.ndarray:
    """Indices of the states stamped (within half a control period) at the ``wanted`` stamps."""
    if not wanted:
        return np.zeros(0, np.int64)
    pick, near = _nearest(stamps, np.array(sorted(wanted), np.int64))
    return pick[near]


def _episode(
    bag: Path, streams: dict[str, _Stream], first: int, last: int, pose_of: np.ndarray, action_of: np.ndarray,
    record: dict[str, Any] | None, hand: str, end_reason: str,
) -> Trajectory:
    """States ``first..last`` of the joint states with their poses and actions; the writer's record if it has one,
    else ``end_reason`` (from the driver's status)."""
    poses, joints, actions = streams[_POSE], streams[_JOINTS], streams[_ACTION]
    complete = record is not None and record["transitions"] == last - first
    steps = np.diff(joints.stamps[first : last + 1])
    return Trajectory(
        states=np.column_stack(
            [
                np.stack([poses.values[pose_of[k]] for k in range(first, last + 1)]),
                np.stack([joints.values[k][0] for k in range(first, last + 1)]),
            ]
        ),
        actions=np.stack([actions.values[action_of[k]] for k in range(first, last)]),
        actuator_angles=_angles(bag, joints, first, last),
        start_ns=int(joints.stamps[first]),
        end_reason=record["end_reason"] if complete else end_reason,
        hand=record["hand"] if record is not None else hand,
        step_ns=None if (steps == CONTROL_PERIOD_NS).all() else steps,
    )


def _angles(bag: Path, joints: _Stream, first: int, last: int) -> np.ndarray | None:
    """Actuator angles of an episode: all there, or none (the real hands do not report them)."""
    angles = [joints.values[k][1] for k in range(first, last + 1)]
    if all(a is None for a in angles):
        return None
    if any(a is None for a in angles):
        missing = joints.stamps[first + next(i for i, a in enumerate(angles) if a is None)]
        raise BagError(bag, f"{_JOINTS} at stamp {missing} ns has no positions while others in its episode do")
    return np.stack(angles)
