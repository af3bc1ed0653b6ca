"""Arbitrary bytes against a running stack (Hypothesis): robot_sim, vision, controller, safety and the operator's
console in realtime on a real router. Every key any service subscribes to and every queryable any service declares (from the services' own
declarations, so a new input is fuzzed without touching this file) gets payloads that its message type does not
accept: random bytes, random MessagePack, messages of other types, and real messages of its own type made wrong
(truncated, oversized, a wrong schema version, NaN or infinity, a number out of range, an unknown enum value, an
image whose data does not fit its size). Each subscriber of a key counts each such payload exactly once as
rejected, no handler fails, every query is answered, and nothing moves."""
import copy
import functools
import math
import random

import msgpack
import msgspec
import numpy as np
import pytest
import zenoh
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from protocol import kinova
from protocol import messages as m
from protocol.conventions import ClockMode
from services.console.service import ConsoleConfig, ConsoleService
from services.controller.service import ControllerConfig, ControllerService
from services.robot_sim.service import RobotSimConfig, robot_sim_service
from services.runtime.transport import Router, open_session
from services.safety.service import SafetyConfig, SafetyService
from services.vision.service import VisionConfig, VisionService
from tests.stack import KEYS, Recorder, wait_for
from tests.protocol.test_messages_fuzz import MESSAGE_TYPES, pack, values
from tests.helpers import ARM

def rejects(payload: bytes, message_type) -> bool:
    try:
        m.decode(payload, message_type)
    except m.ProtocolError:
        return True
    return False


@functools.cache
def minimal_message(message_type) -> bytes:
    """A valid-looking message of ``message_type`` with all-default or minimal fields (made once per type:
    msgspec's field introspection takes milliseconds, and done at every draw it was most of the fuzzers' time)."""
    obj = {f.encode_name: None for f in msgspec.structs.fields(message_type) if f.required}
    if "header" in obj:
        obj["header"] = {"schema": m.SCHEMA_VERSION, "seq": 1, "stamp_ns": 1}
    return pack(obj)


@functools.cache
def other_messages(message_type) -> tuple[bytes, ...]:
    """A valid-looking message of every other type: the wrong schema."""
    return tuple(minimal_message(other) for other in MESSAGE_TYPES if other is not message_type)


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
            # the operator's console follows the stack too (its page's own requests are fuzzed in its tests)
            services["console"] = ConsoleService(ConsoleConfig(zenoh=client_config)).start()
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


#: messages of the inputs that carry no traffic while no task runs (the rest are taken from the live stack)
QUIET_INPUTS = {
    m.EStop: m.EStop(header=m.Header(seq=1, stamp_ns=1), operator="fuzz"),
    m.VisionGoal: m.VisionGoal(header=m.Header(seq=1, stamp_ns=1), features=[[-0.1, -0.1], [0.1, -0.1], [0.1, 0.1],
                                                                              [-0.1, 0.1]], depth_m=0.3),
    m.JointVelocity: m.JointVelocity(header=m.Header(seq=1, stamp_ns=1), velocities=[0.0] * ARM.n_joints),
    m.TorqueCommand: m.TorqueCommand(header=m.Header(seq=1, stamp_ns=1), torques=[0.0] * ARM.n_joints),
    m.Jog: m.Jog(header=m.Header(seq=1, stamp_ns=1, source_stamp_ns=1), mode=m.JogMode.TRANSLATION, deadman=True,
                 linear=(0.0, 0.05, 0.0)),
}


@pytest.fixture(scope="module")
def real_messages(stack):
    """One real payload of each input's type, as the stack publishes it (an image, a robot state, features, the
    controller's twist, safety's command, the camera info), or as an operator would send it."""
    client, services, _ = stack
    inputs, _ = declared(services)
    heard: dict[str, bytes] = {}

    def keep(sample):
        key = str(sample.key_expr)
        if key in inputs and key not in heard and not rejects(sample.payload.to_bytes(), inputs[key]):
            heard[key] = sample.payload.to_bytes()

    subscriber = client.declare_subscriber(f"{KEYS.prefix}/**", keep)
    wait_for(lambda: all(k in heard or t in QUIET_INPUTS for k, t in inputs.items()), timeout=10)
    subscriber.undeclare()
    for key, message_type in inputs.items():
        if key not in heard:
            assert message_type in QUIET_INPUTS, f"no traffic on {key} and no example of {message_type.__name__}"
            heard[key] = m.encode(QUIET_INPUTS[message_type])
    return heard


def leaves(obj, path=()):
    """(path, value) of every scalar in a decoded MessagePack object."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from leaves(v, (*path, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from leaves(v, (*path, i))
    else:
        yield path, obj


def replaced(obj, path, value):
    out = copy.deepcopy(obj)
    target = out
    for part in path[:-1]:
        target = target[part]
    target[path[-1]] = value
    return out


WAYS = ("truncated", "oversized", "trailing", "schema", "nan", "range", "enum", "size")
ALWAYS_REFUSED = ("truncated", "oversized", "trailing", "schema", "nan")


def make_wrong(payload: bytes, way: str, rng: random.Random) -> bytes:
    """A real message made wrong in one ``way`` (it may, rarely, still be valid: the tests send only what its type
    refuses). A way that does not fit the message (no image size to change) truncates it instead."""
    obj = msgpack.unpackb(payload, raw=False)
    scalars = list(leaves(obj))
    numbers = [p for p, v in scalars if isinstance(v, (int, float)) and not isinstance(v, bool)]
    floats = [p for p, v in scalars if isinstance(v, float)] or numbers
    strings = [p for p, v in scalars if isinstance(v, str)]
    if way == "trailing":  # a whole message, then bytes after it
        return payload + rng.randbytes(rng.randint(1, 16))
    if way == "oversized":  # a field far beyond any bound
        big = rng.choice([b"\x00" * 2_000_000, "x" * 100_000, [0.0] * 10_000])
        return pack({**obj, rng.choice(sorted(k for k in obj if k != "header") or ["header"]): big})
    if way == "schema" and "header" in obj:
        return pack(replaced(obj, ("header", "schema"), rng.choice([0, m.SCHEMA_VERSION + 1, -1, 2**40])))
    if way == "nan" and floats:
        return pack(replaced(obj, rng.choice(floats), rng.choice([math.nan, math.inf, -math.inf])))
    if way == "range" and numbers:
        return pack(replaced(obj, rng.choice(numbers), rng.choice([-1, -(2**63), 2**64 - 1, 1e300, -1e300])))
    if way == "enum" and strings:
        return pack(replaced(obj, rng.choice(strings), rng.choice(["no_such_value", "", "Mixed", "ESTOP"])))
    if way == "size" and "width" in obj and "height" in obj:
        side = rng.choice(["width", "height"])
        return pack({**obj, side: obj[side] + rng.choice([-1, 1, 100])})
    return payload[:rng.randrange(len(payload))]


def made_wrong(payload: bytes):
    return st.builds(make_wrong, st.just(payload), st.sampled_from(WAYS), st.randoms(use_true_random=False))


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


def query_argument_example(key: str):
    """A valid argument of the function a query key names (None for one without an argument)."""
    function = key.rsplit("/", 1)[-1]
    if under(key, KEYS.robot_api_all):
        argument_type = kinova.API_FUNCTIONS.get(function, (None, None))[0]
        return argument_type() if argument_type is not None else None
    if function in (m.START_TASK, m.STOP_TASK):
        return m.TaskRequest(operator="fuzz")
    if function == "set_goal":
        return QUIET_INPUTS[m.VisionGoal]
    return None


def under(key: str, api_key: str) -> bool:
    return key.rsplit("/", 1)[0] == api_key.rsplit("/", 1)[0]


def put_and_see_each_refused_once(client, services, batches: dict[str, list[bytes]]) -> None:
    """Put every payload of each key's batch on its key (all keys first, then one wait: the services count them
    in parallel): each subscriber of the key counts each exactly once as rejected, and no handler of any service
    fails."""
    subscribers = [(key, name, f"rejected.{d.stream}") for key in batches for name, service in services.items()
                   for d in service.inputs if d.key == key]
    before = {s: services[s[1]].counters.get(s[2]) for s in subscribers}
    handler_errors = {name: service.counters.get("errors.handler") for name, service in services.items()}
    for key, batch in batches.items():
        for payload in batch:
            # blocking, not dropped: zenoh drops a sample its queues cannot take (its default for data), and a
            # burst of 1 MB images on a slow host is such a sample; what is tested is the services' count of what
            # reached them
            client.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def counted():
        return {s: services[s[1]].counters.get(s[2]) - before[s] for s in subscribers}

    assert wait_for(lambda: all(v >= len(batches[s[0]]) for s, v in counted().items()), timeout=20), counted()
    assert all(v == len(batches[s[0]]) for s, v in counted().items()), counted()
    assert {name: service.counters.get("errors.handler") for name, service in services.items()} == handler_errors


@FUZZ
@given(data=st.data())
def test_every_subscriber_counts_each_malformed_payload_once(stack, data):
    client, services, _ = stack
    inputs, _ = declared(services)
    assert len(inputs) >= 10
    batches = {key: [p for p in data.draw(st.lists(payloads, min_size=3, max_size=8), label=key)
                     if rejects(p, message_type)] for key, message_type in sorted(inputs.items())}
    put_and_see_each_refused_once(client, services, batches)


@FUZZ
@given(data=st.data())
def test_every_subscriber_counts_each_real_message_made_wrong_once(stack, real_messages, data):
    client, services, _ = stack
    inputs, _ = declared(services)
    batches = {key: [p for p in data.draw(st.lists(made_wrong(real_messages[key]), min_size=3, max_size=8), label=key)
                     if rejects(p, message_type)] for key, message_type in sorted(inputs.items())}
    put_and_see_each_refused_once(client, services, batches)


def test_the_real_messages_made_wrong_are_refused_by_their_types(stack, real_messages):
    """The decoder every service uses refuses what no message of the type may be: a truncated message, bytes after
    it, another schema version, NaN or infinity, a field far beyond any bound, an image whose data does not fit
    its size (the oracle here is the way, not the decoder: with a check removed, this fails). Of the other ways,
    more are refused than not; some stay valid by design (a free-text field given an unknown word, an unbounded
    number made huge, a camera info of another size)."""
    _, services, _ = stack
    inputs, _ = declared(services)
    refused = {way: [rejects(make_wrong(real_messages[key], way, random.Random(seed)), message_type)
                     for key, message_type in inputs.items() for seed in range(3)] for way in WAYS}
    summary = {w: f"{sum(r)}/{len(r)}" for w, r in refused.items()}
    assert all(all(refused[way]) for way in ALWAYS_REFUSED), summary
    assert all(sum(r) > len(r) / 2 for r in refused.values()), summary
    image_key = next(k for k, t in inputs.items() if t is m.Image)
    assert all(rejects(make_wrong(real_messages[image_key], "size", random.Random(seed)), m.Image)
               for seed in range(10))


@FUZZ
@given(data=st.data())
def test_every_query_is_answered_whatever_its_payload(stack, data):
    client, services, _ = stack
    _, queries = declared(services)
    assert len(queries) >= len(kinova.API_FUNCTIONS) + 6
    drawn = []
    for key in queries:
        wrong = payloads
        example = query_argument_example(key)
        if example is not None:  # and its real argument made wrong
            wrong = st.one_of(payloads, made_wrong(m.encode(example)).filter(
                lambda p, t=type(example): rejects(p, t)))
        drawn += [(key, payload) for payload in data.draw(st.lists(wrong, min_size=1, max_size=3), label=key)]
    # a few queries in flight at once (their replies are waited for together, not one round trip after another),
    # few enough that the robot's worker takes each well within its API timeout on a slow host
    for first in range(0, len(drawn), QUERIES_IN_FLIGHT):
        pending = [(key, payload, client.get(key, payload=payload, timeout=5.0))
                   for key, payload in drawn[first:first + QUERIES_IN_FLIGHT]]
        for key, payload, handler in pending:
            check_query_reply(key, payload, list(handler))


#: queries the fuzzer keeps in flight at once
QUERIES_IN_FLIGHT = 8


def check_query_reply(key: str, payload: bytes, replies: list) -> None:
    """One reply, and for a request its type refuses, a refusal: an error code, a task or goal not given."""
    assert len(replies) == 1 and replies[0].ok is not None, (key, payload)
    body = replies[0].ok.payload.to_bytes()
    function = key.rsplit("/", 1)[-1]
    if under(key, KEYS.robot_api_all):
        argument_type = kinova.API_FUNCTIONS.get(function, (None, None))[0]
        if argument_type is None or rejects(payload, argument_type):  # a bad request: an error code
            code = m.decode(body, kinova.ApiReply).code
            assert code != int(kinova.ErrorCode.NO_ERROR_KINOVA), (key, payload)
    elif under(key, KEYS.controller_api(m.GET_TASK)):
        assert not m.decode(body, m.TaskStatus).ok, (key, payload)
    elif key == KEYS.vision_api("teach"):
        # a teach's step answered: refused for a bad request (a well-formed one may be refused too: no first view)
        reply = m.decode(body, m.TeachReply)
        assert not reply.ok or not rejects(payload, m.TeachRequest), (key, payload)
    elif under(key, KEYS.vision_api("get_goal")):
        assert not m.decode(body, m.VisionGoalReply).ok, (key, payload)
