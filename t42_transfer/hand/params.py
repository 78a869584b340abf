"""Physical parameters of one simulated Model-T42 hand and its named variants.

Two 3D-printed copies of the T42 differ in spring stiffness, pad friction, tendon
routing, link lengths and in which servo drives which finger.  A variant is one
such copy: ``source``, ``target`` and ``target_abrupt`` are fixed, ``family-<seed>``
draws a reproducible copy around the nominal design.
"""

from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FingerParams:
    """One finger: two spring-loaded phalanges flexed by one tendon."""

    proximal_mm: float = 62.0
    distal_mm: float = 48.0
    k_proximal: float = 0.06
    """Proximal spring stiffness, N m / rad."""
    k_distal: float = 0.50
    """Distal spring stiffness, N m / rad (stiffer than proximal, as on the T42)."""
    r_proximal_mm: float = 8.0
    """Tendon moment arm at the proximal joint (routing ratio numerator)."""
    r_distal_mm: float = 3.0
    rest_deg: float = -8.0
    """Spring rest angle of the proximal joint; negative splays the finger outward."""


@dataclass(frozen=True)
class RegionChange:
    """Parameters that take other values while the object's centre is in one region of the workspace.

    The region is the half-plane ``x > threshold_mm`` (``axis="x"``) or ``y > threshold_mm``
    (``axis="y"``), with ``above=False`` for the other side, in the hand frame (mm).  Inside
    it, the listed frictions replace the hand's and the finger springs are scaled; ``None``
    keeps the hand's value.  MuJoCo has no position-dependent materials, so
    :class:`~t42_transfer.hand.sim.SimulatedHand` sets these model fields before every
    control step from where the object is; the dynamics jump where the object crosses.
    """

    axis: str = "x"
    threshold_mm: float = 10.0
    above: bool = True
    pad_friction: float | None = None
    link_friction: float | None = None
    k_proximal_scale: float = 1.0
    k_distal_scale: float = 1.0

    def __post_init__(self) -> None:
        if self.axis not in ("x", "y"):
            raise ValueError(f"region axis must be 'x' or 'y', got {self.axis!r}")

    def contains(self, xy_mm: np.ndarray) -> bool:
        """Whether an object centre ``(x, y)`` (mm, hand frame) lies in the region."""
        value = float(xy_mm[0 if self.axis == "x" else 1])
        return value > self.threshold_mm if self.above else value < self.threshold_mm


@dataclass(frozen=True)
class HandParams:
    """Everything that makes one hand copy behave as it does."""

    name: str = "nominal"
    left: FingerParams = FingerParams()
    right: FingerParams = FingerParams()
    base_half_width_mm: float = 33.0
    palm_height_mm: float = 30.0
    """Height of the palm block between the finger bases; the object can rest on it."""
    pad_friction: float = 1.16
    """Rubber pads on the distal phalanges (public simulator's value)."""
    link_friction: float = 0.35
    """Bare printed plastic on the proximal phalanges: friction jumps where contact moves."""
    joint_damping: float = 0.004
    """N m s / rad at each finger joint."""
    object_damping: float = 0.6
    """N s / m on the object's planar motion (air and pad hysteresis)."""
    object_radius_mm: float = 17.5
    object_mass_kg: float = 0.1
    tendon_stiffness: float = 4000.0
    """N / m: the tendon stretches a little under load."""
    spool_radius_mm: float = 20.0
    """Servo horn radius: tendon travel per servo radian, and tension -> torque for the load."""
    servo_time_constant_s: float = 0.04
    max_tension_n: float = 80.0
    tendon_friction_n: float = 0.0
    """Dry friction along each tendon's routing (N): a finger holds still until its tendon's change of tension
    passes it, a dead band after every change of move. 0 (the named hands): none."""
    joint_friction_nm: float = 0.0
    """Dry friction at each finger joint (N m; a flexure's hysteresis). 0 (the named hands): none."""
    actuator_order: tuple[int, int] = (0, 1)
    """Which finger (0 left, 1 right) action component 0 and 1 drive; (1, 0) mirrors the hand."""
    load_noise: float = 1.0
    """Std of the load reading noise, raw units (servo load readings are integers and jittery)."""
    position_noise_mm: float = 0.05
    """Std of the object-tracker noise on x, y."""
    region: RegionChange | None = None
    """Where, if anywhere, the hand's materials or springs differ abruptly (see :class:`RegionChange`)."""

    def __post_init__(self) -> None:
        for name in ("tendon_friction_n", "joint_friction_nm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, numbers.Real) and np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")

    def with_(self, **changes: object) -> HandParams:
        return dataclasses.replace(self, **changes)


def _source() -> HandParams:
    return HandParams(name="source")


def _target() -> HandParams:
    # A second print of the same design: stiffer, re-tensioned springs, rougher
    # pads, a tendon routed through different holes, slightly longer links,
    # and one finger printed with a softer flexure than the other.
    left = FingerParams(
        proximal_mm=65.0, distal_mm=50.0, k_proximal=0.085, k_distal=0.65, r_proximal_mm=6.5, r_distal_mm=4.0,
        rest_deg=-5.0,
    )
    right = FingerParams(
        proximal_mm=62.0, distal_mm=46.0, k_proximal=0.045, k_distal=0.42, r_proximal_mm=9.0, r_distal_mm=2.4,
        rest_deg=-10.0,
    )
    return HandParams(
        name="target", left=left, right=right, base_half_width_mm=34.0, pad_friction=1.6, link_friction=0.2,
        joint_damping=0.006, spool_radius_mm=18.0,
    )


ABRUPT_REGION = RegionChange(axis="x", threshold_mm=10.0, above=True, k_proximal_scale=2.5)
"""``target_abrupt``'s compliance jump: beyond x = 10 mm both proximal flexures are 2.5x stiffer."""


def _target_abrupt() -> HandParams:
    # The source hand everywhere but in one region: once the object centre is more than
    # 10 mm toward the right finger, the proximal flexures stiffen 2.5-fold, as when a bent
    # flexure comes up against a second band.  The fingers then push the object back, so
    # it chatters along x = 10 mm; one step from the same state differs by millimetres there
    # and not at all elsewhere.
    return HandParams(name="target_abrupt", region=ABRUPT_REGION)


def _family(seed: int) -> HandParams:
    """A reproducible copy: each parameter scattered around the nominal design."""
    rng = np.random.default_rng([0x742, seed])

    def scale(value: float, spread: float) -> float:
        return float(value * np.exp(rng.normal(0.0, spread)))

    def finger() -> FingerParams:
        f = FingerParams()
        return FingerParams(
            proximal_mm=scale(f.proximal_mm, 0.03), distal_mm=scale(f.distal_mm, 0.03),
            k_proximal=scale(f.k_proximal, 0.2), k_distal=scale(f.k_distal, 0.2),
            r_proximal_mm=scale(f.r_proximal_mm, 0.12), r_distal_mm=scale(f.r_distal_mm, 0.12),
            rest_deg=float(f.rest_deg + rng.normal(0.0, 3.0)),
        )

    base = HandParams()
    return HandParams(
        name=f"family-{seed}", left=finger(), right=finger(),
        base_half_width_mm=scale(base.base_half_width_mm, 0.03),
        pad_friction=scale(base.pad_friction, 0.15), link_friction=scale(base.link_friction, 0.3),
        joint_damping=scale(base.joint_damping, 0.2), spool_radius_mm=scale(base.spool_radius_mm, 0.05),
        actuator_order=(1, 0) if rng.random() < 0.5 else (0, 1),
    )


_NAMED = {"source": _source, "target": _target, "target_abrupt": _target_abrupt}
NAMED_VARIANTS = tuple(_NAMED)


def variant(name: str) -> HandParams:
    """Parameters of a named hand: ``source``, ``target``, ``target_abrupt`` or ``family-<seed>``."""
    if name in _NAMED:
        return _NAMED[name]()
    if name.startswith("family-"):
        try:
            seed = int(name.split("-", 1)[1])
        except ValueError:
            raise ValueError(f"bad variant {name!r}: family variants are named family-<integer seed>") from None
        return _family(seed)
    raise ValueError(f"unknown hand variant {name!r}; expected one of {NAMED_VARIANTS} or family-<seed>")
