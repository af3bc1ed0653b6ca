"""Declared ports (services/runtime/ports.py): every service states what it consumes, produces and answers; the
declarations agree with protocol/topics.py; a service that uses a key it does not declare fails when it declares
it, not later on the wire; the graph `mfvs keys --graph` prints is the one the declarations make."""
import subprocess
import sys

import pytest

from protocol import messages as m
from protocol.keys import Keys
from protocol.topics import topics
from services.runtime.ports import Port, Ports, UndeclaredPort, graph
from services.cli.commands import service_classes
from services.runtime.service import Service, ServiceConfig
from tests.helpers import REPO

def test_every_service_declares_its_ports_and_each_agrees_with_the_topics_table():
    classes = service_classes()
    assert {c.__name__ for c in classes} >= {"VisionService", "ControllerService", "SafetyService", "CameraService",
                                             "ConsoleService", "TorqueControllerService", "RobotSimService",
                                             "ArmOnBusService", "RobotGatewayService", "SdkGatewayService"}
    keys = Keys()
    table = {t.key: t for t in topics(keys)}
    for cls in classes:
        ports = cls.PORTS
        assert isinstance(ports, Ports), f"{cls.__name__} declares no PORTS"
        for port in ports.consumes + ports.produces:
            key = port.keys_of(keys)
            assert key in table, f"{cls.__name__}: {port.key} is no topic of protocol/topics.py"
            assert port.message_type is table[key].message_type, (cls.__name__, port.key)
        for port in ports.produces:
            publisher = table[port.keys_of(keys)].publisher
            assert cls.name in publisher, f"{cls.__name__} publishes {port.key}; topics.py says {publisher!r} does"
        for port in ports.answers:
            assert port.message_type is None and port.keys_of(keys).startswith(keys.prefix), (cls.__name__, port)


def test_a_topic_published_by_a_service_is_declared_by_it():
    """The other way round: each topic topics.py gives to a service is produced in that service's declaration."""
    declared: dict[str, set[str]] = {}
    keys = Keys()
    for cls in service_classes():
        for port in cls.PORTS.produces:
            declared.setdefault(port.keys_of(keys), set()).add(cls.name)
    for topic in topics(keys):
        for service in ("vision", "controller", "safety", "robot_sim", "robot_gateway", "camera"):
            if service in topic.publisher.split(" or "):
                assert service in declared.get(topic.key, set()), (topic.key, service)


class _Declared(Service):
    name = "ported"
    PORTS = Ports(consumes=(Port("desired_twist", m.Twist),), produces=(Port("safety_status", m.SafetyStatus),),
                  answers=(Port("controller_api"),))

    def __init__(self, config, use):
        super().__init__(config)
        self.use = use

    def on_start(self) -> None:
        self.use(self)


@pytest.mark.parametrize("use, ok", [
    (lambda s: s.subscribe(s.keys.desired_twist, m.Twist, lambda *_: None, "twist"), True),
    (lambda s: s.publisher(s.keys.safety_status, "status"), True),
    (lambda s: s.queryable(s.keys.controller_api("start_task"), lambda q: None), True),
    (lambda s: s.subscribe(s.keys.robot_state, m.RobotState, lambda *_: None, "state"), False),  # not declared
    (lambda s: s.subscribe(s.keys.desired_twist, m.JointVelocity, lambda *_: None, "twist"), False),  # another type
    (lambda s: s.publisher(s.keys.robot_command, "command"), False),
    (lambda s: s.queryable(s.keys.robot_api("GetAngularPosition"), lambda q: None), False),
], ids=["subscribe", "publish", "answer", "undeclared-input", "wrong-type", "undeclared-output", "undeclared-query"])
def test_a_service_can_use_only_the_keys_it_declares(router, use, ok):
    service = _Declared(ServiceConfig(zenoh=router.client_config()), use)
    if ok:
        with service:
            assert service.state == "running"
        return
    declared = r"ported \(_Declared\): .*(in the class.s PORTS|is declared to carry Twist)"
    with pytest.raises(UndeclaredPort, match=declared):
        service.start()
    assert service.state == "failed"


def test_the_graph_is_the_declarations_and_mfvs_keys_graph_prints_it():
    rows = graph({"a": Ports(produces=(Port("features", m.Features),)),
                  "b": Ports(consumes=(Port("features", m.Features),), produces=(Port("desired_twist", m.Twist),)),
                  "c": Ports(consumes=(Port("desired_twist", m.Twist), Port("features", m.Features)))})
    keys = Keys()
    assert rows == [(keys.desired_twist, "Twist", ["b"], ["c"]), (keys.features, "Features", ["a"], ["b", "c"])]
    out = subprocess.run([sys.executable, "-m", "services.cli", "keys", "--graph"], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    # the path from a frame to the arm, as the services declare it
    assert "vision --vision/features (Features)--> console, controller, ros2_bridge" in lines
    assert "safety --robot/command (RobotCommand)--> robot_gateway, robot_sim" in lines
    assert "controller --controller/twist (Twist)--> safety" in lines
