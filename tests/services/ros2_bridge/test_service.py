"""The bridge on a running sim stack, as a ROS 2 graph on rmw_zenoh would meet it. Everything ROS-side here is
written from rmw_zenoh's design document (docs/design.md, "Graph Cache", "Topic and Service name mapping",
"Publishers", "Service Servers"), not from the bridge's code or protocol/ros2: the tokens are split by hand, the CDR
read by a small reader below, the requests and the subscriber's own token written out. It lists the node and its
topics, decodes an image, a joint state and a transform, gets the latched robot description as a late joiner,
starts the task with a Trigger call (the arm moves) and stops it with the e-stop's (the arm comes to rest); bad
inputs are refused and counted while the bridge keeps running."""
import math
import struct
import subprocess
import sys
import threading
import time

import pytest
import zenoh
import zenoh.ext

from protocol import messages as m
from protocol.conventions import ClockMode
from services.runtime.service import query_health
from services.runtime.transport import open_session
from services.stack.local import LocalStack, StackConfig
from tests.helpers import REPO
from tests.stack import KEYS, Recorder, wait_for

#: REP-2011 hashes as the ROS 2 Jazzy interface packages state them (share/<pkg>/msg/<Name>.json)
IMAGE_HASH = "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
TRIGGER_REQUEST = b"\x00\x01\x00\x00\x00"  # CDR LE header and std_srvs/Trigger's one placeholder byte


# ------------------------------------------------------------------------------------ what design.md says, by hand
def token_parts(token: str) -> dict:
    """@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>]"""
    parts = token.split("/")
    names = ["admin", "domain", "zid", "nid", "eid", "kind", "enclave", "namespace", "node", "topic", "type", "hash",
             "qos"]
    found = dict(zip(names, parts))
    for name in ("enclave", "namespace", "node", "topic"):
        if name in found:
            found[name] = found[name].replace("%", "/")
    return found


def data_key(parts: dict) -> str:
    return f"{parts['domain']}/{parts['topic'].lstrip('/')}/{parts['type']}/{parts['hash']}"


class Cdr:
    """Little-endian CDR after its 4-byte encapsulation header, each primitive aligned to its size from there."""

    def __init__(self, payload: bytes) -> None:
        assert payload[:2] == b"\x00\x01", payload[:4]
        self.data, self.at = payload, 4

    def _take(self, fmt: str):
        size = struct.calcsize(fmt)
        self.at += -(self.at - 4) % size
        (value,) = struct.unpack_from("<" + fmt, self.data, self.at)
        self.at += size
        return value

    def u8(self): return self._take("B")
    def u32(self): return self._take("I")
    def i32(self): return self._take("i")
    def f64(self): return self._take("d")

    def string(self) -> str:
        length = self.u32()
        text = self.data[self.at:self.at + length - 1].decode()
        self.at += length
        return text

    def header(self) -> tuple[float, str]:
        sec, nanosec = self.i32(), self.u32()
        return sec + nanosec * 1e-9, self.string()


def attachment(sequence: int, gid: bytes) -> bytes:
    return struct.pack("<qq", sequence, time.time_ns()) + bytes([16]) + gid


class Topic:
    """Samples of one data key with their attachments, decoded by ``decode``."""

    def __init__(self, session, key: str, decode) -> None:
        self.items, self.attachments, self._decode = [], [], decode
        self._lock = threading.Lock()
        self._subscriber = session.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        decoded = self._decode(sample.payload.to_bytes())
        with self._lock:
            self.items.append(decoded)
            self.attachments.append(sample.attachment.to_bytes() if sample.attachment is not None else None)

    def last(self):
        with self._lock:
            return self.items[-1] if self.items else None


def image(payload: bytes) -> dict:
    r = Cdr(payload)
    stamp, frame = r.header()
    height, width, encoding, bigendian, step = r.u32(), r.u32(), r.string(), r.u8(), r.u32()
    size = r.u32()
    return dict(stamp=stamp, frame=frame, height=height, width=width, encoding=encoding, step=step, size=size,
                left=len(payload) - r.at)


def joint_state(payload: bytes) -> dict:
    r = Cdr(payload)
    stamp, frame = r.header()
    names = [r.string() for _ in range(r.u32())]
    position = [r.f64() for _ in range(r.u32())]
    velocity = [r.f64() for _ in range(r.u32())]
    return dict(names=names, position=position, velocity=velocity)


def tf_message(payload: bytes) -> list[dict]:
    r = Cdr(payload)
    out = []
    for _ in range(r.u32()):
        stamp, parent = r.header()
        child = r.string()
        translation = [r.f64() for _ in range(3)]
        rotation = [r.f64() for _ in range(4)]
        out.append(dict(parent=parent, child=child, translation=translation, rotation=rotation))
    return out


def pose_stamped(frame_id: str, xyz, xyzw) -> bytes:
    """geometry_msgs/PoseStamped: header (stamp, frame_id), then position and orientation, 8-aligned doubles."""
    text = frame_id.encode() + b"\x00"
    head = b"\x00\x01\x00\x00" + struct.pack("<iII", 0, 0, len(text)) + text
    return head + bytes(-(len(head) - 4) % 8) + struct.pack("<7d", *xyz, *xyzw)


def trigger(session, key: str, sequence: int, gid: bytes, timeout: float = 15.0) -> tuple[bool, str, bytes]:
    """A std_srvs/Trigger call as rmw_zenoh's client makes it: a get on the service's key with the attachment."""
    for reply in session.get(key, payload=TRIGGER_REQUEST, attachment=attachment(sequence, gid), timeout=timeout):
        assert reply.ok is not None, reply.err.payload.to_bytes()
        r = Cdr(reply.ok.payload.to_bytes())
        return bool(r.u8()), r.string(), reply.ok.attachment.to_bytes()
    raise AssertionError(f"no reply on {key}")


# ------------------------------------------------------------------------------------ the tests
def test_nothing_the_bridge_declares_is_a_key_the_robot_acts_on():
    """Its one declared output on the stack (health aside) is a person's jog request, which safety takes only while
    its dead-man is held; and every ROS 2 key starts with the domain's number, whatever the namespace: none is, or
    overlaps, an mfvs key (``mfvs/...``)."""
    from protocol.ros2.keys import Distro
    from services.ros2_bridge import core
    from services.ros2_bridge.service import Ros2BridgeService

    assert [(p.key, p.message_type) for p in Ros2BridgeService.PORTS.produces] == [("desired_jog", m.Jog)]
    for namespace in ("/", "/mfvs/jaco/robot", "/mfvs"):
        graph = core.NodeGraph.build(0, namespace, "command", Distro.JAZZY, "1")
        for declared in graph.endpoints.values():
            assert declared.key.split("/")[0] == "0" and not declared.key.startswith("mfvs"), declared.key


@pytest.fixture
def stack():
    with LocalStack(StackConfig(clock=ClockMode.REALTIME)) as running:
        bridge = subprocess.Popen([sys.executable, "-m", "services.ros2_bridge", "--connect", running.endpoint],
                                  cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        session = open_session(running.router.client_config())
        try:
            yield running, session, bridge
        finally:
            session.close()
            bridge.terminate()
            try:
                bridge.wait(timeout=15)
            except subprocess.TimeoutExpired:
                bridge.kill()
                bridge.wait()


def test_a_ros_2_graph_sees_the_arm_and_starts_and_stops_the_task_through_the_bridge(stack):
    running, session, bridge = stack
    tokens: dict[str, dict] = {}

    def health() -> m.ServiceHealth:
        return query_health(session, KEYS, 2.0).get("ros2_bridge", m.ServiceHealth(
            header=m.Header(), service="none", pid=0, healthy=False, state="not heard", uptime_s=0.0))

    def graph() -> dict:
        for reply in session.liveliness().get("@ros2_lv/0/**", timeout=2.0):
            if reply.ok is not None:
                parts = token_parts(str(reply.ok.key_expr))
                tokens[parts.get("topic", parts["kind"])] = parts
        return tokens

    wanted = {"NN", "/camera/image_raw", "/joint_states", "/tf", "/tf_static", "/robot_description",
              "/diagnostics", "/mfvs/start_task", "/mfvs/estop"}
    assert wait_for(lambda: wanted <= set(graph()), timeout=60, period=0.5), (sorted(tokens), bridge.poll())
    node = tokens["NN"]
    assert (node["node"], node["namespace"], node["enclave"]) == ("mfvs", "/", "/")
    assert {tokens[t]["kind"] for t in wanted - {"NN"}} == {"MP", "SS"} and tokens["/mfvs/estop"]["kind"] == "SS"
    assert tokens["/camera/image_raw"]["type"] == "sensor_msgs::msg::dds_::Image_"
    assert tokens["/camera/image_raw"]["hash"] == IMAGE_HASH
    assert tokens["/tf_static"]["qos"].split(":")[1] == "1"  # transient local, written out

    # no image while no ROS subscription of it is visible (rmw_zenoh's way for uint8[] types) ...
    images = Topic(session, data_key(tokens["/camera/image_raw"]), image)
    assert wait_for(lambda: health().errors.get("images.unwatched", 0) > 0, timeout=90, period=0.5), health()
    assert images.last() is None
    # ... and images once a listener node declares one, as rmw_zenoh would
    zid = str(session.zid())
    listener = [session.liveliness().declare_token(f"@ros2_lv/0/{zid}/0/0/NN/%/%/listener"),
                session.liveliness().declare_token(
                    f"@ros2_lv/0/{zid}/0/1/MS/%/%/listener/%camera%image_raw/sensor_msgs::msg::dds_::Image_/"
                    f"{IMAGE_HASH}/2::,5:,:,:,,")]
    joints = Topic(session, data_key(tokens["/joint_states"]), joint_state)
    transforms = Topic(session, data_key(tokens["/tf"]), tf_message)
    # (the first frame of a cold renderer can take long on a loaded host: the bound is generous, the wait is not)
    assert wait_for(lambda: images.last() and joints.last() and len(joints.items) > 3, timeout=90), \
        (len(images.items), len(joints.items), health())

    frame = images.last()
    assert frame["frame"] == "camera" and frame["encoding"] in ("rgb8", "bgr8", "mono8")
    channels = {"rgb8": 3, "bgr8": 3, "mono8": 1}[frame["encoding"]]
    assert frame["step"] == frame["width"] * channels and frame["size"] == frame["step"] * frame["height"]
    assert 0 <= frame["left"] - frame["size"] < 8
    state = joints.last()
    assert len(state["names"]) == len(state["position"]) == 7 and state["names"][0].startswith("joint_")
    assert wait_for(lambda: any(t["child"] == "end_effector" for items in list(transforms.items)
                                for t in items), timeout=10)
    link = next(t for items in list(transforms.items) for t in items if t["child"] == "end_effector")
    assert math.isclose(sum(c * c for c in link["rotation"]), 1.0, rel_tol=1e-9)
    # every sample's attachment: sequence numbers counting up per publisher, one 16-byte GID per publisher
    for topic in (images, joints):
        seen = list(topic.attachments)
        assert all(a is not None and len(a) == 33 and a[16] == 16 for a in seen)
        numbers = [struct.unpack_from("<q", a)[0] for a in seen]
        assert numbers == sorted(numbers) and len(set(numbers)) == len(numbers)
        assert len({a[17:] for a in seen}) == 1
    assert images.attachments[0][17:] != joints.attachments[0][17:]

    # a late joiner gets the latched description from the publisher's cache (rmw_zenoh's transient local)
    descriptions = []
    late = zenoh.ext.declare_advanced_subscriber(
        session, data_key(tokens["/robot_description"]),
        lambda sample: descriptions.append(Cdr(sample.payload.to_bytes()).string()),
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
    assert wait_for(lambda: descriptions, timeout=10)
    assert descriptions[0].startswith("<?xml") and all(f'"{n}"' in descriptions[0] for n in state["names"])
    late.undeclare()

    # bad inputs: refused, counted, the bridge runs on
    start_key = data_key(tokens["/mfvs/start_task"])
    assert all(not r.ok for r in session.get(start_key, payload=TRIGGER_REQUEST, timeout=5.0))  # no attachment
    session.put(data_key(tokens["/mfvs/goal_pose"]), b"\x00\x01\x00\x00garbage", attachment=attachment(1, bytes(16)))

    assert wait_for(lambda: {"rejected.ros.service.attachment", "rejected.ros.goal.cdr"} <= set(health().errors),
                    timeout=10, period=0.5), health()

    # the task, started and stopped by ROS 2 service calls
    client = bytes(range(100, 116))
    safety = Recorder(session, KEYS.safety_status, m.SafetyStatus)
    start = joints.last()["position"]
    success, message, reply = trigger(session, start_key, 7, client)
    assert success, message
    assert struct.unpack_from("<q", reply)[0] == 7 and reply[17:] == client
    assert wait_for(lambda: max(abs(a - b) for a, b in zip(joints.last()["position"], start)) > 0.02, timeout=30)
    success, message, reply = trigger(session, data_key(tokens["/mfvs/estop"]), 8, client)
    assert success and "estop" in message, message
    assert safety.last().state is m.SafetyState.ESTOP
    assert wait_for(lambda: max(abs(v) for v in joints.last()["velocity"]) < 0.01, timeout=15)

    # a goal pose: one vision takes (the camera 0.3 m before the tag, facing it), one it refuses (the camera facing
    # away), each as vision's answer says
    goal_key = data_key(tokens["/mfvs/goal_pose"])
    session.put(goal_key, pose_stamped("tag", (0.0, 0.0, 0.3), (1.0, 0.0, 0.0, 0.0)), attachment=attachment(2, client))
    session.put(goal_key, pose_stamped("tag", (0.0, 0.0, 0.3), (0.0, 0.0, 0.0, 1.0)), attachment=attachment(3, client))
    assert wait_for(lambda: {"actions.goal", "rejected.ros.goal.vision"} <= set(health().errors), timeout=15,
                    period=0.5), health()
    assert bridge.poll() is None
    for token in listener:
        token.undeclare()

    # the node leaves the graph when the bridge stops: its tokens are gone
    bridge.terminate()
    assert bridge.wait(timeout=15) == 0

    def bridge_tokens() -> list[str]:
        return [str(r.ok.key_expr) for r in session.liveliness().get(f"@ros2_lv/0/{node['zid']}/**", timeout=2.0)
                if r.ok is not None]
    assert wait_for(lambda: not bridge_tokens(), timeout=10, period=0.5), bridge_tokens()
