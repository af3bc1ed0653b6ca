"""The one kinematic and inertial description of the Kinova JACO-2 7-DoF spherical-wrist arm (j2s7s300).

Everything that needs the arm's geometry loads it from here: :func:`urdf` renders the description, MuJoCo
(:func:`load_mujoco`) and Pinocchio (:func:`load_pinocchio`) both load that same text, and
:func:`dh_forward_kinematics` evaluates the DH table directly as an independent reference.

Geometry is Kinova's classic DH table (``shared/reference/kinova.md``): a = 0; d = [−D1, 0, −(D2+D3), −e2,
−(D4+D5), 0, −(D6+D7)]; α = [π/2 ×6, π]; a base transform Rx(π); θ_DH,1 = −q1 and θ_DH,i = q_i otherwise. Checked
against the geometry: joints 2, 4 and 6 at 180° (the centres of their ranges) stand the arm straight up, 1.26 m
tall, and the end effector reaches 0.985 m from the shoulder.

Joint coordinates. *Physical* angles are what the arm reports (GetAngularPosition, degrees, never wrapped).
*Model* angles are the DH θ in radians: ``q_model = SIGN * radians(q_physical)``. The wire (protocol.messages)
carries model angles and rates; Kinova units appear only at the API boundary.

Inertia: link and actuator masses after seed 003 (Tables 3.5-3.7, 6-DoF) arranged on the 7-DoF chain (the
6-DoF upper arm is split across the two 7-DoF upper-arm links; K-75+ actuators on joints 1-4, K-58 on 5-7; the
three-finger hand at the end). Centres of mass lie mid-segment and inertias are solid cylinders: adequate for
simulation and computed torque, not an identified model.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

# Link lengths (m), Kinova's names.
D1, D2, D3, D4, D5, D6, D7, E2 = 0.2755, 0.2050, 0.2050, 0.2073, 0.1038, 0.1038, 0.1600, 0.0098

DH_D = (-D1, 0.0, -(D2 + D3), -E2, -(D4 + D5), 0.0, -(D6 + D7))
DH_ALPHA = (math.pi / 2,) * 6 + (math.pi,)
DH_A = (0.0,) * 7

N_JOINTS = 7
#: model angle = SIGN * physical angle (rad); θ_DH,1 = −q1
SIGN = np.array([-1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])

#: Reach from the shoulder (joint 2 axis) to the end-effector origin with the arm straight (m).
STRAIGHT_REACH = D2 + D3 + D4 + D5 + D6 + D7


@dataclass(frozen=True)
class JointSpec:
    name: str
    continuous: bool
    #: physical limits in degrees (None for continuous joints)
    lower_deg: float | None
    upper_deg: float | None
    max_speed_dps: float
    max_torque_nm: float
    #: mass (kg) of the link this joint moves, including the actuator it carries
    link_mass_kg: float


JOINTS: tuple[JointSpec, ...] = (
    # link 1 (shoulder, 0.182 kg) carries actuator 2 (K-75+, 0.560 kg + 0.012 kg ring)
    JointSpec("joint_1", True, None, None, 36.0, 40.0, 0.182 + 0.572),
    # links 2 and 3 share the 6-DoF upper arm (0.424 kg) and each carry a K-75+ (0.573 kg + ring)
    JointSpec("joint_2", False, 47.0, 313.0, 36.0, 80.0, 0.212 + 0.585),
    JointSpec("joint_3", True, None, None, 36.0, 40.0, 0.212 + 0.585),
    # link 4 (forearm, 0.211 kg) carries actuator 5 (K-58, 0.341 kg + 0.007 kg ring)
    JointSpec("joint_4", False, 30.0, 330.0, 36.0, 40.0, 0.211 + 0.348),
    JointSpec("joint_5", True, None, None, 48.0, 20.0, 0.069 + 0.348),
    JointSpec("joint_6", False, 65.0, 295.0, 48.0, 20.0, 0.069 + 0.348),
    # link 7: the three-finger hand
    JointSpec("joint_7", True, None, None, 48.0, 20.0, 0.727),
)

JOINT_NAMES = tuple(j.name for j in JOINTS)
BASE_LINK = "base_link"
EE_LINK = "end_effector"
LINK_NAMES = tuple(f"link_{i}" for i in range(1, N_JOINTS + 1))

MAX_SPEED_DPS = np.array([j.max_speed_dps for j in JOINTS])
MAX_SPEED = np.radians(MAX_SPEED_DPS)

# The arm's Cartesian limits (shared/reference/kinova.md): the most Kinova's client configuration allows (product
# sheet: 20 cm/s) and its acceleration limits. The robot node declares the limits it applies in every state
# (``RobotState.limits``); the controller and safety read them there.
#: Kinova's client configuration ranges for the maximum translation (m/s) and orientation (rad/s) velocity
LINEAR_SPEED_RANGE = (0.04, 0.2)
ANGULAR_SPEED_RANGE = (0.16, 1.07)
MAX_LINEAR_SPEED_MPS = LINEAR_SPEED_RANGE[1]
MAX_ANGULAR_SPEED_RPS = ANGULAR_SPEED_RANGE[1]
LINEAR_ACCEL_MPS2 = 0.64
ANGULAR_ACCEL_RPS2 = 2.75
JOINT_ACCEL_DPS2 = 200.0
MAX_TORQUE = np.array([j.max_torque_nm for j in JOINTS])
CONTINUOUS = np.array([j.continuous for j in JOINTS])

# Rotor inertia reflected through the gears (K-75+ and K-58 at 160:1 and 110:1; kg·m²) and viscous joint
# friction (N·m·s/rad): part of the one description, so physics (MuJoCo) and model-based control (Pinocchio) agree.
ARMATURE = np.array([0.10, 0.10, 0.10, 0.10, 0.04, 0.04, 0.04])
DAMPING = np.array([0.4, 0.4, 0.4, 0.4, 0.15, 0.15, 0.15])

#: Physical angles (deg) of mfvs's home ("ready") pose: the end effector about 0.45 m in front of the base
#: (−y) at 0.5 m height, approach axis forward and 40° down, every limited joint ≥ 40° from its limits and
#: the wrist ≥ 40° from its singular straight configuration.
HOME_DEG = np.array([270.0, 170.0, 0.0, 80.0, 0.0, 220.0, 0.0])

_LINK_RADIUS = 0.04
_MIN_SEGMENT = 0.08
#: the symmetric range a continuous joint gets in formats that need one (model rad); effectively unbounded
_CONTINUOUS_RANGE = 100.0 * math.pi


def physical_deg_to_model(q_deg) -> np.ndarray:
    """Physical angles (deg, as GetAngularPosition reports) → model angles (rad)."""
    return SIGN * np.radians(np.asarray(q_deg, dtype=float))


def model_to_physical_deg(q) -> np.ndarray:
    return np.degrees(SIGN * np.asarray(q, dtype=float))


def physical_rate_to_model(dq_dps) -> np.ndarray:
    """Physical joint rates (deg/s) → model rates (rad/s)."""
    return SIGN * np.radians(np.asarray(dq_dps, dtype=float))


def model_rate_to_physical(dq) -> np.ndarray:
    return np.degrees(SIGN * np.asarray(dq, dtype=float))


def model_limits() -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper model-angle limits (rad); ±inf for continuous joints."""
    lower = np.full(N_JOINTS, -np.inf)
    upper = np.full(N_JOINTS, np.inf)
    for i, j in enumerate(JOINTS):
        if j.continuous:
            continue
        a, b = SIGN[i] * math.radians(j.lower_deg), SIGN[i] * math.radians(j.upper_deg)
        lower[i], upper[i] = min(a, b), max(a, b)
    return lower, upper


HOME = physical_deg_to_model(HOME_DEG)


def limit_margins_deg(q) -> np.ndarray:
    """Each limited joint's distance to its nearer limit (deg), at one configuration (model radians) or at a stack
    of them (…×7 → …×limited joints)."""
    lower, upper = model_limits()
    limited = np.isfinite(lower)
    q = np.asarray(q, dtype=float)[..., limited]
    return np.degrees(np.minimum(q - lower[limited], upper[limited] - q))


# ------------------------------------------------------------------------------------------------ reference FK


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]])


def _dh(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]])


def dh_forward_kinematics(q) -> np.ndarray:
    """Base → end-effector homogeneous transform straight from the DH table (model angles, rad)."""
    q = np.asarray(q, dtype=float)
    T = _rot_x(math.pi)
    for i in range(N_JOINTS):
        T = T @ _dh(q[i], DH_D[i], DH_A[i], DH_ALPHA[i])
    return T


# ------------------------------------------------------------------------------------------------ description


def _f(x: float) -> str:
    return repr(float(x))


def _inertial(mass: float, length: float, z_com: float) -> str:
    r = _LINK_RADIUS
    ixx = mass * (3 * r * r + length * length) / 12.0
    izz = mass * r * r / 2.0
    return (
        f'<inertial><origin xyz="0 0 {_f(z_com)}" rpy="0 0 0"/><mass value="{_f(mass)}"/>'
        f'<inertia ixx="{_f(ixx)}" ixy="0" ixz="0" iyy="{_f(ixx)}" iyz="0" izz="{_f(izz)}"/></inertial>'
    )


def _segment_geometry(d: float) -> str:
    """A cylinder from the link origin to the next joint (or a sphere when they coincide)."""
    if abs(d) < 1e-6:
        shape = f'<sphere radius="{_f(_LINK_RADIUS * 1.15)}"/>'
        origin = '<origin xyz="0 0 0" rpy="0 0 0"/>'
    else:
        shape = f'<cylinder radius="{_f(_LINK_RADIUS)}" length="{_f(abs(d))}"/>'
        origin = f'<origin xyz="0 0 {_f(d / 2)}" rpy="0 0 0"/>'
    return f"<collision>{origin}<geometry>{shape}</geometry></collision>"


@lru_cache(maxsize=1)
def urdf() -> str:
    """The arm as URDF text: base_link → (Rx(π)) link_0 → joint_1 … joint_7 → end_effector.

    Each joint's origin is the previous DH link's Tz(d)·Rx(α), so joint i's coordinate is exactly θ_DH,i. Continuous
    joints are written as revolute joints with a range of ±100π so every loader keeps one coordinate per joint.
    """
    parts = [
        '<?xml version="1.0"?>',
        '<robot name="j2s7s300">',
        # MuJoCo reads this block and keeps the fixed frames as bodies.
        '<mujoco><compiler angle="radian" discardvisual="false" fusestatic="false" strippath="false"/></mujoco>',
        f'<link name="{BASE_LINK}"><inertial><origin xyz="0 0 0.08" rpy="0 0 0"/><mass value="0.6"/>'
        '<inertia ixx="0.002" ixy="0" ixz="0" iyy="0.002" iyz="0" izz="0.001"/></inertial>'
        '<collision><origin xyz="0 0 0.09" rpy="0 0 0"/><geometry><cylinder radius="0.045" length="0.18"/>'
        "</geometry></collision></link>",
        '<link name="link_0"/>',
        f'<joint name="base_dh" type="fixed"><parent link="{BASE_LINK}"/><child link="link_0"/>'
        f'<origin xyz="0 0 0" rpy="{_f(math.pi)} 0 0"/></joint>',
    ]
    for i, spec in enumerate(JOINTS):
        d = DH_D[i]
        length = max(abs(d), _MIN_SEGMENT)
        link = LINK_NAMES[i]
        parts.append(f'<link name="{link}">{_inertial(spec.link_mass_kg, length, d / 2)}{_segment_geometry(d)}</link>')
        if i == 0:
            origin = '<origin xyz="0 0 0" rpy="0 0 0"/>'
        else:
            origin = f'<origin xyz="{_f(DH_A[i - 1])} 0 {_f(DH_D[i - 1])}" rpy="{_f(DH_ALPHA[i - 1])} 0 0"/>'
        if spec.continuous:
            lo, hi = -_CONTINUOUS_RANGE, _CONTINUOUS_RANGE
        else:
            lo, hi = (SIGN[i] * math.radians(v) for v in (spec.lower_deg, spec.upper_deg))
            lo, hi = min(lo, hi), max(lo, hi)
        parent = "link_0" if i == 0 else LINK_NAMES[i - 1]
        parts.append(
            f'<joint name="{spec.name}" type="revolute"><parent link="{parent}"/><child link="{link}"/>{origin}'
            f'<axis xyz="0 0 1"/><limit lower="{_f(lo)}" upper="{_f(hi)}" effort="{_f(spec.max_torque_nm)}" '
            f'velocity="{_f(math.radians(spec.max_speed_dps))}"/></joint>'
        )
    parts.append(f'<link name="{EE_LINK}"/>')
    parts.append(
        f'<joint name="end_effector_fixed" type="fixed"><parent link="{LINK_NAMES[-1]}"/><child link="{EE_LINK}"/>'
        f'<origin xyz="{_f(DH_A[-1])} 0 {_f(DH_D[-1])}" rpy="{_f(DH_ALPHA[-1])} 0 0"/></joint>'
    )
    parts.append("</robot>")
    return "\n".join(parts)


# ------------------------------------------------------------------------------------------------ loaders


def mujoco_module():
    """The mujoco module, its warnings sent to the ``mujoco`` logger: MuJoCo's own handler writes them into a
    MUJOCO_LOG.TXT in whatever directory the process was started from."""
    import logging

    import mujoco

    if mujoco.get_mju_user_warning() is None:
        log = logging.getLogger("mujoco")
        mujoco.set_mju_user_warning(lambda message: log.warning("MuJoCo: %s", message))
    return mujoco


def mujoco_spec():
    """A MuJoCo MjSpec of the arm (from :func:`urdf`): continuous joints unlimited, rotor inertia and joint
    friction as :data:`ARMATURE` and :data:`DAMPING`, no contacts. Scenes add to it."""
    mujoco = mujoco_module()

    spec = mujoco.MjSpec.from_string(urdf())
    for i, spec_joint in enumerate(JOINTS):
        joint = spec.joint(spec_joint.name)
        joint.armature = float(ARMATURE[i])
        joint.damping = [float(DAMPING[i]), 0.0, 0.0]  # MuJoCo 4: polynomial damping coefficients
        if spec_joint.continuous:
            joint.limited = mujoco.mjtLimited.mjLIMITED_FALSE
    # The primitive link shapes overlap at the joints, and the arm does not collide with itself or its
    # surroundings in this model (protection zones and joint limits keep it clear, as on the real arm):
    # they are visual.
    for geom in spec.geoms:
        geom.contype = 0
        geom.conaffinity = 0
    return spec


def load_mujoco():
    """The bare arm as an MjModel (no scene, no actuators)."""
    return mujoco_spec().compile()


@dataclass(frozen=True)
class PinocchioArm:
    model: object
    ee_frame_id: int


@lru_cache(maxsize=1)
def load_pinocchio() -> PinocchioArm:
    """The arm as a Pinocchio model (immutable; create ``model.createData()`` per user)."""
    import pinocchio as pin

    model = pin.buildModelFromXML(urdf())
    if model.nq != N_JOINTS or model.nv != N_JOINTS:
        raise RuntimeError(f"Pinocchio built nq={model.nq}, nv={model.nv} from the URDF; expected {N_JOINTS}")
    model.armature = ARMATURE.copy()  # URDF has no rotor inertia: the same values MuJoCo gets
    model.damping = DAMPING.copy()
    return PinocchioArm(model, model.getFrameId(EE_LINK))
