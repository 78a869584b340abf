"""A bag played back in time order: opened for reading, and the clock that paces it (no ROS).

Shared by the player node, ``t42 view --bag`` and its snapshots, so a bag is checked and refused the same way
wherever it is played.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from pathlib import Path

from t42_transfer.data.bag.db3 import BagReader
from t42_transfer.data.bag.storage import bag_files
from t42_transfer.data.errors import BagError


def open_bag(path: str | Path, purpose: str = "played") -> BagReader:
    """An open rosbags reader of ``path``, or BagError saying why it cannot be ``purpose`` ("played", "served"); a
    warning names each topic whose stored definition does not parse (it is opened as one stored without)."""
    bag = Path(path)
    storage = bag_files(bag)[0]  # before rosbags opens anything: a FIFO where a file belongs would block it forever
    try:
        reader = BagReader([bag])
        reader.open()
    except Exception as err:  # rosbags raises many types for what is not a sound bag
        hint = ("; an MCAP bag left by a killed recorder needs `t42 bag repair` first" if storage == "mcap" else
                "")
        raise BagError(bag, f"cannot be {purpose} ({type(err).__name__}: {err}){hint}") from None
    for line in reader.undecodable.values():
        warnings.warn(f"{bag}: {line}", stacklevel=2)
    return reader


class Timeline:
    """Bag time <-> steady time at a rate, with pause and rate changes; ``now_ns`` is injectable."""

    def __init__(self, start_bag_ns: int, rate: float, paused: bool = False,
                 now_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self._now = now_ns
        self._bag_ns = start_bag_ns
        """Bag time at steady time ``_at_ns`` (the anchor)."""
        self._at_ns = now_ns()
        self.rate = rate
        self.paused = paused

    def bag_now(self) -> int:
        """The bag time playing now."""
        if self.paused:
            return self._bag_ns
        return self._bag_ns + round((self._now() - self._at_ns) * self.rate)

    def due_ns(self, bag_ns: int) -> float:
        """Steady time at which bag time ``bag_ns`` plays (inf while paused)."""
        if self.paused:
            return math.inf
        return self._at_ns + (bag_ns - self._bag_ns) / self.rate

    def _anchor(self) -> None:
        self._bag_ns, self._at_ns = self.bag_now(), self._now()

    def set_rate(self, rate: float) -> None:
        self._anchor()
        self.rate = rate

    def pause(self) -> None:
        self._anchor()
        self.paused = True

    def resume(self) -> None:
        self._anchor()
        self.paused = False

    def restart(self, bag_ns: int, at_ns: float) -> None:
        """Play bag time ``bag_ns`` at steady time ``at_ns`` (a loop's next pass)."""
        self._bag_ns, self._at_ns = bag_ns, round(at_ns)
