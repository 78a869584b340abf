"""MJCF text of a planar two-finger underactuated hand holding a cylinder.

The hand works in the plane perpendicular to the cylinder's axis.  Gravity acts
along that axis and is carried by pad friction only, so it does not appear in
the plane; :mod:`t42_transfer.hand.sim` turns a grip too weak to carry the
object into a drop.  Each finger is two phalanges on spring joints, flexed by
one tendon (a MuJoCo fixed tendon whose length falls with both joint angles in
the ratio of its moment arms); a position servo with a first-order lag reels the
tendon through an elastic element, and can only pull.

With a :class:`MarkerScene` the same hand also carries what a camera needs: a
fiducial-marker tile on the object's top and tiles on the hand's base, a visual
cylinder for the object, a table and a camera.  Those additions are visual only
(no collisions, no mass, no joints), so the physics is the same; without a scene
the text is exactly the physics model the simulator runs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from t42_transfer.hand.params import FingerParams, HandParams

TIMESTEP_S = 0.002
PROXIMAL_RANGE = "-0.8 1.9"
"""Proximal joint travel (rad): the flexure lets a finger splay well outward when pushed."""

LINK_RADIUS_MM = 7.0
HARD_FRICTION = f'solreffriction="{2 * TIMESTEP_S:g} 1" solimpfriction="0.999 0.9999 0.001 0.5 2"'
"""Dry friction that holds until its limit: MuJoCo's friction loss is a soft constraint, and with its default
softness it yields like a damper at a finger's slow speeds, whatever its limit. The shortest time constant
allowed (two time steps) and near-hard impedance make it stick (docs/experiments/sim_calibration)."""
FINGER_SIDES = ("left", "right")


def _mm(value: float) -> float:
    return value / 1000.0


MARKER_MARGIN_FRACTION = 0.25
"""White border around each marker on its tile, as a fraction of the marker's side (a quiet zone for detection)."""
TILE_HALF_THICKNESS_MM = 0.5


@dataclass(frozen=True)
class SceneMarker:
    """A square fiducial marker lying flat, facing +z; ``x_mm, y_mm, z_mm`` is its centre (top face)."""

    marker_id: int
    size_mm: float
    """Side of the marker's black square (what a tracker's marker size means)."""
    x_mm: float = 0.0
    y_mm: float = 0.0
    z_mm: float = 0.0


@dataclass(frozen=True)
class SceneCamera:
    """A pinhole camera at ``pos_mm`` looking at ``target_mm`` (hand frame), image ``width`` x ``height``."""

    pos_mm: tuple[float, float, float] = (110.0, -120.0, 300.0)
    target_mm: tuple[float, float, float] = (0.0, 40.0, 10.0)
    fovy_deg: float = 45.0
    width: int = 640
    height: int = 480

    def axes(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """The camera's x and y axes in the hand frame (MuJoCo: it looks along -z, y up, up roughly +y)."""
        f = [t - p for t, p in zip(self.target_mm, self.pos_mm, strict=True)]
        norm = math.sqrt(sum(v * v for v in f))
        if norm == 0.0:
            raise ValueError("camera position and target coincide")
        f = [v / norm for v in f]
        up = (0.0, 1.0, 0.0) if abs(f[1]) < 0.99 else (1.0, 0.0, 0.0)
        x = (f[1] * up[2] - f[2] * up[1], f[2] * up[0] - f[0] * up[2], f[0] * up[1] - f[1] * up[0])
        n = math.sqrt(sum(v * v for v in x))
        x = tuple(v / n for v in x)
        y = (x[1] * f[2] - x[2] * f[1], x[2] * f[0] - x[0] * f[2], x[0] * f[1] - x[1] * f[0])
        return x, y


@dataclass(frozen=True)
class MarkerScene:
    """What the camera sees: the object's marker (centred on its top), the base's markers, the camera."""

    object_marker: SceneMarker = SceneMarker(0, 20.0)
    base_markers: tuple[SceneMarker, ...] = (
        SceneMarker(1, 30.0, -60.0, -35.0, 20.0),
        SceneMarker(2, 30.0, 60.0, -35.0, 20.0),
    )
    camera: SceneCamera = SceneCamera()


def marker_texture_file(marker_id: int) -> str:
    """Asset file name of marker ``marker_id``'s tile image (the caller supplies the PNG bytes)."""
    return f"marker_{marker_id}.png"


OBJECT_TOP_MM = 35.0
"""Height of the object's (visual) cylinder top above the hand plane: it stands 15 mm proud of the palm's
top face (z = 20 mm), so the palm never hides its marker."""


def object_marker_height_mm(p: HandParams) -> float:
    """Height of the object marker's face above the hand plane (z = 0): on top of the object's cylinder."""
    return max(OBJECT_TOP_MM, p.object_radius_mm) + 2 * TILE_HALF_THICKNESS_MM


def _tile_xml(name: str, m: SceneMarker, pos_mm: tuple[float, float, float]) -> str:
    half = _mm(m.size_mm * (1 + 2 * MARKER_MARGIN_FRACTION)) / 2
    x, y, z = (_mm(v) for v in pos_mm)
    return f"""
      <geom name="{name}" type="box" pos="{x:.6f} {y:.6f} {z - _mm(TILE_HALF_THICKNESS_MM):.6f}"
            size="{half:.6f} {half:.6f} {_mm(TILE_HALF_THICKNESS_MM):.6f}" material="marker_{m.marker_id}"
            contype="0" conaffinity="0" mass="0" group="1"/>"""


def _scene_parts(p: HandParams, scene: MarkerScene) -> tuple[str, str, str, str]:
    """(visual/asset XML, worldbody XML, object-body XML, camera XML) of ``scene``'s additions."""
    markers = (scene.object_marker, *scene.base_markers)
    ids = [m.marker_id for m in markers]
    if len(set(ids)) != len(ids):
        raise ValueError(f"marker ids must differ, got {ids}")
    cam = scene.camera
    assets = "".join(
        f"""
    <texture name="marker_{m.marker_id}" type="2d" file="{marker_texture_file(m.marker_id)}"/>
    <material name="marker_{m.marker_id}" texture="marker_{m.marker_id}" specular="0" shininess="0"/>"""
        for m in markers
    )
    head = f"""
  <visual>
    <global offwidth="{cam.width}" offheight="{cam.height}"/>
    <headlight ambient="0.5 0.5 0.5" diffuse="0.5 0.5 0.5" specular="0 0 0"/>
  </visual>
  <asset>{assets}
    <material name="table" rgba="0.35 0.37 0.4 1" specular="0"/>
    <material name="object" rgba="0.75 0.55 0.3 1" specular="0"/>
  </asset>"""
    r = _mm(p.object_radius_mm)
    world = "".join(_tile_xml(f"base_marker_{m.marker_id}", m, (m.x_mm, m.y_mm, m.z_mm)) for m in scene.base_markers)
    world += """
    <geom name="table" type="plane" pos="0 0 -0.03" size="0.5 0.5 0.01" material="table"
          contype="0" conaffinity="0" group="1"/>"""
    top = object_marker_height_mm(p)
    cylinder_top = _mm(top - 2 * TILE_HALF_THICKNESS_MM)
    body = f"""
      <geom name="object_cylinder" type="cylinder" fromto="0 0 {-r:.6f} 0 0 {cylinder_top:.6f}"
            size="{r:.6f}" material="object"
            contype="0" conaffinity="0" mass="0" group="1"/>""" + _tile_xml(
        "object_marker", scene.object_marker, (0.0, 0.0, top))
    xa, ya = cam.axes()
    x, y, z = (_mm(v) for v in cam.pos_mm)
    camera = f"""
    <camera name="tracker_camera" pos="{x:.6f} {y:.6f} {z:.6f}" fovy="{cam.fovy_deg:.6f}"
            xyaxes="{' '.join(f'{v:.9f}' for v in (*xa, *ya))}"/>"""
    return head, world, body, camera


def _friction(value: float) -> str:
    """A joint's or tendon's dry-friction attributes; none at 0, so a hand without friction compiles as before."""
    return f' frictionloss="{value}" {HARD_FRICTION}' if value > 0 else ""


def _finger_xml(side: str, f: FingerParams, p: HandParams) -> str:
    sign = -1.0 if side == "left" else 1.0
    friction = _friction(p.joint_friction_nm)
    # Flexion (positive joint angle) turns each finger toward the centre line.
    axis = "0 0 -1" if side == "left" else "0 0 1"
    rest = math.radians(f.rest_deg)
    r = _mm(LINK_RADIUS_MM)
    return f"""
    <body name="{side}_proximal" pos="{sign * _mm(p.base_half_width_mm):.6f} 0 0">
      <joint name="{side}_proximal" type="hinge" axis="{axis}" stiffness="{f.k_proximal}" springref="{rest:.6f}"
             damping="{p.joint_damping}" range="{PROXIMAL_RANGE}" limited="true" armature="2e-5"{friction}/>
      <geom name="{side}_proximal_link" type="capsule" fromto="0 0 0 0 {_mm(f.proximal_mm):.6f} 0" size="{r}"
            friction="{p.link_friction} 0.005 0.0001" contype="2" conaffinity="1" mass="0.012"/>
      <body name="{side}_distal" pos="0 {_mm(f.proximal_mm):.6f} 0">
        <joint name="{side}_distal" type="hinge" axis="{axis}" stiffness="{f.k_distal}" springref="0"
               damping="{p.joint_damping}" range="-0.2 1.7" limited="true" armature="2e-5"{friction}/>
        <geom name="{side}_distal_pad" type="capsule" fromto="0 0 0 0 {_mm(f.distal_mm):.6f} 0" size="{r}"
              friction="{p.pad_friction} 0.005 0.0001" contype="2" conaffinity="1" mass="0.008"/>
      </body>
    </body>"""


def _tendon_xml(side: str, f: FingerParams, p: HandParams) -> str:
    return f"""
    <fixed name="{side}_tendon"{_friction(p.tendon_friction_n)}>
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


def hand_mjcf(p: HandParams, object_start_mm: tuple[float, float], scene: MarkerScene | None = None) -> str:
    """MJCF of hand ``p`` with the object's reference position at ``object_start_mm``.

    With ``scene``, also its markers and camera (visual only; the marker images are assets named by
    :func:`marker_texture_file`, which the caller passes to ``MjModel.from_xml_string``).
    """
    head, world, body, camera = _scene_parts(p, scene) if scene is not None else ("", "", "", "")
    radius = _mm(p.object_radius_mm)
    inertia = 0.5 * p.object_mass_kg * radius**2
    fingers = "".join(_finger_xml(s, f, p) for s, f in zip(FINGER_SIDES, (p.left, p.right), strict=True))
    tendons = "".join(_tendon_xml(s, f, p) for s, f in zip(FINGER_SIDES, (p.left, p.right), strict=True))
    servos = "".join(_servo_xml(s, p) for s in FINGER_SIDES)
    x0, y0 = (_mm(v) for v in object_start_mm)
    half_height, half_width = _mm(p.palm_height_mm) / 2, _mm(p.base_half_width_mm) - 0.009
    return f"""<mujoco model="t42_{p.name}">
  <compiler angle="radian"/>
  <option timestep="{TIMESTEP_S}" gravity="0 0 0" integrator="implicitfast" cone="elliptic"/>{head}
  <worldbody>
    <geom name="palm" type="box" pos="0 {half_height:.6f} 0" size="{half_width:.6f} {half_height:.6f} 0.02"
          contype="2" conaffinity="1"
          friction="0.3 0.005 0.0001"/>{world}{fingers}
    <body name="object" pos="{x0:.6f} {y0:.6f} 0">
      <joint name="object_x" type="slide" axis="1 0 0" damping="{p.object_damping}"/>
      <joint name="object_y" type="slide" axis="0 1 0" damping="{p.object_damping}"/>
      <joint name="object_yaw" type="hinge" axis="0 0 1" damping="{p.object_damping * radius**2:.3e}"/>
      <inertial pos="0 0 0" mass="{p.object_mass_kg}" diaginertia="{inertia:.3e} {inertia:.3e} {inertia:.3e}"/>
      <geom name="object" type="sphere" size="{radius}" contype="1" conaffinity="1" friction="0.1 0.005 0.0001"
            mass="0"/>{body}
    </body>{camera}
  </worldbody>
  <tendon>{tendons}
  </tendon>
  <actuator>{servos}
  </actuator>
</mujoco>
"""
