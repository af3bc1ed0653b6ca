"""The operator console's rules, with no zenoh and no web server in them (``service.py`` and ``web.py`` are the
adapters that decode, lock, count and send):

* what the page shows (:class:`ConsoleModel`): the camera's overlays (the detected corners, the goal where the lens
  puts it, each corner's recent path), the feature error over time, the arm's speed against its limit, each joint
  against its range (the arm's description, as the robot declares its arm), the task, the e-stop, each service's health, the last refusals and warnings;
* what a person may ask, and who (:func:`parse_page_message`, :class:`Access`, :func:`decide`): start and stop
  the task, teach a view, start a grasp and open the hand (confirmed), engage and release the e-stop, and nothing
  else; the token beyond loopback, the page's own origin
  only; which request goes to the stack and which is refused, the refusal's reason (a counter's name) with a
  sentence for the page;
* a camera frame's wire format to the page (:func:`frame_packet`), and how finely frames are sent while the pages
  are behind (:class:`FrameSize`).
"""
from __future__ import annotations

import enum
import hmac
import ipaddress
import json
import math
import struct
from collections import deque
from dataclasses import dataclass
from typing import Annotated, Optional, Union
from urllib.parse import urlsplit

import msgspec
import numpy as np

from protocol import messages as m
from services.console.jog import JogSnapshot
from services.model.arm import ArmDescription, declared_arm
from services.model.limits import declared as declared_limits
from services.observe.foxglove_view import controller_line, estop_line, normalized_to_pixels, safety_line
from services.runtime.jsonsafe import json_safe
from services.runtime.service import service_condition

# ------------------------------------------------------------------------------------------------ requests


#: the most points whose recent positions the page draws as trails (a tag's four corners; a keypoint target's
#: hundreds would hide the image)
MAX_TRAILS = 8


class Action(str, enum.Enum):
    """Everything the page may ask of the stack. None of it commands the robot: the task is the controller's
    (through safety), the e-stop is safety's."""

    TASK_START = "task_start"
    TASK_STOP = "task_stop"
    ESTOP_ENGAGE = "estop_engage"
    ESTOP_RELEASE = "estop_release"
    #: teach the current view as the goal (services/vision/teach_client.py): the arm moves the camera a few
    #: centimetres and back, once the person confirmed on the page
    TEACH = "teach"
    #: a grasp task: reach the taught view, grasp, lift and hold (services/controller/phases.py)
    GRASP = "grasp"
    #: open the hand (a grasp task's hold ends in it), once the person confirmed on the page: what it holds falls
    OPEN_HAND = "open_hand"
    #: go on with a task the person's stick paused (the controller's resume_task, as `mfvs task resume`)
    TASK_RESUME = "task_resume"


#: the longest message the page sends (a request is a few hundred bytes)
MAX_PAGE_MESSAGE_BYTES = 4096
Token = Annotated[str, msgspec.Meta(max_length=256)]


class AuthMessage(msgspec.Struct, tag="auth", tag_field="type", forbid_unknown_fields=True):
    """The page's first message where the console asks for a token: until it is right, nothing is sent to it
    (the camera shows a person)."""

    token: Token


class ActionMessage(msgspec.Struct, tag="action", tag_field="type", forbid_unknown_fields=True):
    action: Action
    #: the page's number for the request, given back with the answer
    id: Annotated[int, msgspec.Meta(ge=0, le=2**31)] = 0
    #: who asks and why, as `mfvs task --operator --reason` takes them
    operator: Annotated[str, msgspec.Meta(max_length=64)] = ""
    reason: Annotated[str, msgspec.Meta(max_length=256)] = ""
    #: the person confirmed it on the page (a release and a teach need it)
    confirm: bool = False
    #: a teach: the object's region the person drew on the image (px, the image's own; none: the frame less a
    #: border), and the goal's name
    region_px: Annotated[list[tuple[float, float]], msgspec.Meta(max_length=64)] = []
    name: Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_.\-]{0,64}$")] = ""
    token: Token = ""


class DrawnMessage(msgspec.Struct, tag="drawn", tag_field="type", forbid_unknown_fields=True):
    """The page drew (or could not decode) the frame it was sent last, and takes the next one: the console sends
    a page one frame at a time, so that frames never queue on the way to a page that draws slowly (each waits for
    the page, and only the newest is encoded)."""

    seq: Annotated[int, msgspec.Meta(ge=0)] = 0


PageMessage = Union[AuthMessage, ActionMessage, DrawnMessage, JogSnapshot]
_page_decoder = msgspec.json.Decoder(PageMessage)


class Refused(Exception):
    """A request the console does not carry out: ``reason`` names its counter (``refused.<reason>`` in the
    console's health), ``message`` is the sentence the page shows."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason
        self.message = message


def _is_jog(data: str) -> bool:
    try:
        raw = json.loads(data)
    except ValueError:
        return False
    return isinstance(raw, dict) and raw.get("type") == "jog"


def parse_page_message(data: Union[str, bytes]) -> PageMessage:
    """A message from the page: JSON text, one of the kinds above; Refused("malformed" or "unknown_action")
    otherwise."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        raise Refused("malformed", "the console takes requests as JSON text, not binary messages")
    if len(data) > MAX_PAGE_MESSAGE_BYTES:
        raise Refused("malformed", f"a request of {len(data)} characters: the console takes at most "
                                   f"{MAX_PAGE_MESSAGE_BYTES}")
    try:
        message = _page_decoder.decode(data)
    except msgspec.ValidationError as exc:
        if "$.action" in str(exc):
            raise Refused("unknown_action", f"no such action ({exc}): the console takes "
                                            f"{', '.join(a.value for a in Action)}") from None
        if _is_jog(data):
            raise Refused("jog_malformed", f"not a stick's snapshot the console takes: {exc}") from None
        raise Refused("malformed", f"not a request the console takes: {exc}") from None
    except msgspec.DecodeError as exc:
        raise Refused("malformed", f"not JSON: {exc}") from None
    if isinstance(message, ActionMessage):
        for name in ("operator", "reason"):
            if not getattr(message, name).isprintable():
                raise Refused("malformed", f"the {name} holds control characters")
    return message


# ------------------------------------------------------------------------------------------------ who may ask

#: the shortest token or password the console takes (beyond loopback it is all that stands before the arm's
#: task and e-stop release)
MIN_TOKEN_LENGTH = 8
_LOOPBACK_NAMES = {"localhost", "localhost.localdomain", "ip6-localhost"}


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or a name, without port; IPv6 with or without brackets) is this machine's
    loopback."""
    host = host.strip().strip("[]").lower()
    if host in _LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _hostname(host_header: str) -> str:
    """The host of a Host header (``name:port``, ``[v6]:port``, or a bare name)."""
    host_header = host_header.strip()
    if host_header.startswith("["):
        return host_header[1:host_header.find("]")] if "]" in host_header else host_header
    return host_header.rsplit(":", 1)[0] if host_header.count(":") == 1 else host_header


@dataclass(frozen=True)
class Access:
    """Who may use the console. On loopback (the default) whoever can reach the machine's loopback, as with the
    command line; beyond it only with the token (or password), which then every action and the page's stream need.
    Either way only the console's own page: a request from another origin (a site open in the same browser) is
    refused, and on loopback a Host that is not loopback (a DNS-rebinding site) too."""

    listen: str
    token: Optional[str] = None

    def __post_init__(self) -> None:
        if self.token is not None and len(self.token) < MIN_TOKEN_LENGTH:
            raise ValueError(f"the token must have at least {MIN_TOKEN_LENGTH} characters")
        if self.token is None and not self.loopback:
            raise ValueError(f"listening beyond loopback ({self.listen}) needs a token or password "
                             f"(--token or --token-file): whoever reaches the page could start the arm's task")

    @property
    def loopback(self) -> bool:
        return is_loopback(self.listen)

    @property
    def token_required(self) -> bool:
        return self.token is not None

    def token_ok(self, given: str) -> bool:
        if self.token is None:
            return True
        return hmac.compare_digest(given.encode(), self.token.encode())

    def check_origin(self, origin: Optional[str], host: str, scheme: str) -> None:
        """A request to the stream (the WebSocket's upgrade) must come from the console's own page: its Origin is
        this Host over this scheme. Refused("origin" or "host") otherwise."""
        if not host:
            raise Refused("host", "the request names no host")
        if self.loopback and not is_loopback(_hostname(host)):
            raise Refused("host", f"this console answers on loopback only, not as {host!r}")
        if not origin:
            raise Refused("origin", "the request has no Origin: the console takes requests from its own page only")
        parts = urlsplit(origin)
        if parts.scheme.lower() != scheme.lower() or parts.netloc.lower() != host.lower():
            raise Refused("origin", f"a request from the page of {origin!r} (cross-site): the console takes "
                                    f"requests from its own page only ({scheme}://{host})")


# ------------------------------------------------------------------------------------------------ what goes out


@dataclass(frozen=True)
class Situation:
    """What the stack says now, as far as the rules need it: whether the e-stop is latched (None: safety has not
    reported lately)."""

    estop_engaged: Optional[bool]


@dataclass(frozen=True)
class Command:
    """A request cleared to go to the stack, who it is from filled in (a teach: its region and name)."""

    action: Action
    operator: str
    reason: str
    region_px: tuple = ()
    name: str = ""


_WHO = {Action.OPEN_HAND: "opens the hand", Action.TASK_RESUME: "resumes the task"}
_WHO.update({a: "starts the task" for a in (Action.TASK_START, Action.GRASP)})

#: who a stop is from when the page does not say: a stop never waits for a name
ANONYMOUS = "console"


def decide(request: ActionMessage, access: Access, situation: Situation) -> Command:
    """Whether a request goes to the stack: the token first (beyond loopback), then the rules. Stopping (the
    task, the e-stop) is never held back for a missing name; starting the task and releasing the e-stop are
    deliberate: they say who, and a release is confirmed."""
    if not access.token_ok(request.token):
        raise Refused("token", "no valid token with the request: the console does nothing without it")
    operator, reason = request.operator.strip(), request.reason.strip()
    action = request.action
    if action in (Action.TASK_START, Action.GRASP, Action.OPEN_HAND, Action.TASK_RESUME):
        if action is Action.OPEN_HAND and not request.confirm:
            raise Refused("unconfirmed", "opening the hand drops what it holds: it needs a confirmation on the page")
        if not operator:
            raise Refused("operator", f"say who {_WHO[action]} (the operator's name)")
        if situation.estop_engaged is None:
            raise Refused("safety_silent", "safety is not reporting: no task starts without it")
        if situation.estop_engaged:
            raise Refused("estop_engaged", "the e-stop is engaged: release it before starting a task")
    elif action is Action.ESTOP_ENGAGE:
        if situation.estop_engaged:
            raise Refused("already_engaged", "the e-stop is already engaged (safety says so): nothing sent")
    elif action is Action.TEACH:
        if not request.confirm:
            raise Refused("unconfirmed", "a teach moves the arm: it needs a confirmation on the page")
        if not operator:
            raise Refused("operator", "say who teaches (the operator's name)")
        if situation.estop_engaged is None:
            raise Refused("safety_silent", "safety is not reporting: nothing moves without it")
        if situation.estop_engaged:
            raise Refused("estop_engaged", "the e-stop is engaged: release it before teaching")
        if request.region_px and len(request.region_px) < 3:
            raise Refused("region", "a region needs three corners or more (drag a box on the image)")
        return Command(action, operator, reason, tuple(tuple(p) for p in request.region_px),
                       request.name or "taught")
    elif action is Action.ESTOP_RELEASE:
        if not request.confirm:
            raise Refused("unconfirmed", "releasing the e-stop needs a confirmation on the page")
        if not operator:
            raise Refused("operator", "say who releases the e-stop (the operator's name)")
        if situation.estop_engaged is None:
            raise Refused("safety_silent", "safety is not reporting: its e-stop cannot be released now")
        if not situation.estop_engaged:
            raise Refused("not_engaged", "the e-stop is not engaged: nothing to release")
    return Command(action, operator or ANONYMOUS, reason)


# ------------------------------------------------------------------------------------------------ the arm


@dataclass(frozen=True)
class RobotArm:
    """The arm the robot declares in its states (name, fingerprint, joint count) and, when this host describes
    exactly that arm, its description (else ``problem`` says why not: an arm this host does not describe, a
    description of another version, a state of another length)."""

    name: str
    digest: str
    n_joints: int
    description: Optional[ArmDescription]
    problem: str

    @classmethod
    def of(cls, state: m.RobotState) -> "RobotArm":
        description, problem = declared_arm(state.arm, state.arm_digest, len(state.q), None, None)
        return cls(state.arm, state.arm_digest, len(state.q), description, problem)

    def declares(self, state: m.RobotState) -> bool:
        return (self.name, self.digest, self.n_joints) == (state.arm, state.arm_digest, len(state.q))


def joints_shown(state: m.RobotState, arm: Optional[ArmDescription]) -> list[dict]:
    """Each joint as the page shows it. With the arm's description: its name, its angle in the physical degrees
    GetAngularPosition reports (as Kinova's own tools show them), its range in the same degrees and its distance to
    the nearer limit (None for a continuous joint); without one, the model angle in degrees only."""
    if arm is None:
        return [{"label": f"J{i + 1}", "deg": round(math.degrees(q), 2), "lower_deg": None, "upper_deg": None,
                 "margin_deg": None} for i, q in enumerate(state.q)]
    physical = arm.model_to_physical_deg(state.q)
    margins = iter(arm.limit_margins_deg(state.q))  # the limited joints', in order
    return [{"label": joint.name, "deg": round(float(deg), 2),
             "lower_deg": None if joint.continuous else joint.lower_deg,
             "upper_deg": None if joint.continuous else joint.upper_deg,
             "margin_deg": None if joint.continuous else round(float(next(margins)), 2)}
            for joint, deg in zip(arm.joints, physical)]


def fingers_shown(state: m.RobotState, arm: Optional[ArmDescription]) -> list[dict]:
    """Each finger as the page shows it (none where the robot reports none): its angle and the target it holds, in
    degrees of its travel (0 open), in Kinova's finger units where this host describes the hand, and its current."""
    fingers = state.fingers
    if fingers is None:
        return []
    hand = arm.hand if arm is not None else None
    names = hand.finger_names if hand is not None and hand.n_fingers == len(fingers.position) else \
        tuple(f"F{i + 1}" for i in range(len(fingers.position)))
    return [{"label": name, "deg": round(math.degrees(position), 1), "target_deg": round(math.degrees(target), 1),
             "units": None if hand is None else round(float(hand.angle_to_units(position))),
             "closed_deg": None if hand is None else round(math.degrees(hand.closed_angle), 1),
             "current_a": round(current, 3)}
            for name, position, target, current in zip(names, fingers.position, fingers.target, fingers.current_a)]


# ------------------------------------------------------------------------------------------------ the model

#: how long safety's last status counts as what it says now (it reports at 10 Hz)
SAFETY_FRESH_S = 1.0
#: the speed is the end effector's travel over at least this long (the states come at 100 Hz)
SPEED_WINDOW_S = 0.05
#: the series keep a sample per this long
SERIES_STEP_S = 0.05
#: a source's line that repeats within this long is not logged again (s)
REPEAT_S = 10.0


@dataclass(frozen=True)
class Event:
    """A line of the page's log: the last refusals and warnings, the task's starts and stops, the e-stop."""

    at_s: float
    source: str
    level: str
    text: str


def _level(line: tuple) -> tuple[str, str]:
    level, text = line
    return level.name.lower(), text


class _Series:
    """(time, value) samples over the last ``span_s``, one per SERIES_STEP_S at most."""

    def __init__(self, span_s: float) -> None:
        self.span_s = span_s
        self.samples: deque[tuple[float, float]] = deque()

    def add(self, t: float, value: float) -> None:
        if self.samples and t < self.samples[-1][0]:  # a new run of the clock (a restarted simulator)
            self.samples.clear()
        if self.samples and t - self.samples[-1][0] < SERIES_STEP_S:
            return
        self.samples.append((t, value))
        while self.samples and self.samples[0][0] < t - self.span_s:
            self.samples.popleft()

    def relative(self) -> dict:
        """Times in seconds before the newest sample, as the page plots them."""
        if not self.samples:
            return {"t": [], "v": []}
        last = self.samples[-1][0]
        return {"t": [round(t - last, 3) for t, _ in self.samples], "v": [v for _, v in self.samples]}


class ConsoleModel:
    """What the page shows, from the stack's messages. Not thread-safe: the service calls it under its lock. Times
    ``now`` are the console's wall clock (s), the series' times are the messages' own stamps."""

    def __init__(self, path_s: float = 3.0, series_s: float = 20.0, max_events: int = 30) -> None:
        self.path_s = path_s
        self.info: Optional[m.CameraInfo] = None
        self.features: Optional[m.Features] = None
        self.state: Optional[m.RobotState] = None
        self.controller: Optional[m.ControllerStatus] = None
        self.safety: Optional[m.SafetyStatus] = None
        self.safety_at = -math.inf
        self.task: Optional[m.TaskStatus] = None
        #: the last goal taught from the page (its name, digest and file)
        self.taught: Optional[dict] = None
        self.task_known = False
        self.error = _Series(series_s)
        self.speed = _Series(series_s)
        self.speed_now: Optional[float] = None
        self.joint_speed_ratio: Optional[float] = None
        #: the arm the robot declares (None until a state came)
        self.arm: Optional[RobotArm] = None
        self.events: deque[Event] = deque(maxlen=max_events)
        self.health: dict[str, dict] = {}
        self._paths: deque[tuple[float, list]] = deque()
        self._poses: deque[tuple[float, np.ndarray]] = deque()
        self._said: dict[tuple[str, str], float] = {}

    # -------------------------------------------------------------- the log
    def note(self, source: str, level: str, text: str, now: float) -> None:
        self.events.append(Event(now, source, level, text))

    def note_once(self, source: str, level: str, text: str, now: float) -> None:
        """A line, unless the same was said within REPEAT_S (a refusal that comes with every snapshot)."""
        self._say(source, level, text, now)

    def _say(self, source: str, level: str, text: str, now: float) -> None:
        """A line, unless the source said the same within REPEAT_S (a fault that comes and goes with every state, a
        state that flickers, an e-stop sent again until confirmed: once, not a screenful)."""
        if now - self._said.get((source, text), -math.inf) >= REPEAT_S:
            self._said[(source, text)] = now
            self.note(source, level, text, now)

    # -------------------------------------------------------------- the stack's messages
    def on_camera_info(self, info: m.CameraInfo) -> None:
        self.info = info

    def on_features(self, features: m.Features, now: float) -> dict:
        """The frame's overlay (what the page draws over the image with this capture stamp)."""
        self.features = features
        t = features.header.stamp_ns * 1e-9
        if features.pixels and len(features.pixels) <= MAX_TRAILS:
            if self._paths and t < self._paths[-1][0]:
                self._paths.clear()
            self._paths.append((t, [list(p) for p in features.pixels]))
        while self._paths and self._paths[0][0] < t - self.path_s:
            self._paths.popleft()
        if features.status in m.USABLE_FEATURE_STATUSES:
            self.error.add(t, features.error_norm)
        keypoints = features.keypoints
        return {"type": "overlay", "capture_ns": features.header.source_stamp_ns, "status": features.status.value,
                "front_end": features.front_end.value, "detail": features.detail,
                "error_norm": features.error_norm, "error_rms": features.error_rms,
                "points": [list(p) for p in features.pixels],
                # a tag's corners are its outline; a keypoint target's outline is its taught region, where seen
                "outline": ([list(p) for p in features.pixels] if features.front_end is m.FrontEnd.TAG
                            else [list(p) for p in keypoints.region_px] if keypoints is not None else []),
                "inliers": keypoints.inliers if keypoints is not None else None,
                "goal": self.goal_pixels(features)}

    def goal_pixels(self, features: m.Features) -> list:
        """The goal points where the camera's lens puts them (none until its intrinsics are known)."""
        if not features.goal_points or self.info is None:
            return []
        return np.round(normalized_to_pixels(features.goal_points, self.info), 2).tolist()

    def paths(self) -> list[list[list[float]]]:
        """Each point's recent positions (px), oldest first, for a target of a few points (a tag's corners); a point
        count that changed starts them afresh."""
        if not self._paths:
            return []
        count = len(self._paths[-1][1])
        recent = []
        for _, corners in reversed(self._paths):
            if len(corners) != count:
                break
            recent.append(corners)
        recent.reverse()
        return [[[round(c[i][0], 1), round(c[i][1], 1)] for c in recent] for i in range(count)]

    def on_state(self, state: m.RobotState, now: float) -> str:
        """A robot state: "" or, when this host does not describe the arm it declares, why (the page shows the state
        without the arm's ranges and limits; the service counts it)."""
        self.state = state
        if self.arm is None or not self.arm.declares(state):  # the first state, or a robot restarted on another arm
            self.arm = RobotArm.of(state)
            if self.arm.description is not None:
                self.note("robot", "info", f"arm {state.arm}: {self.arm.description.title}, {self.arm.n_joints} joints",
                          now)
        if self.arm.problem:
            self._say("robot", "error", f"arm: {self.arm.problem}", now)
        t = state.header.stamp_ns * 1e-9
        position = np.array([state.pose.X, state.pose.Y, state.pose.Z])
        if self._poses and t <= self._poses[-1][0]:
            if t < self._poses[-1][0]:
                self._poses.clear()
            else:
                return
        self._poses.append((t, position))
        while len(self._poses) > 2 and self._poses[1][0] <= t - SPEED_WINDOW_S:
            self._poses.popleft()
        t0, p0 = self._poses[0]
        if t - t0 >= SPEED_WINDOW_S * 0.99:
            self.speed_now = float(np.linalg.norm(position - p0) / (t - t0))
            self.speed.add(t, self.speed_now)
        limits = self.limits()
        ratios = [abs(v) / limit for v, limit in zip(state.dq, limits.joint_speed_rps)] if limits is not None else []
        self.joint_speed_ratio = max(ratios) if ratios else None
        if state.faults:
            self._say("robot", "error", "faults: " + "; ".join(state.faults), now)
        return self.arm.problem

    def limits(self) -> Optional[m.MotionLimits]:
        """The limits the robot declares, else its arm description's; None when it declares none for an arm this
        host does not describe."""
        if self.state is None:
            return None
        if self.arm is None or self.arm.description is None:
            return self.state.limits
        return declared_limits(self.state, self.arm.description)

    def on_controller(self, status: m.ControllerStatus, now: float) -> None:
        self.controller = status
        level, text = _level(controller_line(status))
        if level != "info":
            self._say("controller", level, text, now)

    def on_safety(self, status: m.SafetyStatus, now: float) -> None:
        previous = self.safety
        self.safety, self.safety_at = status, now
        if previous is None or previous.state is not status.state:
            level, _ = _level(safety_line(status))
            self._say("safety", level, f"state {status.state.value}", now)
        if status.last_refusal and (previous is None or previous.last_refusal != status.last_refusal):
            self._say("safety", "warning", f"refused: {status.last_refusal}", now)
        if previous is not None and previous.in_control != status.in_control:
            self._say("safety", "info", f"in control: {status.in_control or 'nobody'}", now)

    def on_estop(self, estop: m.EStop, now: float) -> None:
        level, text = _level(estop_line(estop))
        self._say("estop", level, text, now)

    def on_task(self, task: Optional[m.TaskStatus], now: float) -> None:
        """The controller's task as it answered (None: it did not answer)."""
        previous, self.task, self.task_known = self.task, task, task is not None
        if task is None:
            return
        if previous is None or (previous.state, previous.task) != (task.state, task.task):
            who = f" by {task.by}" + (f": {task.reason}" if task.reason else "") if task.by else ""
            verb = task.state.value
            self.note("task", "info", f"task {task.task} {verb}{who}", now)

    def on_taught(self, goal: str, digest: str, path: str, now: float) -> None:
        """A goal taught from the page: what the page shows of it, and where it is kept."""
        self.taught = {"goal": goal, "digest": digest, "path": path}
        self.note("teach", "info", f"goal {goal} ({digest}) taught; kept in {path}", now)

    def on_health(self, found: dict[str, m.ServiceHealth], now: float) -> None:
        """Every service's health as it answered; one that answered before and not now is gone."""
        for name, health in found.items():
            condition = service_condition(health)
            self._condition(name, condition, now, detail=health.detail, degraded=list(health.degraded))
        for name in set(self.health) - set(found):
            self._condition(name, "gone", now, detail=self.health[name]["detail"], degraded=[])

    def _condition(self, name: str, condition: str, now: float, detail: str, degraded: list[str]) -> None:
        before = self.health.get(name, {}).get("condition")
        since = now if before != condition else self.health[name]["since"]
        self.health[name] = {"name": name, "condition": condition, "detail": detail, "degraded": degraded,
                             "since": since}
        if before != condition and (before is not None or condition != "healthy"):
            why = f" ({'; '.join(degraded)})" if degraded else ""
            self.note(name, "info" if condition == "healthy" else "warning", f"{condition}{why}", now)

    # -------------------------------------------------------------- what the rules and the page see
    def situation(self, now: float) -> Situation:
        if self.safety is None or now - self.safety_at > SAFETY_FRESH_S:
            return Situation(estop_engaged=None)
        return Situation(estop_engaged=self.safety.state is m.SafetyState.ESTOP)

    def joints(self) -> list[dict]:
        return [] if self.state is None else joints_shown(self.state, self._description())

    def fingers(self) -> list[dict]:
        return [] if self.state is None else fingers_shown(self.state, self._description())

    def _description(self) -> Optional[ArmDescription]:
        """The robot's arm as this host describes it (None: no arm declared, or not described here)."""
        return self.arm.description if self.arm is not None else None

    def arm_shown(self) -> Optional[dict]:
        """The arm the robot declares, as the page names it, and which angles the joints are shown in."""
        if self.arm is None:
            return None
        described = self.arm.description is not None
        return {"name": self.arm.name, "title": self.arm.description.title if described else None,
                "joints": self.arm.n_joints, "described": described, "problem": self.arm.problem,
                "angles": "physical" if described else "model"}

    def snapshot(self, now: float) -> dict:
        """Everything the page shows but the image and its overlay, as JSON-able values."""
        situation = self.situation(now)
        safety = None if self.safety is None else {
            "state": self.safety.state.value, "active_limits": list(self.safety.active_limits),
            "last_refusal": self.safety.last_refusal, "age_s": round(now - self.safety_at, 2),
            "in_control": self.safety.in_control}
        task = None if self.task is None else {
            "state": self.task.state.value, "task": self.task.task, "by": self.task.by, "reason": self.task.reason,
            "message": self.task.message, "known": self.task_known, "plan": self.task.plan.value,
            "phase": self.task.phase, "outcome": self.task.outcome,
            "grasp": None if self.task.grasp is None else self.task.grasp.value}
        controller = None if self.controller is None else {
            "law": self.controller.law, "status": self.controller.status.value,
            "iteration": self.controller.iteration, "error_norm": self.controller.error_norm,
            "detail": self.controller.detail}
        limits = self.limits()
        image = None if self.info is None else {"width": self.info.width, "height": self.info.height}
        return json_safe({
            "type": "status", "estop": {"engaged": situation.estop_engaged}, "safety": safety, "task": task,
            "controller": controller, "features": None if self.features is None else {
                "status": self.features.status.value, "error_norm": self.features.error_norm,
                "front_end": self.features.front_end.value, "detail": self.features.detail,
                "goal": self.features.keypoints.goal if self.features.keypoints else None,
                "inliers": self.features.keypoints.inliers if self.features.keypoints else None},
            "taught": self.taught,
            "error": self.error.relative(),
            "speed": {**self.speed.relative(), "now": self.speed_now,
                      "limit": limits.linear_speed_mps if limits is not None else None,
                      "joint_ratio": self.joint_speed_ratio},
            "arm": self.arm_shown(), "joints": self.joints(), "fingers": self.fingers(), "paths": self.paths(),
            "image": image,
            "health": sorted(({k: v for k, v in h.items() if k != "since"} for h in self.health.values()),
                             key=lambda h: h["name"]),
            "events": [{"at_s": e.at_s, "source": e.source, "level": e.level, "text": e.text}
                       for e in reversed(self.events)],
        })


# ------------------------------------------------------------------------------------------------ frames

_LENGTH = struct.Struct(">I")


class FrameSize:
    """How finely the console sends its frames: whole, or halved on each side (a quarter of the pixels to encode,
    send, decode and draw) while the pages are behind. Behind: a frame's encoding and its page's drawing (from
    sending to the page's word that it drew it), smoothed, take longer than a camera period, so that the page
    cannot draw at the camera's rate. Back to whole once the halved frames take less than a third of a period
    (halving cuts the time about fourfold: the gap keeps it from switching at every frame). Our rule, no
    standard's."""

    #: the weight of the newest frame in the smoothed time
    SMOOTHING = 0.2
    #: back to whole below this fraction of the camera period
    RECOVER_FRACTION = 1 / 3

    def __init__(self) -> None:
        self.scale = 1
        self.smoothed_s = 0.0

    def on_drawn(self, encode_s: float, draw_s: float, period_s: float) -> int:
        """A page drew a frame (``encode_s`` to encode, ``draw_s`` from sending to its word); the scale now."""
        if not (math.isfinite(encode_s) and math.isfinite(draw_s) and period_s > 0):
            return self.scale
        self.smoothed_s += self.SMOOTHING * (max(0.0, encode_s) + max(0.0, draw_s) - self.smoothed_s)
        if self.scale == 1 and self.smoothed_s > period_s:
            self.scale = 2
        elif self.scale == 2 and self.smoothed_s < self.RECOVER_FRACTION * period_s:
            self.scale = 1
        return self.scale


def frame_packet(jpeg: bytes, header: dict) -> bytes:
    """A camera frame as the page receives it (one binary WebSocket message): the header's length (4 bytes, big
    endian), the header as JSON (the capture stamp ``capture_ns``, ``received_ns`` and ``encoded_ns`` on the
    console's wall clock, ``wall_stamps``: whether the capture stamp is wall time too, so the page may read its
    delay off it), then the JPEG."""
    encoded = json.dumps(header, separators=(",", ":")).encode()
    return _LENGTH.pack(len(encoded)) + encoded + jpeg


def read_frame_packet(packet: bytes) -> tuple[dict, bytes]:
    """The header and the JPEG of a :func:`frame_packet`."""
    (length,) = _LENGTH.unpack_from(packet)
    return json.loads(packet[4:4 + length]), packet[4 + length:]
