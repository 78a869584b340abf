"""The trained workspace: where the planner may trust a model's prediction.

A learned model extrapolates badly outside its training states, so a plan whose
prediction leaves them is not a plan but a guess.  The object positions are
bounded by a k-DOP: for ``D`` directions ``n_j`` at angles ``j * pi / D`` the
projection ``n_j . (x, y)`` must lie within the training states' range, widened
by a margin.  With ``D = 2`` this is the min/max box of x and y; the default
``D = 8`` is a 16-sided polygon hugging the convex hull of the training states,
so it cuts the box's empty corners but stays nearly as cheap to test as a box
and as easy to store (2 D numbers).  Loads are bounded by ``load_limit``
(default the overload limit, past which the hand itself stops); one product
``[D + 2, 4] @ [4, N]`` tests all bounds of N states at once.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from t42_transfer.conventions import OVERLOAD_LOAD
from t42_transfer.data.trajectory import Trajectory

DIRECTIONS = 8
MARGIN_MM = 5.0
"""Default widening: about the distance the object moves in 5-10 control steps."""


def _normals(directions: int) -> np.ndarray:
    angles = np.arange(directions) * math.pi / directions
    return np.stack([np.cos(angles), np.sin(angles)], axis=1)


MAX_DIRECTIONS = 360
"""More bounding directions than any workspace needs (the trained ones use a few dozen); caps stored ones."""


@dataclass(frozen=True)
class Workspace:
    """Bounds ``lower[j] <= n_j . (x, y) <= upper[j]`` (margin included) and ``|load| <= load_limit``.

    The number of directions D is even, so the x and y axes (j = 0 and D / 2) are among them.
    """

    lower: np.ndarray
    upper: np.ndarray
    load_limit: float = OVERLOAD_LOAD

    def __post_init__(self) -> None:
        lower, upper = (np.asarray(v, dtype=np.float64).reshape(-1) for v in (self.lower, self.upper))
        if len(lower) < 2 or len(lower) % 2 or lower.shape != upper.shape:
            raise ValueError(
                f"need matching lower/upper bounds for an even number of directions, got {lower.shape}, {upper.shape}"
            )
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)) and np.all(lower <= upper)):
            raise ValueError("workspace bounds must be finite with lower <= upper")
        if not self.load_limit > 0:
            raise ValueError(f"load_limit must be positive, got {self.load_limit}")
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)

    # ----------------------------------------------------------------- building
    @classmethod
    def from_states(
        cls,
        states: np.ndarray,
        margin_mm: float = MARGIN_MM,
        directions: int = DIRECTIONS,
        load_limit: float = OVERLOAD_LOAD,
    ) -> Workspace:
        """The k-DOP of ``states[:, :2]`` (any state layout starting with x, y) widened by ``margin_mm``."""
        xy = np.asarray(states, dtype=np.float64)[:, :2]
        if len(xy) == 0 or not np.all(np.isfinite(xy)):
            raise ValueError("need at least one finite state to define a workspace")
        proj = xy @ _normals(directions).T
        return cls(proj.min(0) - margin_mm, proj.max(0) + margin_mm, load_limit)

    @classmethod
    def from_trajectories(cls, trajectories: Iterable[Trajectory], **kwargs: Any) -> Workspace:
        """The workspace of every state of ``trajectories`` (a TrajectorySet, or several chained)."""
        states = [t.states for t in trajectories]
        if not states:
            raise ValueError("no trajectories to define a workspace")
        return cls.from_states(np.concatenate(states), **kwargs)

    @classmethod
    def box(
        cls, x_min: float, x_max: float, y_min: float, y_max: float, load_limit: float = OVERLOAD_LOAD
    ) -> Workspace:
        """An axis-aligned box (the ``D = 2`` k-DOP), margin included."""
        return cls(np.array([x_min, y_min]), np.array([x_max, y_max]), load_limit)

    # ---------------------------------------------------------------- storing
    def to_dict(self) -> dict[str, Any]:
        """JSON-able form, e.g. for ``save_model(..., extra={"workspace": ws.to_dict()})``."""
        return {"lower": self.lower.tolist(), "upper": self.upper.tolist(), "load_limit": self.load_limit}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Workspace:
        """The workspace of :meth:`to_dict`'s form; ValueError (one line) for anything else, as files carry it."""
        if not isinstance(data, Mapping):
            raise ValueError(f"a stored workspace must be an object, got {type(data).__name__}")
        bounds = []
        for key in ("lower", "upper"):
            value = data.get(key)
            if not (isinstance(value, list) and 2 <= len(value) <= MAX_DIRECTIONS
                    and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
                raise ValueError(f"a stored workspace's {key!r} must be a list of 2 to {MAX_DIRECTIONS} numbers")
            bounds.append(np.asarray(value, dtype=np.float64))
        limit = data.get("load_limit", OVERLOAD_LOAD)
        if not isinstance(limit, (int, float)) or isinstance(limit, bool):
            raise ValueError(f"a stored workspace's load_limit must be a number, got {limit!r:.40}")
        return cls(bounds[0], bounds[1], float(limit))

    @classmethod
    def from_metadata(cls, metadata: Mapping[str, Any], file: str | Path | None = None) -> Workspace | None:
        """The workspace a model file stores under ``extra.workspace``, or None; ValueError if it is malformed,
        naming ``file`` (the model's) when given."""
        extra = metadata.get("extra") or {}
        stored = extra.get("workspace") if isinstance(extra, Mapping) else None
        try:
            return None if stored is None else cls.from_dict(stored)
        except ValueError as err:
            if file is None:
                raise
            raise ValueError(f"{file}: {err}") from None

    @classmethod
    def for_planning(
        cls, bags: Sequence[str | Path] | None, metadata: Mapping[str, Any], model: str | Path
    ) -> Workspace:
        """The workspace of the states in ``bags`` when given, else the one ``model``'s file stores (``metadata``).

        ValueError (one line) when neither: no default box can know where a model was trained."""
        if bags:
            from t42_transfer.data.bag import read_bag

            return cls.from_trajectories(t for bag in bags for t in read_bag(bag))
        stored = cls.from_metadata(metadata, model)
        if stored is None:
            raise ValueError(f"{model} stores no workspace: pass --workspace BAG ... (the model's training data)")
        return stored

    # ---------------------------------------------------------------- testing
    @property
    def directions(self) -> int:
        return len(self.lower)

    def bounds(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` of the enclosing box (an even D includes the x and y directions)."""
        y = self.directions // 2
        return float(self.lower[0]), float(self.upper[0]), float(self.lower[y]), float(self.upper[y])

    @cached_property
    def _scaled_bounds(self) -> tuple[Tensor, Tensor]:
        """Rows ``[D + 2, 4]`` and offsets ``[D + 2, 1]`` with every bound as ``|row . s - offset| <= 1``."""
        centre, half = (self.upper + self.lower) / 2, np.maximum((self.upper - self.lower) / 2, 1e-9)
        rows = np.zeros((self.directions + 2, 4))
        rows[: self.directions, :2] = _normals(self.directions) / half[:, None]
        rows[self.directions :, 2:] = np.eye(2) / self.load_limit
        offset = np.concatenate([centre / half, [0.0, 0.0]])[:, None]
        return torch.as_tensor(rows, dtype=torch.float32), torch.as_tensor(offset, dtype=torch.float32)

    def allows(self, states: Tensor) -> Tensor:
        """Whether each state ``states[..., 4]`` is inside and within the load limit (False for NaN/inf).

        One product ``[D + 2, 4] @ [4, N]`` tests the D directions and the two loads;
        the reduction over bounds then runs along contiguous rows.
        """
        rows, offset = (t.to(states.dtype) for t in self._scaled_bounds)
        scaled = torch.mm(rows, states.reshape(-1, 4).T).sub_(offset).abs_()
        return (scaled.amax(0) <= 1.0).reshape(states.shape[:-1])

    def describe_xy(self) -> str:
        """The x and y extent (mm), for a message: the polygon lies within it (its other sides cut corners)."""
        x_min, x_max, y_min, y_max = self.bounds()
        return f"x {x_min:.1f} to {x_max:.1f} mm, y {y_min:.1f} to {y_max:.1f} mm at most"

    def contains_xy(self, xy: Tensor) -> Tensor:
        """Whether each point ``xy[..., 2]`` lies inside, loads aside (False for NaN/inf)."""
        return self.allows(torch.cat([xy, torch.zeros_like(xy)], dim=-1))

    def loads_ok(self, states: Tensor) -> Tensor:
        """Whether both loads of each state ``states[..., 4]`` are within the limit (False for NaN)."""
        return (states[..., 2:].abs() <= self.load_limit).all(-1)
