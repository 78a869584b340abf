"""MJCF text of a planar two-finger underactuated hand holding a cylinder.

The hand works in the plane perpendicular to the cylinder's axis.  Gravity acts
along that axis and is carried by pad friction only, so it does not appear in
the plane; :mod:`t42_transfer.hand.sim` turns a grip too weak to carry the
object into a drop.  Each finger is two phalanges on spring joints, flexed by
one tendon (a MuJoCo fixed tendon whose length falls with both joint angles in
the ratio of its moment arms); a position servo with a first-order lag reels the
tendon through an elastic element, and can only pull.
"""

from __future__ import annotations

import math

from t42_transfer.hand.params import FingerParams, HandParams

TIMESTEP_S = 0.002
PROXIMAL_RANGE = "-0.8 1.9"
"""Proximal joint travel (rad): the flexure lets a finger splay well outward when pushed."""

LINK_RADIUS_MM = 7.0
FINGER_SIDES = ("left", "right")


def _mm(value: float) -> float:
    return value / 1000.0


def _finger_xml(side: str, f: FingerParams, p: HandParams) -> str:
    sign = -1.0 if side == "left" else 1.0
    # Flexion (positive joint angle) turns each finger toward the centre line.
    axis = "0 0 -1" if side == "left" else "0 0 1"
    rest = math.radians(f.rest_deg)
    r = _mm(LINK_RADIUS_MM)
    return f"""
    <body name="{side}_proximal" pos="{sign * _mm(p.base_half_width_mm):.6f} 0 0">
      <joint name="{side}_proximal" type="hinge" axis="{axis}" stiffness="{f.k_proximal}" springref="{rest:.6f}"
             damping="{p.joint_damping}" range="{PROXIMAL_RANGE}" limited="true" armature="2e-5"/>
      <geom name="{side}_proximal_link" type="capsule" fromto="0 0 0 0 {_mm(f.proximal_mm):.6f} 0" size="{r}"
            friction="{p.link_friction} 0.005 0.0001" contype="2" conaffinity="1" mass="0.012"/>
      <body name="{side}_distal" pos="0 {_mm(f.proximal_mm):.6f} 0">
        <joint name="{side}_distal" type="hinge" axis="{axis}" stiffness="{f.k_distal}" springref="0"
               damping="{p.joint_damping}" range="-0.2 1.7" limited="true" armature="2e-5"/>
        <geom name="{side}_distal_pad" type="capsule" fromto="0 0 0 0 {_mm(f.distal_mm):.6f} 0" size="{r}"
              friction="{p.pad_friction} 0.005 0.0001" contype="2" conaffinity="1" mass="0.008"/>
      </body>
    </body>"""


def _tendon_xml(side: str, f: FingerParams) -> str:
    return f"""
    <fixed name="{side}_tendon">
      <joint joint="{side}_proximal" coef="{-_mm(f.r_proximal_mm):.6f}"/>
      <joint joint="{side}_distal" coef="{-_mm(f.r_distal_mm):.6f}"/>
    </fixed>"""


def _servo_xml(side: str, p: HandParams) -> str:
    k = p.tendon_stiffness
    damping = 0.05 * k * p.servo_time_constant_s
    return f"""
    <general name="{side}_servo" tendon="{side}_tendon" dyntype="filterexact" dynprm="{p.servo_time_constant_s}"
             gaintype="fixed" gainprm="{k}" biastype="affine" biasprm="0 {-k} {-damping:.4f}"
             forcelimited="true" forcerange="{-p.max_tension_n} 0"/>"""


def hand_mjcf(p: HandParams, object_start_mm: tuple[float, float]) -> str:
    """MJCF of hand ``p`` with the object's reference position at ``object_start_mm``."""
    radius = _mm(p.object_radius_mm)
    inertia = 0.5 * p.object_mass_kg * radius**2
    fingers = "".join(_finger_xml(s, f, p) for s, f in zip(FINGER_SIDES, (p.left, p.right), strict=True))
    tendons = "".join(_tendon_xml(s, f) for s, f in zip(FINGER_SIDES, (p.left, p.right), strict=True))
    servos = "".join(_servo_xml(s, p) for s in FINGER_SIDES)
    x0, y0 = (_mm(v) for v in object_start_mm)
    half_height, half_width = _mm(p.palm_height_mm) / 2, _mm(p.base_half_width_mm) - 0.009
    return f"""<mujoco model="t42_{p.name}">
  <compiler angle="radian"/>
  <option timestep="{TIMESTEP_S}" gravity="0 0 0" integrator="implicitfast" cone="elliptic"/>
  <worldbody>
    <geom name="palm" type="box" pos="0 {half_height:.6f} 0" size="{half_width:.6f} {half_height:.6f} 0.02"
          contype="2" conaffinity="1"
          friction="0.3 0.005 0.0001"/>{fingers}
    <body name="object" pos="{x0:.6f} {y0:.6f} 0">
      <joint name="object_x" type="slide" axis="1 0 0" damping="{p.object_damping}"/>
      <joint name="object_y" type="slide" axis="0 1 0" damping="{p.object_damping}"/>
      <joint name="object_yaw" type="hinge" axis="0 0 1" damping="{p.object_damping * radius**2:.3e}"/>
      <inertial pos="0 0 0" mass="{p.object_mass_kg}" diaginertia="{inertia:.3e} {inertia:.3e} {inertia:.3e}"/>
      <geom name="object" type="sphere" size="{radius}" contype="1" conaffinity="1" friction="0.1 0.005 0.0001"
            mass="0"/>
    </body>
  </worldbody>
  <tendon>{tendons}
  </tendon>
  <actuator>{servos}
  </actuator>
</mujoco>
"""
