"""A simulated Model-T42 hand with the real hand's step interface.

``reset(seed)`` places the object between open fingers and runs the grasp
routine (close each servo until its load passes ``GRASP_LOAD``); ``step(action)``
turns each servo by ``action * ACTION_UNIT_RAD`` and simulates 0.1 s.  The state
is what the real hand publishes: object x, y (mm, hand frame: x across the palm,
y away from it) and the two servo loads in raw units, signed like the real
servos (load1 > 0, load2 < 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from t42_transfer.conventions import (
    ACTION_DIM,
    ACTION_LIMIT,
    ACTION_UNIT_RAD,
    CONTROL_PERIOD_S,
    DROP_JUMP_MM,
    DROPPED,
    GRASP_LOAD,
    LOAD_UNIT_NM,
    LOST_CONTACT,
    OVERLOAD,
    OVERLOAD_LOAD,
)
from t42_transfer.hand.mjcf import FINGER_SIDES, TIMESTEP_S, hand_mjcf
from t42_transfer.hand.params import HandParams, variant

SERVO_MAX_RAD = 4.0
"""Servo travel; moves beyond it are refused, as the real driver refused them."""
LOAD_GUARD = 0.9 * OVERLOAD_LOAD
"""Like the real driver, refuse a tightening move of a servo whose |load| is above this."""
GRASP_INCREMENT = 0.5
"""Action size of the grasp routine's closing steps."""
GRASP_MAX_STEPS = 200
LOAD_SIGNS = np.array([1.0, -1.0])
OBJECT_START_MM = (0.0, 90.0)
START_JITTER_MM = 2.0


class GraspFailed(RuntimeError):
    """The grasp routine could not close on the object."""


@dataclass(frozen=True)
class StepInfo:
    """What the last step did besides the state."""

    done: bool
    end_reason: str
    """'' while running, else 'dropped', 'lost_contact' or 'overload'."""
    refused: bool
    """True when a servo move was refused at its travel limit."""


@dataclass(frozen=True)
class HandSnapshot:
    """A hand's full state at one instant (see :meth:`SimulatedHand.snapshot`)."""

    data: mujoco.MjData
    servo: np.ndarray
    state: np.ndarray
    done: bool
    end_reason: str
    rng_state: dict


class SimulatedHand:
    """One simulated hand; not thread-safe, cheap to create (one per process)."""

    def __init__(self, params: HandParams | str = "source") -> None:
        self.params = variant(params) if isinstance(params, str) else params
        self._model = mujoco.MjModel.from_xml_string(hand_mjcf(self.params, OBJECT_START_MM))
        self._data = mujoco.MjData(self._model)
        self._substeps = int(round(CONTROL_PERIOD_S / TIMESTEP_S))
        m = self._model
        self._obj_qpos = [m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)]
                          for n in ("object_x", "object_y")]
        self._obj_geom = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "object")
        self._finger_geoms = [
            {mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{s}_{g}") for g in ("proximal_link", "distal_pad")}
            for s in FINGER_SIDES
        ]
        self._servo_ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, f"{s}_servo") for s in FINGER_SIDES]
        self._region_fields = self._region_fields_of(self.params)
        self._spool_m = self.params.spool_radius_mm / 1000.0
        self._slack_length = np.array(
            [-f.r_proximal_mm / 1000.0 * np.radians(f.rest_deg) for f in (self.params.left, self.params.right)]
        )
        self._order = list(self.params.actuator_order)
        self._rng = np.random.default_rng(0)
        self._servo = np.zeros(2)  # servo angles (rad), indexed by finger
        self._state = np.zeros(4)
        self._done = True
        self._end_reason = ""
        self._force = np.zeros(6)

    # ----------------------------------------------------------------- public API
    @property
    def state(self) -> np.ndarray:
        """Last observed state (x mm, y mm, load1, load2)."""
        return self._state.copy()

    @property
    def actuator_angles(self) -> np.ndarray:
        """Servo angles (rad) in action order: component i of an action turns angle i."""
        return self._servo[self._order].copy()

    @property
    def done(self) -> bool:
        return self._done

    @property
    def end_reason(self) -> str:
        return self._end_reason

    def place(self, seed: int | None = None) -> None:
        """Open the hand and place the object near the centre, as a person at the bench does before a grasp."""
        self._rng = np.random.default_rng(seed)
        mujoco.mj_resetData(self._model, self._data)
        jitter = self._rng.uniform(-START_JITTER_MM, START_JITTER_MM, size=2) / 1000.0
        for adr, offset in zip(self._obj_qpos, jitter, strict=True):
            self._data.qpos[adr] = offset
        self._servo[:] = 0.0
        self._apply_servo()
        mujoco.mj_forward(self._model, self._data)
        self._done = False
        self._end_reason = ""
        self._state = np.concatenate([self.object_xy, np.zeros(2)])  # no sensor draw: reset's noise stays as it was

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Open the hand, place the object near the centre, and close on it."""
        self.place(seed)
        closed = np.zeros(2, dtype=bool)
        for _ in range(GRASP_MAX_STEPS):
            loads = self._tensions_load()
            closed |= loads > GRASP_LOAD
            if closed.all():
                break
            self._servo += np.where(closed, 0.0, GRASP_INCREMENT * ACTION_UNIT_RAD)
            self._apply_servo()
            self._apply_region()
            mujoco.mj_step(self._model, self._data, nstep=self._substeps)
        else:
            raise GraspFailed(f"hand {self.params.name!r} did not reach the grasp load in {GRASP_MAX_STEPS} steps")
        if not self._has_contact().all():
            raise GraspFailed(f"hand {self.params.name!r} closed without holding the object")
        self._state = self._observe()
        return self.state

    def step(self, action: np.ndarray | tuple[float, float]) -> np.ndarray:
        """Apply one action for one control period and return the new state."""
        self.step_info(action)
        return self.state

    def step_info(self, action: np.ndarray | tuple[float, float]) -> StepInfo:
        """:meth:`step`, also telling whether the episode ended and why."""
        if self._done:
            raise RuntimeError("episode is over: call reset() first")
        a = np.asarray(action, dtype=float)
        if a.shape != (ACTION_DIM,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be 2 finite numbers, got {action!r}")
        if np.any(np.abs(a) > ACTION_LIMIT + 1e-9):
            raise ValueError(f"action {a.tolist()} outside [-{ACTION_LIMIT}, {ACTION_LIMIT}]")
        delta = np.zeros(2)
        delta[self._order] = a * ACTION_UNIT_RAD
        target = self._servo + delta
        straining = (delta > 0) & (self._tensions_load() > LOAD_GUARD)
        blocked = (target < 0.0) | (target > SERVO_MAX_RAD) | straining
        self._servo = np.where(blocked, self._servo, target)
        return self._advance(bool(np.any(blocked)))

    def hold(self, angles: np.ndarray | tuple[float, float]) -> StepInfo:
        """One control period with the servos at absolute ``angles`` (rad, action order), as a servo bus sets them.

        Angles are clamped to the servos' travel; no load guard applies (a real driver keeps its own).  Unlike
        :meth:`step_info` it runs after an episode ended too: the object lies where it fell until :meth:`place`.
        """
        a = np.asarray(angles, dtype=float)
        if a.shape != (ACTION_DIM,) or not np.all(np.isfinite(a)):
            raise ValueError(f"angles must be 2 finite numbers, got {angles!r}")
        target = np.zeros(2)
        target[self._order] = a
        clamped = np.clip(target, 0.0, SERVO_MAX_RAD)
        self._servo = clamped
        return self._advance(bool(np.any(clamped != target)), keep_done=True)

    def _advance(self, refused: bool, keep_done: bool = False) -> StepInfo:
        """One control period of physics with the servos where they are; the end of the episode checked."""
        self._apply_servo()
        before = self._state[:2].copy()
        self._apply_region()
        mujoco.mj_step(self._model, self._data, nstep=self._substeps)
        self._state = self._observe()
        if not (keep_done and self._done):
            self._end_reason = self._check_end(before)
            self._done = bool(self._end_reason)
        return StepInfo(self._done, self._end_reason, refused)

    @property
    def loads(self) -> np.ndarray:
        """True servo loads (raw units, signed as the state's), in action order, without sensor noise."""
        return self._tensions_load()[self._order] * LOAD_SIGNS

    def snapshot(self) -> HandSnapshot:
        """Everything the next steps depend on (physics, servos, sensor-noise generator):
        :meth:`restore` replays them."""
        data = mujoco.MjData(self._model)
        mujoco.mj_copyData(data, self._model, self._data)
        return HandSnapshot(data, self._servo.copy(), self._state.copy(), self._done, self._end_reason,
                            self._rng.bit_generator.state)

    def restore(self, snap: HandSnapshot) -> None:
        """Back to ``snap``: the same actions then give exactly the same states (a perfect model of this hand)."""
        mujoco.mj_copyData(self._data, self._model, snap.data)
        self._servo[:] = snap.servo
        self._state = snap.state.copy()
        self._done, self._end_reason = snap.done, snap.end_reason
        self._rng.bit_generator.state = snap.rng_state

    @property
    def object_xy(self) -> np.ndarray:
        """True object centre (mm, hand frame), without tracker noise."""
        return np.array([self._data.qpos[a] for a in self._obj_qpos]) * 1000.0 + np.array(OBJECT_START_MM)

    @property
    def in_region(self) -> bool:
        """Whether the object is in the hand's :attr:`~HandParams.region` (always False without one)."""
        region = self.params.region
        return region is not None and region.contains(self.object_xy)

    # ------------------------------------------------------------------ internals
    def _region_fields_of(self, p: HandParams) -> list[tuple[np.ndarray, tuple[int, ...], float, float]]:
        """(model array, index, value outside, value inside) for every model field the region changes."""
        region = p.region
        if region is None:
            return []
        m = self._model
        fields = []
        for side, finger in zip(FINGER_SIDES, (p.left, p.right), strict=True):
            for geom, base, inside in (("distal_pad", p.pad_friction, region.pad_friction),
                                       ("proximal_link", p.link_friction, region.link_friction)):
                if inside is not None:
                    fields.append((m.geom_friction,
                                   (mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{side}_{geom}"), 0),
                                   base, inside))
            for joint, base, scale in (("proximal", finger.k_proximal, region.k_proximal_scale),
                                       ("distal", finger.k_distal, region.k_distal_scale)):
                if scale != 1.0:
                    fields.append((m.jnt_stiffness,
                                   (mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{side}_{joint}"),),
                                   base, base * scale))
        return fields

    def _apply_region(self) -> None:
        """Set the region's friction and stiffness values for the coming control period.

        Decided once per control period (0.1 s) from the object's true position at its
        start: the object moves at most a few millimetres in a period, so the boundary is
        sharp to that, and the 2 ms substeps stay in MuJoCo's C loop.  Contacts read the
        geom frictions and the passive forces the joint stiffnesses afresh at every substep.
        """
        if self._region_fields:
            inside = self.in_region
            for array, index, outside_value, inside_value in self._region_fields:
                array[index] = inside_value if inside else outside_value

    def _apply_servo(self) -> None:
        # The servo sets the tendon's rest length: reeling in shortens it.  At servo
        # angle 0 the tendon is just slack with the finger at its spring rest pose.
        for finger, act_id in enumerate(self._servo_ids):
            self._data.ctrl[act_id] = self._slack_length[finger] - self._spool_m * self._servo[finger]

    def _tensions_load(self) -> np.ndarray:
        """Servo loads (raw units, unsigned) per finger, from the tendon tensions."""
        tension = -self._data.actuator_force[self._servo_ids]
        return tension * self._spool_m / LOAD_UNIT_NM

    def _observe(self) -> np.ndarray:
        xy = self.object_xy + self._rng.normal(0.0, self.params.position_noise_mm, size=2)
        loads = self._tensions_load()[self._order]
        loads = np.round(loads + self._rng.normal(0.0, self.params.load_noise, size=2)) * LOAD_SIGNS
        return np.concatenate([xy, loads])

    def _contact_forces(self) -> tuple[np.ndarray, float]:
        """Per finger: whether it touches the object; and the grip's friction capacity (N)."""
        touching = np.zeros(2, dtype=bool)
        capacity = 0.0
        d = self._data
        for i in range(d.ncon):
            c = d.contact[i]
            pair = {int(c.geom1), int(c.geom2)}
            if self._obj_geom not in pair:
                continue
            other = (pair - {self._obj_geom}).pop()
            for finger, geoms in enumerate(self._finger_geoms):
                if other in geoms:
                    touching[finger] = True
            mujoco.mj_contactForce(self._model, d, i, self._force)
            capacity += float(c.friction[0]) * max(float(self._force[0]), 0.0)
        return touching, capacity

    def _has_contact(self) -> np.ndarray:
        return self._contact_forces()[0]

    def _check_end(self, before_xy: np.ndarray) -> str:
        touching, capacity = self._contact_forces()
        if np.linalg.norm(self._state[:2] - before_xy) > DROP_JUMP_MM:
            return DROPPED
        if not touching.all():
            return LOST_CONTACT
        if capacity < self.params.object_mass_kg * 9.81:
            return DROPPED  # friction can no longer carry the object's weight along its axis
        if np.any(np.abs(self._state[2:]) > OVERLOAD_LOAD):
            return OVERLOAD
        return ""
