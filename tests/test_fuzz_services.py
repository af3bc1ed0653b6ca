"""Arbitrary bytes against a running stack (Hypothesis): robot_sim, vision, controller and safety in realtime on a
real router. Every key any service subscribes to and every queryable any service declares (from the services' own
declarations, so a new input is fuzzed without touching this file) gets payloads that its message type does not
accept: random bytes, random MessagePack, and messages of other types. Each subscriber of a key counts each such
payload exactly once as rejected, no handler fails, every query is answered, and nothing moves."""
import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from protocol import kinova
from protocol import messages as m
from protocol.conventions import ClockMode
from services.controller.service import ControllerConfig, ControllerService
from services.robot_sim.service import RobotSimConfig, robot_sim_service
from services.runtime.transport import Router, open_session
from services.safety.service import SafetyConfig, SafetyService
from services.vision.service import VisionConfig, VisionService
from tests.stack import KEYS, Recorder, wait_for
from tests.protocol.test_messages_fuzz import MESSAGE_TYPES, pack, values

def rejects(payload: bytes, message_type) -> bool:
    try:
        m.decode(payload, message_type)
    except m.ProtocolError:
        return True
    return False


def other_messages(message_type):
    """A valid-looking message of every other type with all-default or minimal fields: the wrong schema."""
    out = []
    for other in MESSAGE_TYPES:
        if other is message_type:
            continue
        obj = {f.encode_name: None for f in msgspec.structs.fields(other) if f.required}
        if "header" in obj:
            obj["header"] = {"schema": m.SCHEMA_VERSION, "seq": 1, "stamp_ns": 1}
        out.append(pack(obj))
    return out


payloads = st.one_of(st.binary(min_size=1, max_size=120), values.map(pack),
                     st.sampled_from(MESSAGE_TYPES).flatmap(lambda t: st.sampled_from(other_messages(t))))
#: no shrinking: each example talks to live services, and the failing batch is reported as it is
FUZZ = settings(max_examples=4, deadline=None, suppress_health_check=list(HealthCheck),
                phases=[Phase.explicit, Phase.reuse, Phase.generate])


@pytest.fixture(scope="module")
def stack():
    """The services in this process (their counters and declarations are what this test reads), each a separate
    zenoh client of a real router, in realtime."""
    with Router(port=0) as router:
        client_config = router.client_config()
        configs = {"safety": SafetyConfig(), "vision": VisionConfig(), "controller": ControllerConfig(),
                   "robot": RobotSimConfig()}
        for config in configs.values():
            config.zenoh, config.clock = client_config, ClockMode.REALTIME
        services = {}
        try:
            services["safety"] = SafetyService(configs["safety"]).start()
            services["vision"] = VisionService(configs["vision"]).start()
            services["controller"] = ControllerService(configs["controller"]).start()
            services["robot"] = robot_sim_service(configs["robot"]).start()
            client = open_session(client_config)
            states = Recorder(client, KEYS.robot_state, m.RobotState)
            assert wait_for(lambda: len(states) > 20 and services["vision"].counters.get("rejected.image") == 0)
            q0 = np.array(states.last().q)
            yield client, services, states
            # after all of it: every service runs, no handler failed, the e-stop is not latched, the arm has not
            # moved
            for name, service in services.items():
                assert service.state == "running", name
                assert service.counters.get("errors.handler") == 0, (name, service.counters.snapshot())
            assert not services["safety"].core.estop_latched
            assert not services["controller"].core.task.running
            assert np.abs(np.array(states.last().q) - q0).max() < 1e-4
            states.close()
            client.close()
        finally:
            for service in reversed(list(services.values())):
                service.stop()


def declared(services) -> tuple[dict, list[str]]:
    """{key: message type} of every subscription of the stack's services, and every key they answer queries on
    (the robot's API wildcard as the functions it answers, and one it does not know)."""
    inputs = {}
    for service in services.values():
        for declared_input in service.inputs:
            # one key, one message type: whoever subscribes to it decodes the same thing
            assert inputs.setdefault(declared_input.key, declared_input.message_type) is \
                declared_input.message_type, declared_input
    queries = []
    for key in sorted({key for service in services.values() for key in service.queryables}):
        if key == KEYS.robot_api_all:
            queries += [KEYS.robot_api(f) for f in sorted(kinova.API_FUNCTIONS)] + [KEYS.robot_api("NoSuchFunction")]
        else:
            queries.append(key)
    return inputs, queries


def under(key: str, api_key: str) -> bool:
    return key.rsplit("/", 1)[0] == api_key.rsplit("/", 1)[0]


@FUZZ
@given(data=st.data())
def test_every_subscriber_counts_each_malformed_payload_once(stack, data):
    client, services, _ = stack
    inputs, _ = declared(services)
    assert len(inputs) >= 10
    for key, message_type in sorted(inputs.items()):
        batch = [p for p in data.draw(st.lists(payloads, min_size=3, max_size=8), label=key)
                 if rejects(p, message_type)]
        subscribers = [(name, f"rejected.{d.stream}") for name, service in services.items() for d in service.inputs
                       if d.key == key]
        before = {s: services[s[0]].counters.get(s[1]) for s in subscribers}
        handler_errors = {name: service.counters.get("errors.handler") for name, service in services.items()}
        for payload in batch:
            client.put(key, payload)

        def counted():
            return {s: services[s[0]].counters.get(s[1]) - before[s] for s in subscribers}

        assert wait_for(lambda: all(v >= len(batch) for v in counted().values()), timeout=10), (key, counted())
        assert all(v == len(batch) for v in counted().values()), (key, counted())
        assert {name: service.counters.get("errors.handler") for name, service in services.items()} == \
            handler_errors, key


@FUZZ
@given(data=st.data())
def test_every_query_is_answered_whatever_its_payload(stack, data):
    client, services, _ = stack
    _, queries = declared(services)
    assert len(queries) >= len(kinova.API_FUNCTIONS) + 6
    for key in queries:
        function = key.rsplit("/", 1)[-1]
        for payload in data.draw(st.lists(payloads, min_size=1, max_size=3), label=key):
            replies = list(client.get(key, payload=payload, timeout=5.0))
            assert len(replies) == 1 and replies[0].ok is not None, (key, payload)
            body = replies[0].ok.payload.to_bytes()
            if under(key, KEYS.robot_api_all):
                argument_type = kinova.API_FUNCTIONS.get(function, (None, None))[0]
                if argument_type is None or rejects(payload, argument_type):  # a bad request: an error code
                    code = m.decode(body, kinova.ApiReply).code
                    assert code != int(kinova.ErrorCode.NO_ERROR_KINOVA), (key, payload)
            elif under(key, KEYS.controller_api(m.GET_TASK)):
                assert not m.decode(body, m.TaskStatus).ok, (key, payload)
            elif under(key, KEYS.vision_api("get_goal")):
                assert not m.decode(body, m.VisionGoalReply).ok, (key, payload)
