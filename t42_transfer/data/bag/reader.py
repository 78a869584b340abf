"""Reading a bag whole: episodes (:func:`read_bag`), a summary (:func:`bag_info`), a check (:func:`verify_bag`).

Everything wrong with a bag is one :class:`BagError` line naming the bag and the problem; what was read
in place of a sound bag (a damaged file's prefix, a missing metadata.yaml) is a warning.
"""

from __future__ import annotations

import contextlib
import warnings
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from t42_transfer.conventions import ACTION_UNIT_RAD, checked_action_unit
from t42_transfer.data.bag.episodes import assemble_episodes, decode_streams, missing_hand_topics
from t42_transfer.data.bag.hand_topics import hand_topic_names
from t42_transfer.data.bag.metadata import EPISODES_KEY, UNIT_KEY, declared_unit, metadata_yaml
from t42_transfer.data.bag.storage import RawBag, load_raw, metadata_mismatches
from t42_transfer.data.errors import BagError
from t42_transfer.data.trajectory import TrajectorySet


def read_bag(path: str | Path, action_unit_rad: float | None = None) -> TrajectorySet:
    """Episodes recorded in a rosbag2 bag (MCAP or sqlite3, ours or a real ``ros2 bag record``'s).

    A bag holds the actuators' steps; its actions come in ``action_unit_rad`` (a model's unit: an action past
    ``ACTION_LIMIT`` in it refuses the bag, whose hand was driven in larger steps), by default in the unit the bag
    declares (:func:`bag_unit`).

    Every joint state is a state; the object pose with the nearest header stamp
    within half a control period gives its x, y; the applied action stamped
    within half a period gives its action.  A step that lost a message (a
    recording started or stopped mid-step, a message dropped under load) is left
    out and its episode split there, with one warning naming what was dropped.
    Stamp gaps of ``EPISODE_GAP_S`` or more separate episodes.  A shorter gap is
    a late step when the bag's ``hand/status`` says so (kept, its duration in
    ``step_ns``), else missing steps (the episode splits there, with a warning).
    An action on an episode's last state has no next state and is not a
    transition.  A driver's end status (``dropped``, ``lost_contact``,
    ``overload``) or ``reset`` gives the episode it names its ``end_reason``; the
    state the object fell or slipped into is left out.  Episodes shorter than
    ``MIN_EPISODE_STEPS`` are dropped with a warning.
    """
    bag = Path(path)
    asked = None if action_unit_rad is None else checked_action_unit(action_unit_rad)
    with refusals(bag):
        raw = load_raw(bag)
        _warn_loaded(bag, raw)
        unit = bag_unit(bag, raw) if asked is None else asked
        return assemble_episodes(bag, decode_streams(bag, raw, unit, checked=asked is not None), raw)


def declared_bag_unit(path: str | Path) -> float | None:
    """The action unit ``path`` declares, from its metadata.yaml (the storage's copy when there is none), or None
    (a recorder's bag): :func:`read_bag` reads it in the suite's then."""
    bag = Path(path)
    with refusals(bag):
        meta, _ = metadata_yaml(bag) if bag.is_dir() else (None, "")
        declared = declared_unit(meta.custom if meta is not None else load_raw(bag).custom)
        return None if declared is None else _checked_unit(bag, declared)


def bag_unit(bag: Path, raw: RawBag) -> float:
    """The action unit a bag's custom data declares (``write_bag`` does), else the suite's: a recorder's bag holds
    steps in whatever unit its hand was driven, which only the reader knows."""
    return _checked_unit(bag, declared_unit(raw.custom))


def _checked_unit(bag: Path, declared: float | None) -> float:
    try:
        return ACTION_UNIT_RAD if declared is None else checked_action_unit(declared)
    except ValueError as err:
        raise BagError(bag, f"custom_data {UNIT_KEY}: {err}") from None


def bag_info(path: str | Path) -> dict[str, Any]:
    """Summary for a CLI; episodes are counted as :func:`read_bag` (and so the transfer server) finds them.

    A bag without the hand's topics (an empty one, a ``ros2 bag record`` of other topics) is listed as
    ``ros2 bag info`` lists it, with ``no_hand_episodes`` saying what it lacks (None for a hand's bag):
    a summary names what is there, :func:`read_bag` refuses it.
    """
    bag = Path(path)
    with refusals(bag):
        raw = load_raw(bag)
        _warn_loaded(bag, raw)
        recorded = hand_topic_names(bag, raw.custom, raw.topics)
        missing = missing_hand_topics(raw, recorded)
        if not missing:
            data = assemble_episodes(bag, decode_streams(bag, raw, bag_unit(bag, raw)), raw)
            episodes, transitions, hand = len(data), data.num_transitions, data.hand
            late = sum(len(t.late_steps) for t in data)
            ends = dict(sorted(Counter(t.end_reason or "unknown" for t in data).items()))
        else:  # nothing to count
            episodes, transitions, late, ends, hand = 0, 0, 0, {}, None
    return {
        "path": str(bag),
        "storage": raw.storage,
        "ros_distro": raw.ros_distro,
        "start_ns": raw.start_ns,
        "duration_s": (raw.end_ns - raw.start_ns) / 1e9,
        "topics": {name: {"type": t.msgtype, "count": t.count} for name, t in sorted(raw.topics.items())},
        "hand_topics": recorded,
        "episodes": episodes,
        "transitions": transitions,
        "late_steps": late,
        "end_reasons": ends,
        "hand": hand,
        "no_hand_episodes": f"it has no {', '.join(missing)}" if missing else None,
        "metadata": {k: v for k, v in raw.custom.items() if k != EPISODES_KEY},
        "recovered_prefix": raw.cut,
    }


def verify_bag(path: str | Path) -> list[str]:
    """Where a bag directory's metadata.yaml disagrees with its data; empty when they agree.

    Checked: the storage files present against ``relative_file_paths``, each
    topic's message count, the total, the start time (first log time) and the
    duration (last minus first log time), all counted from the messages
    themselves; a damaged or missing file is reported too.  BagError for what is
    no bag directory or cannot be read at all.
    """
    bag = Path(path)
    with refusals(bag):
        raw = load_raw(bag)
        if raw.meta is None and not raw.problem:
            raise BagError(bag, "is a storage file, not a bag directory: it has no metadata.yaml to verify against")
        found = [raw.stopped] if raw.stopped else []
        if raw.meta is None:
            return [*found, f"{raw.problem}: nothing to verify the data against"]
        return [*found, *metadata_mismatches(bag, raw.meta, raw)]


@contextlib.contextmanager
def refusals(bag: Path) -> Iterator[None]:
    """Failures reading ``bag`` as one-line BagErrors.

    OS errors (permission denied, a directory where a file belongs...) become
    BagErrors naming the file; a problem quoting text with line breaks or other
    unprintable characters (a topic name from a damaged file) has them escaped.
    """
    try:
        yield
    except BagError as err:
        if err.problem.isprintable():
            raise
        raise BagError(err.path, _one_line(err.problem)) from None
    except FileExistsError:  # a refusal to overwrite, named as such
        raise
    except OSError as err:
        where = f": {err.filename}" if err.filename else ""
        raise BagError(bag, _one_line(f"{err.strerror or type(err).__name__}{where}")) from None


def _one_line(text: str) -> str:
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _warn_loaded(bag: Path, raw: RawBag) -> None:
    """Warn of what was read in place of a sound bag, and of each topic not decodable from it; BagError when damage
    left no hand message."""
    if raw.problem:
        warnings.warn(f"{bag}: {raw.problem}; read its storage files directly", stacklevel=3)
    if raw.stopped:
        if not any(raw.messages.values()):
            raise BagError(bag, f"{raw.stopped}; scanning its MCAP records recovered no hand messages")
        warnings.warn(
            f"{bag}: recovered the readable prefix, {sum(t.count for t in raw.topics.values())} messages up to "
            f"log time {raw.end_ns} ns; {raw.stopped}",
            stacklevel=3,
        )
    for line in raw.undecodable.values():  # (counted as any topic; the hand's decode with the project's types)
        warnings.warn(f"{bag}: {line}", stacklevel=3)
