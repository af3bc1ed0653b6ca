"""Arm descriptions: one file per arm in ``services/model/arms/<name>.yaml``, each from public facts with its sources
named beside its numbers; :func:`load_arm` reads one into an immutable :class:`ArmDescription`, and everything that
needs an arm's geometry, limits or inertia takes it from there. A third arm is one new file.

Like Pinocchio's and MuJoCo's models, a description is immutable and shared: MuJoCo (:meth:`ArmDescription.mujoco_spec`)
and Pinocchio (:meth:`ArmDescription.load_pinocchio`) both load the same URDF text (:meth:`ArmDescription.urdf`), and
:meth:`ArmDescription.dh_forward_kinematics` evaluates the DH table directly as an independent reference.

Geometry is a classic DH table, T_i = Rz(θ_i)·Tz(d_i)·Tx(a_i)·Rx(α_i), after a base rotation, with
θ_DH,i = sign_i·q_i + offset_i for the physical angle q_i (radians) the arm reports (GetAngularPosition, never wrapped).
*Model* angles are those θ_DH (radians): the wire (protocol.messages) carries model angles and rates; Kinova units
appear only at the API boundary.

Inertia: each link's mass from the file's source, its centre of mass mid-segment and a solid cylinder (mfvs's choice:
adequate for simulation and computed torque, not an identified model).
"""
from __future__ import annotations

import ast
import math
import operator
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Optional, Union

import msgspec
import numpy as np
import yaml

ARMS_DIR = Path(__file__).resolve().parent / "arms"
#: the hands an arm file may name (``hand: <name>``), one file each
HANDS_DIR = Path(__file__).resolve().parent / "hands"
#: Kinova's actuators as their data sheets give them (the arm files name each joint's)
ACTUATORS_FILE = Path(__file__).resolve().parent / "actuators.yaml"
#: the arm a stack runs when nothing chooses one (Sensors 2022's)
DEFAULT_ARM = "j2s7s300"
BASE_LINK = "base_link"
EE_LINK = "end_effector"
#: the most joints the Kinova API carries (AngularInfo: Actuator1..7)
MAX_JOINTS = 7
#: the most fingers it carries (FingersPosition: Finger1..3)
MAX_FINGERS = 3

_LINK_RADIUS = 0.04
_MIN_SEGMENT = 0.08
#: the symmetric range a continuous joint gets in formats that need one (model rad); effectively unbounded
_CONTINUOUS_RANGE = 100.0 * math.pi


class ArmError(ValueError):
    """An arm that cannot be had: an unknown name, or a description file that is not valid."""


# ------------------------------------------------------------------------------------------------ the file


Number = Union[float, int, str]

_OPERATORS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv,
              ast.USub: operator.neg, ast.UAdd: operator.pos}
_FUNCTIONS = {"sin": math.sin, "cos": math.cos, "sqrt": math.sqrt, "radians": math.radians}


def evaluate(value: Number, names: dict[str, float]) -> float:
    """A number of a description file: a number, or arithmetic as the sources write it (+ - * / of numbers, the
    file's lengths, pi, sin, cos, sqrt, radians)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, str):
        raise ArmError(f"{value!r} is not a number or an expression")

    def walk(node) -> float:
        if isinstance(node, ast.Expression):
            return walk(node.body)
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
            return float(node.value)
        if isinstance(node, ast.Name):
            if node.id == "pi":
                return math.pi
            if node.id in names:
                return names[node.id]
            raise ArmError(f"unknown name {node.id!r} in {value!r}")
        if isinstance(node, ast.BinOp) and type(node.op) in _OPERATORS:
            return _OPERATORS[type(node.op)](walk(node.left), walk(node.right))
        if isinstance(node, ast.UnaryOp) and type(node.op) in _OPERATORS:
            return _OPERATORS[type(node.op)](walk(node.operand))
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in _FUNCTIONS
                and len(node.args) == 1 and not node.keywords):
            return _FUNCTIONS[node.func.id](walk(node.args[0]))
        raise ArmError(f"{value!r}: only numbers, names, + - * / and sin, cos, sqrt, radians are allowed")

    try:
        tree = ast.parse(value, mode="eval")
    except SyntaxError:
        raise ArmError(f"{value!r} is not an expression") from None
    result = walk(tree)
    if not math.isfinite(result):
        raise ArmError(f"{value!r} is not finite")
    return result


class _DHRow(msgspec.Struct, forbid_unknown_fields=True):
    d: Number
    a: Number
    alpha: Number
    sign: int
    offset: Number


class _Kinematics(msgspec.Struct, forbid_unknown_fields=True):
    base_rpy: tuple[Number, Number, Number]
    dh: list[_DHRow]
    shoulder_height: Number
    reach: Number


class _Cartesian(msgspec.Struct, forbid_unknown_fields=True):
    linear_speed_range_mps: tuple[float, float]
    angular_speed_range_rps: tuple[float, float]
    linear_accel_mps2: float
    angular_accel_rps2: float
    joint_accel_dps2: float


class _Joint(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    range_deg: Optional[tuple[float, float]]
    max_speed_dps: float
    actuator: str


class _Link(msgspec.Struct, forbid_unknown_fields=True):
    mass_kg: Number


class Actuator(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """One actuator model's data sheet (services/model/actuators.yaml)."""

    peak_torque_nm: float
    stall_torque_nm: float
    nominal_torque_nm: float
    no_load_speed_rpm: float
    nominal_speed_rpm: float
    gear_ratio: float
    torque_gradient_nm_per_a: float
    backdriving_torque_nm: tuple[float, float]
    torque_sensor_precision_nm: float
    torque_sensor_drift_nm: float
    mass_kg: float

    @property
    def no_load_speed(self) -> float:
        """rad/s at the output."""
        return self.no_load_speed_rpm * 2.0 * math.pi / 60.0


class _Emulation(msgspec.Struct, forbid_unknown_fields=True):
    link_mass_scale: list[float]
    torque_mode_friction_fraction: float


class _Base(msgspec.Struct, forbid_unknown_fields=True):
    mass_kg: Number
    com_z: Number
    height: Number
    radius: Number


class _Finger(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    bus_address: int


class _Origin(msgspec.Struct, forbid_unknown_fields=True):
    xyz: tuple[Number, Number, Number]
    rpy: tuple[Number, Number, Number]


class _Hand(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    title: str
    fingers: list[_Finger]
    closed_units: float
    closed_deg: float
    closing_time_s: float
    end_effector_in_hand_link: _Origin
    finger_origins_in_hand_link: list[_Origin]
    proximal_length_m: float
    distal_offset_m: tuple[float, float, float]
    distal_length_m: float
    link_radius_m: float
    proximal_mass_kg: float
    distal_mass_kg: float
    grip_force_n: float
    full_force_current_a: float


class _File(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    title: str
    seed: str
    lengths: dict[str, float]
    kinematics: _Kinematics
    cartesian: _Cartesian
    joints: list[_Joint]
    home_deg: list[float]
    bus_addresses: list[int]
    robot_type: int
    links: list[_Link]
    base: _Base
    armature: list[float]
    damping: list[float]
    emulation: _Emulation
    #: the hand it carries: a file of services/model/hands (None: none)
    hand: Optional[str] = None


# ------------------------------------------------------------------------------------------------ the description


@dataclass(frozen=True)
class JointSpec:
    name: str
    continuous: bool
    #: physical limits in degrees (None for continuous joints)
    lower_deg: Optional[float]
    upper_deg: Optional[float]
    max_speed_dps: float
    #: the actuator that drives it (its data sheet's name) and its data sheet
    actuator: str
    spec: Actuator
    #: mass (kg) of the link this joint moves, including the actuator it carries
    link_mass_kg: float

    @property
    def max_torque_nm(self) -> float:
        """The most torque the joint gives: its actuator's peak (software limitation)."""
        return self.spec.peak_torque_nm

    @property
    def peak_torque_nm(self) -> float:
        return self.spec.peak_torque_nm

    @property
    def nominal_torque_nm(self) -> float:
        return self.spec.nominal_torque_nm


@dataclass(frozen=True)
class HandDescription:
    """The arm's hand: a second actuator group beside the joints, never joints of the arm's chain (Pinocchio's
    model and every joint vector stay the arm's). Each finger is one actuated proximal hinge; its angle is the
    wire's (rad, 0 open, growing as it closes), Kinova's API and bus carry it in Kinova's finger units."""

    name: str
    title: str
    finger_names: tuple[str, ...]
    #: each finger actuator's RS-485 address
    bus_addresses: tuple[int, ...]
    #: Kinova's finger units at the closed end of the travel, and the hinge's angle there (rad)
    closed_units: float
    closed_angle: float
    #: full travel, open to closed, at the fingers' top speed (s)
    closing_time_s: float
    #: each finger's hinge in the end effector's frame (4×4: the hinge turns about its z, the finger along its x)
    finger_origins: tuple[np.ndarray, ...]
    #: a finger's links: the proximal's length, the distal's origin on it and length, their radius (m), masses (kg)
    proximal_length_m: float
    distal_offset_m: tuple[float, float, float]
    distal_length_m: float
    link_radius_m: float
    proximal_mass_kg: float
    distal_mass_kg: float
    #: the three fingers' normal forces together on an object held at the pinch (N)
    grip_force_n: float
    #: the current a finger's motor draws at its full force (A): what a grasp detector judges currents against
    full_force_current_a: float
    #: the file it was read from
    path: Path

    @property
    def finger_mass_kg(self) -> float:
        return self.proximal_mass_kg + self.distal_mass_kg

    @property
    def n_fingers(self) -> int:
        return len(self.finger_names)

    @property
    def max_speed(self) -> float:
        """A finger's top rate (rad/s): the full travel in the closing time."""
        return self.closed_angle / self.closing_time_s

    def units_to_angle(self, units) -> np.ndarray:
        """Kinova's finger units (FingersPosition, as GetAngularPosition and the bus report them) → rad."""
        return np.asarray(units, dtype=float) * (self.closed_angle / self.closed_units)

    def angle_to_units(self, angle) -> np.ndarray:
        return np.asarray(angle, dtype=float) * (self.closed_units / self.closed_angle)

    def clip(self, angle) -> np.ndarray:
        """Angles within the travel, open (0) to closed."""
        return np.clip(np.asarray(angle, dtype=float), 0.0, self.closed_angle)


@dataclass(frozen=True, eq=False)
class ArmDescription:
    """One arm, immutable: its kinematics, limits, inertia and bus, as its description file gives them."""

    name: str
    title: str
    #: the seed paper that uses this arm
    seed: str
    joints: tuple[JointSpec, ...]
    dh_d: tuple[float, ...]
    dh_a: tuple[float, ...]
    dh_alpha: tuple[float, ...]
    base_rpy: tuple[float, float, float]
    #: θ_DH = sign·q_physical + offset (rad)
    sign: np.ndarray
    offset: np.ndarray
    shoulder_height: float
    #: the end effector's distance from the shoulder with the arm straight (m)
    reach: float
    home_deg: np.ndarray
    bus_addresses: tuple[int, ...]
    #: Kinova's robot type for this arm (KinovaTypes.h), as its base reports it in the device list (DeviceType)
    robot_type: int
    base_mass_kg: float
    base_com_z: float
    base_height: float
    base_radius: float
    armature: np.ndarray
    damping: np.ndarray
    #: the emulated arm's truth where it departs from this description, the controllers' model (robot_sim builds it
    #: so): each link's mass and inertia scaled, and the Coulomb friction an actuator's torque loop leaves at its
    #: joint, as a fraction of the smallest backdriving torque of its data sheet
    true_link_mass_scale: np.ndarray
    torque_mode_friction_fraction: float
    #: the range of the top translation (m/s) and orientation (rad/s) speeds a client may set, and the accelerations
    linear_speed_range_mps: tuple[float, float]
    angular_speed_range_rps: tuple[float, float]
    linear_accel_mps2: float
    angular_accel_rps2: float
    joint_accel_dps2: float
    #: the file it was read from
    path: Path
    #: its hand (None: the arm carries none, or its file does not describe one)
    hand: Optional[HandDescription] = None

    @property
    def max_linear_speed_mps(self) -> float:
        return self.linear_speed_range_mps[1]

    @property
    def max_angular_speed_rps(self) -> float:
        return self.angular_speed_range_rps[1]

    def __eq__(self, other) -> bool:
        return isinstance(other, ArmDescription) and other.name == self.name and other.digest == self.digest

    def __hash__(self) -> int:
        return hash((self.name, self.digest))

    def __repr__(self) -> str:
        return f"ArmDescription({self.name!r}, {self.n_joints} joints)"

    # -------------------------------------------------------------------- derived, constant
    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @cached_property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    @cached_property
    def link_names(self) -> tuple[str, ...]:
        return tuple(f"link_{i}" for i in range(1, self.n_joints + 1))

    @cached_property
    def continuous(self) -> np.ndarray:
        return np.array([j.continuous for j in self.joints])

    @cached_property
    def max_speed_dps(self) -> np.ndarray:
        return np.array([j.max_speed_dps for j in self.joints])

    @cached_property
    def max_speed(self) -> np.ndarray:
        """Each joint's top speed (rad/s)."""
        return np.radians(self.max_speed_dps)

    @cached_property
    def max_torque(self) -> np.ndarray:
        """Each joint's peak torque (N·m, its actuator's software limitation)."""
        return np.array([j.max_torque_nm for j in self.joints])

    @cached_property
    def true_friction_nm(self) -> np.ndarray:
        """The Coulomb friction (N·m) the emulated arm's joints show in torque mode: the given fraction of their
        actuators' smallest backdriving torque (the rest the actuator's torque loop, closed on its output's sensor,
        takes out)."""
        return self.torque_mode_friction_fraction * np.array([j.spec.backdriving_torque_nm[0] for j in self.joints])

    @cached_property
    def home(self) -> np.ndarray:
        """The home pose in model angles (rad)."""
        return self.physical_deg_to_model(self.home_deg)

    @cached_property
    def digest(self) -> str:
        """A fingerprint of the description's text (and its hand's): two hosts with the same name and digest run the
        same arm."""
        import hashlib

        text = self.path.read_bytes() + (self.hand.path.read_bytes() if self.hand is not None else b"")
        return hashlib.sha256(text).hexdigest()[:16]

    # -------------------------------------------------------------------- angles
    def physical_deg_to_model(self, q_deg) -> np.ndarray:
        """Physical angles (deg, as GetAngularPosition reports them) → model angles (rad)."""
        return self.sign * np.radians(np.asarray(q_deg, dtype=float)) + self.offset

    def model_to_physical_deg(self, q) -> np.ndarray:
        return np.degrees(self.sign * (np.asarray(q, dtype=float) - self.offset))

    def physical_rate_to_model(self, dq_dps) -> np.ndarray:
        """Physical joint rates (deg/s) → model rates (rad/s)."""
        return self.sign * np.radians(np.asarray(dq_dps, dtype=float))

    def model_rate_to_physical(self, dq) -> np.ndarray:
        return np.degrees(self.sign * np.asarray(dq, dtype=float))

    def model_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper model-angle limits (rad); ±inf for continuous joints."""
        return self._model_limits[0].copy(), self._model_limits[1].copy()

    @cached_property
    def _model_limits(self) -> tuple[np.ndarray, np.ndarray]:
        lower = np.full(self.n_joints, -np.inf)
        upper = np.full(self.n_joints, np.inf)
        for i, j in enumerate(self.joints):
            if j.continuous:
                continue
            a = self.sign[i] * math.radians(j.lower_deg) + self.offset[i]
            b = self.sign[i] * math.radians(j.upper_deg) + self.offset[i]
            lower[i], upper[i] = min(a, b), max(a, b)
        return lower, upper

    def limit_margins_deg(self, q) -> np.ndarray:
        """Each limited joint's distance to its nearer limit (deg), at one configuration (model radians) or at a
        stack of them (…×n → …×limited joints)."""
        lower, upper = self._model_limits
        limited = np.isfinite(lower)
        q = np.asarray(q, dtype=float)[..., limited]
        return np.degrees(np.minimum(q - lower[limited], upper[limited] - q))

    def within_limits(self, q) -> bool:
        lower, upper = self._model_limits
        q = np.asarray(q, dtype=float)
        return bool(np.all(q >= lower) and np.all(q <= upper))

    # -------------------------------------------------------------------- reference kinematics
    def dh_forward_kinematics(self, q) -> np.ndarray:
        """Base → end-effector homogeneous transform straight from the DH table (model angles, rad)."""
        q = np.asarray(q, dtype=float)
        T = _rpy(*self.base_rpy)
        for i in range(self.n_joints):
            T = T @ _dh(q[i], self.dh_d[i], self.dh_a[i], self.dh_alpha[i])
        return T

    # -------------------------------------------------------------------- the URDF both loaders read
    @cached_property
    def _urdf(self) -> str:
        parts = [
            '<?xml version="1.0"?>',
            f'<robot name="{self.name}">',
            # MuJoCo reads this block and keeps the fixed frames as bodies.
            '<mujoco><compiler angle="radian" discardvisual="false" fusestatic="false" strippath="false"/></mujoco>',
            f'<link name="{BASE_LINK}">{_inertial(self.base_mass_kg, self.base_height, self.base_com_z, self.base_radius)}'
            f'<collision><origin xyz="0 0 {_f(self.base_height / 2)}" rpy="0 0 0"/><geometry><cylinder '
            f'radius="{_f(self.base_radius)}" length="{_f(self.base_height)}"/></geometry></collision></link>',
            '<link name="link_0"/>',
            f'<joint name="base_dh" type="fixed"><parent link="{BASE_LINK}"/><child link="link_0"/>'
            f'<origin xyz="0 0 0" rpy="{" ".join(_f(v) for v in self.base_rpy)}"/></joint>',
        ]
        lower, upper = self._model_limits
        for i, spec in enumerate(self.joints):
            d = self.dh_d[i]
            length = max(math.hypot(d, self.dh_a[i]), _MIN_SEGMENT)
            link = self.link_names[i]
            if i == self.n_joints - 1 and self.hand is not None:
                inertial = _composite_inertial(self.palm_inertia(), self.finger_masses_in_last_link())
            else:
                inertial = _inertial(spec.link_mass_kg, length, d / 2, _LINK_RADIUS, self.dh_a[i] / 2)
            parts.append(f'<link name="{link}">{inertial}'
                         f'{_segment_geometry(d, self.dh_a[i])}</link>')
            if i == 0:
                origin = '<origin xyz="0 0 0" rpy="0 0 0"/>'
            else:
                origin = (f'<origin xyz="{_f(self.dh_a[i - 1])} 0 {_f(self.dh_d[i - 1])}" '
                          f'rpy="{_f(self.dh_alpha[i - 1])} 0 0"/>')
            lo, hi = (-_CONTINUOUS_RANGE, _CONTINUOUS_RANGE) if spec.continuous else (lower[i], upper[i])
            parent = "link_0" if i == 0 else self.link_names[i - 1]
            parts.append(
                f'<joint name="{spec.name}" type="revolute"><parent link="{parent}"/><child link="{link}"/>{origin}'
                f'<axis xyz="0 0 1"/><limit lower="{_f(lo)}" upper="{_f(hi)}" effort="{_f(spec.max_torque_nm)}" '
                f'velocity="{_f(math.radians(spec.max_speed_dps))}"/></joint>'
            )
        parts.append(f'<link name="{EE_LINK}"/>')
        parts.append(
            f'<joint name="end_effector_fixed" type="fixed"><parent link="{self.link_names[-1]}"/>'
            f'<child link="{EE_LINK}"/><origin xyz="{_f(self.dh_a[-1])} 0 {_f(self.dh_d[-1])}" '
            f'rpy="{_f(self.dh_alpha[-1])} 0 0"/></joint>'
        )
        parts.append("</robot>")
        return "\n".join(parts)

    def palm_inertia(self, mass_kg: Optional[float] = None) -> tuple[float, np.ndarray, np.ndarray]:
        """The last link's body without the hand's fingers (all of it for an arm without a hand): (mass, centre of
        mass, inertia about it) in the link's frame, the solid cylinder of :func:`_inertial`. ``mass_kg``: another
        mass for the same body (the emulated arm's truth)."""
        i = self.n_joints - 1
        d, a = self.dh_d[i], self.dh_a[i]
        mass = self.joints[i].link_mass_kg - (self.hand.n_fingers * self.hand.finger_mass_kg if self.hand else 0.0)
        mass = mass if mass_kg is None else mass_kg
        length = max(math.hypot(d, a), _MIN_SEGMENT)
        ixx, izz = _cylinder(mass, length, _LINK_RADIUS)
        pitch = math.atan2(a / 2, d / 2) if a else 0.0
        R = _rpy(0.0, pitch, 0.0)[:3, :3]
        return mass, np.array([a / 2, 0.0, d / 2]), R @ np.diag([ixx, ixx, izz]) @ R.T

    def finger_masses_in_last_link(self) -> list[tuple[float, np.ndarray]]:
        """Each finger link's mass at its centre, in the last link's frame, the fingers open (what the arm's chain
        carries of the hand besides its palm; the fingers' own inertia about their centres, about 1e-6 kg·m², is
        left out)."""
        hand = self.hand
        i = self.n_joints - 1
        ee_in_last = _translation(self.dh_a[i], self.dh_d[i]) @ _rpy(self.dh_alpha[i], 0.0, 0.0)
        centres = ((hand.proximal_mass_kg, [hand.proximal_length_m / 2, 0.0, 0.0]),
                   (hand.distal_mass_kg, np.array(hand.distal_offset_m) + [hand.distal_length_m / 2, 0.0, 0.0]))
        return [(mass, (ee_in_last @ T @ np.array([*centre, 1.0]))[:3])
                for T in hand.finger_origins for mass, centre in centres]

    def urdf(self) -> str:
        """The arm as URDF text: base_link → (base rotation) link_0 → joint_1 … joint_n → end_effector.

        Each joint's origin is the previous DH link's Tz(d)·Tx(a)·Rx(α), so joint i's coordinate is exactly θ_DH,i.
        Continuous joints are written as revolute joints with a range of ±100π so every loader keeps one coordinate
        per joint."""
        return self._urdf

    # -------------------------------------------------------------------- loaders
    def mujoco_spec(self):
        """A MuJoCo MjSpec of the arm (from :meth:`urdf`): continuous joints unlimited, rotor inertia and joint
        friction as :attr:`armature` and :attr:`damping`, no contacts. Scenes add to it."""
        mujoco = mujoco_module()

        spec = mujoco.MjSpec.from_string(self.urdf())
        for i, spec_joint in enumerate(self.joints):
            joint = spec.joint(spec_joint.name)
            joint.armature = float(self.armature[i])
            joint.damping = [float(self.damping[i]), 0.0, 0.0]  # MuJoCo 4: polynomial damping coefficients
            if spec_joint.continuous:
                joint.limited = mujoco.mjtLimited.mjLIMITED_FALSE
        # The primitive link shapes overlap at the joints, and the arm does not collide with itself or its
        # surroundings in this model (protection zones and joint limits keep it clear, as on the real arm):
        # they are visual.
        for geom in spec.geoms:
            geom.contype = 0
            geom.conaffinity = 0
        return spec

    def load_mujoco(self):
        """The bare arm as an MjModel (no scene, no actuators)."""
        return self.mujoco_spec().compile()

    def load_pinocchio(self) -> "PinocchioArm":
        """The arm as a Pinocchio model (immutable; create ``model.createData()`` per user)."""
        return _pinocchio(self)


@dataclass(frozen=True)
class PinocchioArm:
    model: object
    ee_frame_id: int


@lru_cache(maxsize=None)
def _pinocchio(arm: ArmDescription) -> PinocchioArm:
    import pinocchio as pin

    model = pin.buildModelFromXML(arm.urdf())
    if model.nq != arm.n_joints or model.nv != arm.n_joints:
        raise ArmError(f"Pinocchio built nq={model.nq}, nv={model.nv} from {arm.name}'s URDF; expected "
                       f"{arm.n_joints}")
    model.armature = arm.armature.copy()  # URDF has no rotor inertia: the same values MuJoCo gets
    model.damping = arm.damping.copy()
    return PinocchioArm(model, model.getFrameId(EE_LINK))


def mujoco_module():
    """The mujoco module, its warnings sent to the ``mujoco`` logger: MuJoCo's own handler writes them into a
    MUJOCO_LOG.TXT in whatever directory the process was started from."""
    import logging

    import mujoco

    if mujoco.get_mju_user_warning() is None:
        log = logging.getLogger("mujoco")
        mujoco.set_mju_user_warning(lambda message: log.warning("MuJoCo: %s", message))
    return mujoco


# ------------------------------------------------------------------------------------------------ loading


def arm_names() -> list[str]:
    """The arms this installation describes (one file each in services/model/arms)."""
    return sorted(p.stem for p in ARMS_DIR.glob("*.yaml"))


def check_arm_name(name: str) -> str:
    """``name`` when it is a described arm; else :class:`ArmError` naming the ones there are."""
    if name not in arm_names():
        raise ArmError(f"unknown arm {name!r}; known: {', '.join(arm_names())}")
    return name


@lru_cache(maxsize=None)
def load_arm(name: str = DEFAULT_ARM) -> ArmDescription:
    """The arm described by ``services/model/arms/<name>.yaml`` (cached: one immutable description per name)."""
    check_arm_name(name)
    return read_description(ARMS_DIR / f"{name}.yaml")


def declared_arm(name: str, digest: str, n_joints: int, expected: Optional[str],
                 current: Optional[ArmDescription]) -> tuple[Optional[ArmDescription], str]:
    """The arm a service runs on, from the one the robot declares (its name, description fingerprint and joint count,
    as every robot state carries them): (the description, "") or (None, why not). ``expected``: the arm the service
    was started for (None: the robot's); ``current``: the one it runs on already (it does not change arms while it
    runs)."""
    if expected is not None and name != expected:
        return None, f"started for the {expected}, the robot runs the {name}: nothing is done for it"
    if current is not None:
        if name != current.name or digest != current.digest:
            return None, (f"running for the {current.name} ({current.digest}), the robot now runs the {name} "
                          f"({digest}): restart the service")
        arm = current
    else:
        try:
            arm = load_arm(name)
        except ArmError as exc:
            return None, f"the robot runs an arm this host does not describe: {exc}"
        if arm.digest != digest:
            return None, (f"the robot's {name} description ({digest}) differs from this host's ({arm.digest}): "
                          "run the same mfvs on both")
    if n_joints != arm.n_joints:
        return None, f"the robot's state has {n_joints} joints, the {arm.name} {arm.n_joints}"
    return arm, ""


@lru_cache(maxsize=1)
def load_actuators() -> dict[str, Actuator]:
    """The actuators' data sheets by model (services/model/actuators.yaml)."""
    try:
        return msgspec.convert(yaml.safe_load(ACTUATORS_FILE.read_text()), dict[str, Actuator])
    except (msgspec.ValidationError, yaml.YAMLError, OSError) as exc:
        raise ArmError(f"{ACTUATORS_FILE}: {exc}") from None


def _read_named(path: Path, kind: type):
    """A description file as ``kind`` (its schema), whose ``name`` is its file's."""
    try:
        data = msgspec.convert(yaml.safe_load(path.read_text()), kind)
    except (msgspec.ValidationError, yaml.YAMLError, OSError) as exc:
        raise ArmError(f"{path}: {exc}") from None
    if data.name != path.stem:
        raise ArmError(f"{path}: its name is {data.name!r}, its file {path.stem!r}")
    return data


def read_description(path: Path) -> ArmDescription:
    """An arm description file, validated: every joint its DH row, link and limits, the lengths it names, a home
    within the limits."""
    path = Path(path)
    data = _read_named(path, _File)
    n = len(data.joints)
    counts = {"kinematics.dh": len(data.kinematics.dh), "links": len(data.links), "home_deg": len(data.home_deg),
              "bus_addresses": len(data.bus_addresses), "armature": len(data.armature), "damping": len(data.damping),
              "emulation.link_mass_scale": len(data.emulation.link_mass_scale)}
    wrong = [f"{key} has {count}" for key, count in counts.items() if count != n]
    if not 1 <= n <= MAX_JOINTS or wrong:
        raise ArmError(f"{path}: {n} joints ({'; '.join(wrong) or f'at most {MAX_JOINTS}'})")
    names = dict(data.lengths)

    def num(value) -> float:
        try:
            return evaluate(value, names)
        except ArmError as exc:
            raise ArmError(f"{path}: {exc}") from None

    actuators = load_actuators()
    joints = []
    for joint, link in zip(data.joints, data.links):
        if joint.range_deg is not None and not joint.range_deg[0] < joint.range_deg[1]:
            raise ArmError(f"{path}: {joint.name}'s range_deg must be [lower, upper]")
        if not (joint.max_speed_dps > 0 and num(link.mass_kg) > 0):
            raise ArmError(f"{path}: {joint.name}: speeds and masses must be positive")
        if joint.actuator not in actuators:
            raise ArmError(f"{path}: {joint.name}'s actuator {joint.actuator!r} has no data sheet in "
                           f"{ACTUATORS_FILE.name} (there: {', '.join(actuators)})")
        joints.append(JointSpec(joint.name, joint.range_deg is None,
                                None if joint.range_deg is None else joint.range_deg[0],
                                None if joint.range_deg is None else joint.range_deg[1],
                                joint.max_speed_dps, joint.actuator, actuators[joint.actuator], num(link.mass_kg)))
    emulation = data.emulation
    if not 0.0 <= emulation.torque_mode_friction_fraction <= 1.0 or any(
            not 0.5 <= k <= 2.0 for k in emulation.link_mass_scale):
        raise ArmError(f"{path}: emulation: torque_mode_friction_fraction within 0..1, link_mass_scale within "
                       "0.5..2")
    dh = data.kinematics.dh
    if any(row.sign not in (-1, 1) for row in dh):
        raise ArmError(f"{path}: each DH row's sign is 1 or -1")
    base = data.base
    arm = ArmDescription(
        name=data.name, title=data.title, seed=data.seed, joints=tuple(joints),
        dh_d=tuple(num(r.d) for r in dh), dh_a=tuple(num(r.a) for r in dh), dh_alpha=tuple(num(r.alpha) for r in dh),
        base_rpy=tuple(num(v) for v in data.kinematics.base_rpy),
        sign=np.array([float(r.sign) for r in dh]), offset=np.array([num(r.offset) for r in dh]),
        shoulder_height=num(data.kinematics.shoulder_height), reach=num(data.kinematics.reach),
        home_deg=np.array(data.home_deg, dtype=float), bus_addresses=tuple(data.bus_addresses),
        robot_type=data.robot_type,
        base_mass_kg=num(base.mass_kg), base_com_z=num(base.com_z), base_height=num(base.height),
        base_radius=num(base.radius), armature=np.array(data.armature, dtype=float),
        damping=np.array(data.damping, dtype=float),
        true_link_mass_scale=np.array(emulation.link_mass_scale, dtype=float),
        torque_mode_friction_fraction=emulation.torque_mode_friction_fraction,
        linear_speed_range_mps=tuple(data.cartesian.linear_speed_range_mps),
        angular_speed_range_rps=tuple(data.cartesian.angular_speed_range_rps),
        linear_accel_mps2=data.cartesian.linear_accel_mps2, angular_accel_rps2=data.cartesian.angular_accel_rps2,
        joint_accel_dps2=data.cartesian.joint_accel_dps2, path=path, hand=_hand(path, data.hand))
    if not arm.within_limits(arm.home):
        raise ArmError(f"{path}: home_deg is outside the joint limits")
    addresses = arm.bus_addresses + (arm.hand.bus_addresses if arm.hand else ())
    if len(set(addresses)) != len(addresses) or not all(0 < a < 0xFF for a in addresses):
        raise ArmError(f"{path}: bus_addresses and the fingers' bus_address must be distinct addresses 0x01-0xFE")
    return arm


def _hand(path: Path, name: Optional[str]) -> Optional[HandDescription]:
    """The hand an arm file names, validated."""
    if name is None:
        return None
    hands = sorted(p.stem for p in HANDS_DIR.glob("*.yaml"))
    if name not in hands:
        raise ArmError(f"{path}: unknown hand {name!r}; known: {', '.join(hands) or 'none'}")
    path = HANDS_DIR / f"{name}.yaml"
    hand = _read_named(path, _Hand)
    if not 1 <= len(hand.fingers) <= MAX_FINGERS:
        raise ArmError(f"{path}: a hand has 1 to {MAX_FINGERS} fingers, not {len(hand.fingers)}")
    if len({f.name for f in hand.fingers}) != len(hand.fingers):
        raise ArmError(f"{path}: the fingers' names must differ")
    if not (hand.closed_units > 0 and 0 < hand.closed_deg < 180 and hand.closing_time_s > 0):
        raise ArmError(f"{path}: hand: closed_units and closing_time_s must be positive, closed_deg within 0..180")
    if len(hand.finger_origins_in_hand_link) != len(hand.fingers):
        raise ArmError(f"{path}: {len(hand.fingers)} fingers, {len(hand.finger_origins_in_hand_link)} origins")
    sizes = (hand.proximal_length_m, hand.distal_length_m, hand.link_radius_m, hand.proximal_mass_kg,
             hand.distal_mass_kg, hand.grip_force_n, hand.full_force_current_a)
    if not all(math.isfinite(v) and v > 0 for v in sizes):
        raise ArmError(f"{path}: the fingers' lengths, radius, masses, grip force and full-force current must be "
                       "positive")

    def origin(o: _Origin) -> np.ndarray:
        try:
            xyz, rpy = [evaluate(v, {}) for v in o.xyz], [evaluate(v, {}) for v in o.rpy]
        except ArmError as exc:
            raise ArmError(f"{path}: {exc}") from None
        T = _rpy(*rpy)
        T[:3, 3] = xyz
        return T

    ee_from_hand_link = np.linalg.inv(origin(hand.end_effector_in_hand_link))
    return HandDescription(name=hand.name, title=hand.title, finger_names=tuple(f.name for f in hand.fingers),
                           bus_addresses=tuple(f.bus_address for f in hand.fingers),
                           closed_units=float(hand.closed_units), closed_angle=math.radians(hand.closed_deg),
                           closing_time_s=float(hand.closing_time_s),
                           finger_origins=tuple(ee_from_hand_link @ origin(o) for o in hand.finger_origins_in_hand_link),
                           proximal_length_m=hand.proximal_length_m, distal_offset_m=tuple(hand.distal_offset_m),
                           distal_length_m=hand.distal_length_m, link_radius_m=hand.link_radius_m,
                           proximal_mass_kg=hand.proximal_mass_kg, distal_mass_kg=hand.distal_mass_kg,
                           grip_force_n=hand.grip_force_n, full_force_current_a=hand.full_force_current_a,
                           path=path)


# ------------------------------------------------------------------------------------------------ helpers


def _f(x: float) -> str:
    return repr(float(x))


def _rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rz(yaw)·Ry(pitch)·Rx(roll) as a 4×4 (URDF's rpy)."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw),
                              math.sin(yaw))
    if pitch == 0.0 and yaw == 0.0:  # the common base turn about x alone, exactly as a rotation about x
        return np.array([[1.0, 0, 0, 0], [0, cr, -sr, 0], [0, sr, cr, 0], [0, 0, 0, 1]])
    R = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) @ \
        np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    T = np.eye(4)
    T[:3, :3] = R
    return T


def _dh(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]])


def _cylinder(mass: float, length: float, radius: float) -> tuple[float, float]:
    """A solid cylinder's moments of inertia about its centre: across its axis, and about it."""
    return mass * (3 * radius * radius + length * length) / 12.0, mass * radius * radius / 2.0


def _translation(x: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3], T[2, 3] = x, z
    return T


def _composite_inertial(body: tuple[float, np.ndarray, np.ndarray], points: list[tuple[float, np.ndarray]]) -> str:
    """One URDF inertial for a body (mass, centre, inertia about it) and point masses rigid on it (parallel axes)."""
    mass, centre, inertia = body
    total = mass + sum(m for m, _ in points)
    com = (mass * centre + sum(m * c for m, c in points)) / total

    def shifted(m: float, at: np.ndarray) -> np.ndarray:
        r = at - com
        return m * (float(r @ r) * np.eye(3) - np.outer(r, r))

    I = inertia + shifted(mass, centre) + sum((shifted(m, c) for m, c in points), np.zeros((3, 3)))
    return (f'<inertial><origin xyz="{" ".join(_f(v) for v in com)}" rpy="0 0 0"/><mass value="{_f(total)}"/>'
            f'<inertia ixx="{_f(I[0, 0])}" ixy="{_f(I[0, 1])}" ixz="{_f(I[0, 2])}" iyy="{_f(I[1, 1])}" '
            f'iyz="{_f(I[1, 2])}" izz="{_f(I[2, 2])}"/></inertial>')


def _inertial(mass: float, length: float, z_com: float, radius: float, x_com: float = 0.0) -> str:
    """A solid cylinder's inertia about its centre of mass at (x_com, 0, z_com), its axis from the link's origin
    through that centre (z when x_com is 0)."""
    ixx, izz = _cylinder(mass, length, radius)
    pitch = math.atan2(x_com, z_com) if x_com else 0.0
    return (
        f'<inertial><origin xyz="{_f(x_com)} 0 {_f(z_com)}" rpy="0 {_f(pitch)} 0"/><mass value="{_f(mass)}"/>'
        f'<inertia ixx="{_f(ixx)}" ixy="0" ixz="0" iyy="{_f(ixx)}" iyz="0" izz="{_f(izz)}"/></inertial>'
    )


def _segment_geometry(d: float, a: float = 0.0) -> str:
    """A cylinder along the link's segment to the next joint (or a sphere when they coincide)."""
    if abs(d) < 1e-6 and abs(a) < 1e-6:
        shape = f'<sphere radius="{_f(_LINK_RADIUS * 1.15)}"/>'
        origin = '<origin xyz="0 0 0" rpy="0 0 0"/>'
    elif abs(a) < 1e-6:
        shape = f'<cylinder radius="{_f(_LINK_RADIUS)}" length="{_f(abs(d))}"/>'
        origin = f'<origin xyz="0 0 {_f(d / 2)}" rpy="0 0 0"/>'
    else:  # along (a, 0, d): a cylinder's z turned onto that direction
        length = math.hypot(a, d)
        pitch = math.atan2(a, d)
        shape = f'<cylinder radius="{_f(_LINK_RADIUS)}" length="{_f(length)}"/>'
        origin = f'<origin xyz="{_f(a / 2)} 0 {_f(d / 2)}" rpy="0 {_f(pitch)} 0"/>'
    return f"<collision>{origin}<geometry>{shape}</geometry></collision>"
