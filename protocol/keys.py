"""Every zenoh key expression of mfvs, under ``mfvs/<robot_id>/...``. No other module spells a key.

Use ``Keys("jaco")`` for one robot's keys; all services of one stack share the robot id.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

ROOT = "mfvs"

#: the services that are a robot node (the last hop of every applied command's trace; the robot's keys are theirs):
#: robot_sim's api mode on the simulated arm, robot_gateway in front of the emulated bus or a real arm
ROBOT_SERVICES = ("robot_sim", "robot_gateway")
#: the servo pipeline's services, in the order a frame passes through them: vision measures, the controller
#: decides, safety checks and sends to the robot
PIPELINE_SERVICES = ("vision", "controller", "safety")
#: the order a stack starts them: safety first (nothing reaches the robot before it can refuse), then as a frame
#: flows
PIPELINE_START_ORDER = ("safety", *(name for name in PIPELINE_SERVICES if name != "safety"))
#: the services whose configuration names the arm: one setting for a whole stack (`--arm NAME`)
ARM_SERVICES = ("robot_sim", "robot_gateway", "controller", "safety")

# A robot id is one key chunk: no '/', no wildcards or zenoh's reserved characters.
_ROBOT_ID = re.compile(r"^[A-Za-z0-9_\-.]{1,64}$")
_CHUNK = _ROBOT_ID

def last_chunk(key_expr) -> str:
    """A key's last chunk: the service a liveliness token names, the function an API query asks for."""
    return str(key_expr).rsplit("/", 1)[-1]


class InvalidKeyChunk(ValueError):
    """A robot id, service name or function name that cannot be a key chunk."""


def _check_chunk(kind: str, value: str) -> str:
    if not isinstance(value, str) or not _CHUNK.match(value):
        raise InvalidKeyChunk(
            f"invalid {kind} {value!r}: use 1-64 characters from [A-Za-z0-9_-.], no '/', '*', '$', '#' or '?'"
        )
    return value


@dataclass(frozen=True)
class Keys:
    """The key expressions of one robot's stack. ``Keys.all_robots()`` gives the same keys for every robot id
    (a ``*`` chunk), for access-control rules and monitoring."""

    robot_id: str = "jaco"

    def __post_init__(self) -> None:
        _check_chunk("robot id", self.robot_id)

    @classmethod
    def all_robots(cls) -> "Keys":
        keys = object.__new__(cls)  # a wildcard chunk, which a robot id may not be
        object.__setattr__(keys, "robot_id", "*")
        return keys

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{self.robot_id}"

    def _k(self, suffix: str) -> str:
        return f"{self.prefix}/{suffix}"

    # camera (robot_sim renders; a camera driver on hardware)
    @property
    def camera_image(self) -> str:
        return self._k("camera/image")

    @property
    def camera_info(self) -> str:
        return self._k("camera/info")

    # vision
    @property
    def features(self) -> str:
        return self._k("vision/features")

    @property
    def vision_goal(self) -> str:
        """Publishing a goal message here changes the vision goal at run time."""
        return self._k("vision/goal")

    def vision_api(self, function: str) -> str:
        return self._k(f"vision/api/{_check_chunk('function name', function)}")

    # controller
    @property
    def desired_twist(self) -> str:
        return self._k("controller/twist")

    @property
    def desired_joint_velocity(self) -> str:
        return self._k("controller/joint_velocity")

    @property
    def controller_status(self) -> str:
        return self._k("controller/status")

    def controller_api(self, function: str) -> str:
        """The queryables of the controller's task (protocol.messages.TASK_FUNCTIONS): the stack comes up idle and
        moves only for a started task."""
        return self._k(f"controller/api/{_check_chunk('function name', function)}")

    # jog (a person's stick: services/jog)
    @property
    def desired_jog(self) -> str:
        """A person's jog requests (protocol.messages.Jog); safety takes them from the jog identity only."""
        return self._k("jog/request")

    # safety
    @property
    def robot_command(self) -> str:
        """Only the safety service may publish here (deploy ACLs enforce it)."""
        return self._k("robot/command")

    @property
    def safety_status(self) -> str:
        return self._k("safety/status")

    @property
    def estop(self) -> str:
        """Any operator tool may publish an e-stop request here; only an explicit reset releases it."""
        return self._k("safety/estop")

    # robot (robot_sim or robot_gateway)
    @property
    def robot_state(self) -> str:
        return self._k("robot/state")

    def robot_api(self, function: str) -> str:
        """The queryable of a Kinova API function (protocol.kinova.API_FUNCTIONS lists them)."""
        return self._k(f"robot/api/{_check_chunk('function name', function)}")

    @property
    def robot_api_all(self) -> str:
        return self._k("robot/api/*")

    @property
    def robot_check_arm(self) -> str:
        """The commissioning check (ArmCheckRequest → ArmCheckReply): the robot node moves each joint a little and
        compares the arm's own Cartesian report with the arm description (`mfvs check arm`)."""
        return self._k("robot/check/arm")

    @property
    def lowlevel_command(self) -> str:
        return self._k("robot/lowlevel/command")

    @property
    def lowlevel_state(self) -> str:
        return self._k("robot/lowlevel/state")

    @property
    def sim_objects(self) -> str:
        """Where the simulator's free objects are (its truth, for what measures a grasp; a real arm has none)."""
        return self._k("sim/objects")

    # time
    @property
    def clock(self) -> str:
        """The simulator's clock (simulated time) in both clock modes."""
        return self._k("sim/clock")

    # service runtime
    def health(self, service: str) -> str:
        return self._k(f"health/{_check_chunk('service name', service)}")

    @property
    def health_all(self) -> str:
        return self._k("health/*")

    def liveliness(self, service: str) -> str:
        return self._k(f"alive/{_check_chunk('service name', service)}")

    @property
    def liveliness_all(self) -> str:
        return self._k("alive/*")
