"""The service runtime against a real zenoh router on a loopback port."""
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import msgpack
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention, ClockMode, Frame
from protocol.keys import Keys
from services.runtime.clock import SimulatedClock, WallClock, make_clock
from services.runtime.config import ConfigError, apply_override, config_from_text, load_config
from services.runtime.logs import RateLimitedLogger
from services.runtime.metrics import Counters, RateMeter
from services.runtime.service import Service, ServiceConfig, service_condition
from services.runtime.transport import Router, ZenohConfig, open_session, to_zenoh_config
from tests.stack import wait_for
from tests.helpers import ARM_DECLARED, REPO, signal_a_thread_not_the_main





def twist(seq=0, x=0.1):
    return m.Twist(header=m.Header(seq=seq), frame=Frame.MIXED, angular=AngularConvention.SEED000,
                   linear=(x, 0.0, 0.0), rotational=(0.0, 0.0, 0.0))


class EchoService(Service):
    """Receives twists and republishes them with its hop in the trace."""

    name = "echo"

    def on_start(self):
        self.received = []
        self.out = self.publisher(self.keys.safety_status, "echo")
        self.subscribe(self.keys.desired_twist, m.Twist, self.on_twist, "twist")

    def on_twist(self, msg, recv_ns):
        if msg.linear[0] < 0:
            raise RuntimeError("handler bug")
        self.received.append(msg)
        self.out.put(m.SafetyStatus(header=self.header("echo", source=msg.header, recv_ns=recv_ns),
                                    state=m.SafetyState.OK))


@pytest.fixture
def client(router):
    session = open_session(router.client_config())
    yield session
    session.close()


def test_default_zenoh_config_has_multicast_scouting_off():
    conf = to_zenoh_config(ZenohConfig())
    assert conf.get_json("scouting/multicast/enabled") == "false"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]


def test_router_routes_between_two_clients(router, client):
    got = []
    other = open_session(router.client_config())
    try:
        sub = other.declare_subscriber("mfvs/test/**", lambda s: got.append(s.payload.to_bytes()))
        time.sleep(0.2)
        client.put("mfvs/test/a", b"hello")
        assert wait_for(lambda: got == [b"hello"])
        sub.undeclare()
    finally:
        other.close()


def test_router_on_a_chosen_port():
    with Router(port=0) as a:
        port = a.port
    with Router(port=port) as b:
        assert b.endpoint == f"tcp/127.0.0.1:{port}" and len(b.zid) > 0


def test_service_lifecycle_liveliness_health_and_bad_input(router, client):
    keys = Keys()
    service = EchoService(ServiceConfig(zenoh=router.client_config(), health_period_s=0.1))
    statuses, healths = [], []
    client.declare_subscriber(
        keys.safety_status, lambda s: statuses.append(m.decode(s.payload.to_bytes(), m.SafetyStatus)))
    client.declare_subscriber(
        keys.health("echo"), lambda s: healths.append(m.decode(s.payload.to_bytes(), m.ServiceHealth)))
    service.start()
    try:
        assert wait_for(lambda: any(True for _ in client.liveliness().get(keys.liveliness_all)))
        alive = [str(r.ok.key_expr) for r in client.liveliness().get(keys.liveliness_all)]
        assert alive == [keys.liveliness("echo")]
        time.sleep(0.2)
        pub = client.declare_publisher(keys.desired_twist)
        pub.put(m.encode(twist(seq=1)))
        assert wait_for(lambda: len(service.received) == 1)
        # bad input: garbage, truncated, NaN, wrong schema, unknown convention, handler failure
        plain = m.to_builtins(twist(seq=2))
        bad = [b"\x00\xff garbage", m.encode(twist())[:10]]
        for mutate in (lambda d: d["linear"].__setitem__(0, float("nan")),
                       lambda d: d["header"].__setitem__("schema", 99),
                       lambda d: d.__setitem__("angular", "rpy_rates")):
            d = msgpack.unpackb(msgpack.packb(plain))
            mutate(d)
            bad.append(msgpack.packb(d))
        for payload in bad:
            pub.put(payload)
        pub.put(m.encode(twist(seq=3, x=-1.0)))  # the handler raises
        pub.put(m.encode(twist(seq=4)))
        assert wait_for(lambda: len(service.received) == 2)
        assert [t.header.seq for t in service.received] == [1, 4]
        assert service.counters.get("rejected.twist") == 5
        assert service.counters.get("errors.handler") == 1
        assert service.state == "running"
        # the republished status carries the trace with this service's hop
        assert wait_for(lambda: len(statuses) == 2)
        assert statuses[-1].header.trace[-1].service == "echo"
        # periodic health with counters and rates; and a health query
        assert wait_for(lambda: any(h.errors.get("rejected.twist") == 5 for h in healths))
        latest = healths[-1]
        assert latest.healthy and latest.state == "running" and latest.pid == os.getpid()
        assert latest.rates_hz["twist"] > 0
        replies = list(client.get(keys.health("echo")))
        answer = m.decode(replies[0].ok.payload.to_bytes(), m.ServiceHealth)
        assert answer.service == "echo" and answer.errors["errors.handler"] == 1
    finally:
        service.stop()
    assert service.state == "stopped"
    assert wait_for(lambda: not list(client.liveliness().get(keys.liveliness_all)))


SERVICE_SCRIPT = textwrap.dedent(
    """
    import sys
    from services.runtime.service import Service, ServiceConfig, service_condition
    from services.runtime.transport import ZenohConfig
    cfg = ServiceConfig(zenoh=ZenohConfig(connect=[sys.argv[1]]), health_period_s=0.1)
    class Idle(Service):
        name = "idle"
        def on_stop(self):
            print("on_stop ran", flush=True)
    sys.exit(Idle(cfg).run())
    """
)


@pytest.mark.parametrize("sig, to", [(signal.SIGTERM, "process"), (signal.SIGINT, "process"),
                                     (signal.SIGTERM, "a thread not the main")])
def test_service_process_stops_cleanly_on_signal(router, client, sig, to):
    keys = Keys()
    proc = subprocess.Popen([sys.executable, "-c", SERVICE_SCRIPT, router.endpoint], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert wait_for(lambda: any(True for _ in client.liveliness().get(keys.liveliness("idle"))), timeout=20)
        if to == "process":
            proc.send_signal(sig)
        else:  # the kernel may hand a signal sent to the process to any thread: one of zenoh's
            signal_a_thread_not_the_main(proc.pid, sig)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "on_stop ran" in out
    assert wait_for(lambda: not list(client.liveliness().get(keys.liveliness("idle"))))


def test_service_name_must_be_a_key_chunk():
    with pytest.raises(ValueError):
        Service(name="bad/name")


def test_start_twice_is_an_error(router):
    service = Service(ServiceConfig(zenoh=router.client_config()), name="twice")
    with service:
        with pytest.raises(RuntimeError):
            service.start()


# ------------------------------------------------------------------------------------------ config


def test_config_defaults_unknown_keys_and_types(tmp_path):
    cfg = config_from_text("robot_id: arm2\nzenoh: {mode: peer}\n", ServiceConfig)
    assert cfg.robot_id == "arm2" and cfg.zenoh.mode == "peer" and cfg.health_period_s == 1.0
    assert cfg.clock is ClockMode.REALTIME
    with pytest.raises(ConfigError) as err:
        config_from_text("zenoh: {mdoe: peer}", ServiceConfig)
    assert err.value.key == "zenoh.mdoe" and "unknown field" in str(err.value)
    with pytest.raises(ConfigError) as err:
        config_from_text("clock: sometimes", ServiceConfig)
    assert err.value.key == "clock"
    with pytest.raises(ConfigError) as err:
        config_from_text("zenoh: {mode: satellite}", ServiceConfig)
    assert err.value.key == "zenoh.mode"
    path = tmp_path / "svc.yaml"
    path.write_text("service:\n  robot_id: arm3\n  health_period_s: 0.5\n")
    assert load_config(path, ServiceConfig, section="service").robot_id == "arm3"
    path.write_text("service: {health_period_s: soon}\n")
    with pytest.raises(ConfigError) as err:
        load_config(path, ServiceConfig, section="service")
    assert err.value.key == "service.health_period_s" and str(path) in str(err.value)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.yaml", ServiceConfig)
    path.write_text("a: [1,\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(path, ServiceConfig)
    assert load_config(None, ServiceConfig) == ServiceConfig()


def test_overrides_set_one_key_of_a_config_and_are_validated_with_it():
    data = {"bus": {"interface": "virtual"}}
    for assignment in ("bus.channel=127.0.0.1:7448", "mode=actuator_bus", "dsp.zones=[]", "scene.camera.cx=null"):
        apply_override(data, assignment)
    assert data == {"bus": {"interface": "virtual", "channel": "127.0.0.1:7448"}, "mode": "actuator_bus",
                    "dsp": {"zones": []}, "scene": {"camera": {"cx": None}}}
    with pytest.raises(ConfigError, match="not key=value"):
        apply_override(data, "bus.channel")
    with pytest.raises(ConfigError) as err:
        apply_override(data, "bus.interface.name=x")
    assert err.value.key == "bus.interface"
    with pytest.raises(ConfigError, match="not valid YAML"):
        apply_override(data, "dsp.zones=[1,")


def test_zenoh_config_file_must_exist():
    with pytest.raises(ConfigError, match="not found"):
        to_zenoh_config(ZenohConfig(config_file="/nonexistent/router.json5"))


# ------------------------------------------------------------------------------------------ clock, metrics, logs


def test_a_lockstep_follower_takes_the_simulators_stamps_as_time(router, client):
    """Zenoh orders nothing between keys: a frame can arrive before the clock tick that announced it. A follower
    subscribed with sim_stamped receives it at its capture time and moves its clock there; other streams do not
    move the clock, and nothing rewinds it."""
    keys = Keys()

    class Follower(Service):
        name = "follower"

        def on_start(self):
            self.got = []
            self.subscribe(keys.robot_state, m.RobotState, lambda msg, t: self.got.append(("state", t)),
                           "robot_state", sim_stamped=True)
            self.subscribe(keys.desired_twist, m.Twist, lambda msg, t: self.got.append(("twist", t)), "twist")

    service = Follower(ServiceConfig(zenoh=router.client_config(), clock=ClockMode.LOCKSTEP)).start()
    try:
        time.sleep(0.3)
        state = m.RobotState(**ARM_DECLARED, header=m.Header(stamp_ns=5_000_000_000), q=[0.0] * 7, dq=[0.0] * 7, tau=[0.0] * 7,
                             pose=m.KinovaPose(X=0, Y=0, Z=0, ThetaX=0, ThetaY=0, ThetaZ=0),
                             control_mode=m.ControlMode.IDLE)
        client.put(keys.desired_twist, m.encode(msgspec_replace(twist(), stamp_ns=9_000_000_000)))
        assert wait_for(lambda: len(service.got) == 1)
        assert service.got[-1] == ("twist", 0) and service.clock.now_ns() == 0
        client.put(keys.robot_state, m.encode(state))
        assert wait_for(lambda: len(service.got) == 2)
        assert service.got[-1] == ("state", 5_000_000_000) and service.clock.now_ns() == 5_000_000_000
        client.put(keys.robot_state, m.encode(msgspec_replace(state, stamp_ns=4_000_000_000)))  # an older one
        assert wait_for(lambda: len(service.got) == 3)
        assert service.got[-1] == ("state", 5_000_000_000) and service.clock.now_ns() == 5_000_000_000
    finally:
        service.stop()


def msgspec_replace(message, stamp_ns):
    import msgspec

    return msgspec.structs.replace(message, header=msgspec.structs.replace(message.header, stamp_ns=stamp_ns))


def test_simulated_clock_is_monotonic_and_waitable():
    clock = SimulatedClock()
    assert clock.now_ns() == 0
    clock.advance_ns(10)
    with pytest.raises(ValueError):
        clock.set_ns(5)
    clock.advance_to(5)  # never back
    assert clock.now_ns() == 10
    clock.advance_to(12)
    assert clock.now_ns() == 12
    clock.set_ns(10 + 2)
    assert not clock.wait_until_ns(100, timeout_s=0.01)
    threading.Timer(0.05, clock.set_ns, args=(100,)).start()
    assert clock.wait_until_ns(100, timeout_s=5)
    assert make_clock("lockstep").mode is ClockMode.LOCKSTEP
    assert isinstance(make_clock(ClockMode.REALTIME), WallClock)


def test_counters_and_rate_meter():
    c = Counters()
    c.inc("a")
    c.inc("a", 2)
    assert c.snapshot() == {"a": 3} and c.get("b") == 0
    now = [0.0]
    meter = RateMeter(window_s=1.0, clock=lambda: now[0])
    for _ in range(100):
        now[0] += 0.01
        meter.tick()
    assert meter.rate_hz() == pytest.approx(100, rel=0.02)
    now[0] += 2.0
    assert meter.rate_hz() == 0.0


def test_rate_limited_logger(caplog):
    import logging

    now = [0.0]
    log = RateLimitedLogger(logging.getLogger("t"), interval_s=1.0, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING):
        assert log.warning("k", "bad input")
        assert not log.warning("k", "bad input")
        assert not log.warning("k", "bad input")
        assert log.warning("other", "other key")
        now[0] = 1.5
        assert log.warning("k", "bad input")
    assert [r.getMessage() for r in caplog.records][-1] == "bad input (2 similar suppressed in the last 1 s)"


def test_guarded_publisher_survives_undeclare_during_puts(router, client):
    from services.runtime.transport import GuardedPublisher

    publisher = GuardedPublisher.declare(client, "mfvs/test/guarded")
    errors = []

    def hammer():
        try:
            for _ in range(2000):
                publisher.put(b"x")
        except Exception as exc:  # the race this class exists to prevent
            errors.append(exc)

    threads = [threading.Thread(target=hammer) for _ in range(3)]
    for t in threads:
        t.start()
    time.sleep(0.005)
    publisher.undeclare()
    for t in threads:
        t.join()
    assert errors == [] and publisher.put(b"late") is False


def test_periodic_schedule_keeps_slots_and_skips_after_a_stall():
    from services.runtime.clock import PeriodicSchedule

    schedule = PeriodicSchedule(0.01)
    assert [schedule.wait() for _ in range(5)] == [(i, False) for i in range(5)]
    assert 0.035 <= schedule.elapsed_s() < 1.0  # slot 4 is due 40 ms after the start
    time.sleep(0.2)  # a stall of 20 periods, more than the 5 allowed
    slot, skipped = schedule.wait()
    assert skipped and slot >= 20
    patient = PeriodicSchedule(0.01, max_lag_periods=None)
    patient.wait()
    time.sleep(0.1)
    assert patient.wait() == (1, False)  # never skips: it runs the missed slots


class PacedService(Service):
    """A loop ticking ``loop`` at ``hz`` (its nominal rate is 100 Hz), counting ``loop.overruns`` when told to."""

    name = "paced"

    def __init__(self, config, hz: float):
        super().__init__(config)
        self.hz, self.overrun = hz, threading.Event()

    def on_start(self):
        self.declare_loop("loop", 100.0, overruns=("loop.overruns",))
        threading.Thread(target=self._loop, daemon=True).start()

    def _loop(self):
        while not self.stop_requested:
            self.rates.tick("loop")
            if self.overrun.is_set():
                self.overrun.clear()
                self.counters.inc("loop.overruns")
            time.sleep(1.0 / self.hz)


@pytest.mark.parametrize("hz, slow", [(300.0, False), (40.0, True)])
def test_a_loop_below_its_rate_or_overrunning_is_degraded_in_status(router, hz, slow):
    """`mfvs status` says degraded, with the reasons, for a loop under 95 % of its nominal rate (once a rate window
    has passed) or with overruns in the last health period; healthy only when neither."""
    from services.stack.launcher import status_json
    service = PacedService(ServiceConfig(zenoh=router.client_config(), health_period_s=0.2), hz=hz).start()
    try:
        def condition():
            found = {s["name"]: s for s in status_json(router.endpoint, "jaco")["services"]}
            return found.get("paced")

        time.sleep(service.rates.window_s + 0.5)
        paced = condition()
        if slow:
            assert paced["condition"] == "degraded" and not paced["healthy"]
            assert any(reason.startswith("loop at ") and "(nominal 100)" in reason for reason in paced["degraded"])
        else:
            assert paced["condition"] == "healthy" and paced["degraded"] == []
            service.overrun.set()
            assert wait_for(lambda: condition()["degraded"] == ["loop.overruns +1"], timeout=5)
            assert condition()["condition"] == "degraded"
            assert wait_for(lambda: condition()["condition"] == "healthy", timeout=5)  # not grown since
    finally:
        service.stop()


def test_a_services_condition_is_read_off_its_health():
    def health(healthy=True, degraded=()):
        return m.ServiceHealth(header=m.Header(), service="vision", pid=1, healthy=healthy, state="running",
                               uptime_s=1.0, degraded=list(degraded))

    assert service_condition(health()) == "healthy"
    assert service_condition(health(degraded=["image at 20.0 Hz (nominal 30)"])) == "degraded"
    assert service_condition(health(healthy=False, degraded=["late"])) == "unhealthy"
    assert service_condition(None) == "unknown"


def test_state_history_finds_the_state_of_a_frame():
    from services.runtime.state_history import StateHistory

    history: StateHistory[str] = StateHistory(size=3)
    assert history.at_capture(100) is None and history.for_input(100) == (None, False)
    for stamp in (10, 20, 30, 40):  # 10 falls out: three are kept
        history.add(stamp, f"s{stamp}")
    assert history.at_capture(35) == "s30" and history.at_capture(40) == "s40" and history.at_capture(99) == "s40"
    assert history.at_capture(15) is None  # older than every state kept: not guessed
    assert history.for_input(30) == ("s30", True) and history.for_input(25) == ("s30", True)
    assert history.for_input(45) == (None, False)  # lockstep: the frame's tick has not arrived yet


def test_threads_carry_their_names_to_the_kernel():
    import threading
    from services.runtime.threads import start_thread

    seen = {}

    def record():
        with open(f"/proc/self/task/{threading.get_native_id()}/comm") as f:
            seen["comm"] = f.read().strip()

    start_thread(record, "mfvs-test-named-thread").join(timeout=5.0)
    assert seen["comm"] == "mfvs-test-named"  # the kernel keeps the first 15 bytes


def test_sessions_share_memory_in_a_small_pool_and_a_router_opens_without_scouting(tmp_path):
    """zenoh's 16 MiB shared-memory pool ended up resident in every session an image passed through, and a router
    with nobody to scout for waited half a second to open. A message larger than the pool still arrives (without
    shared memory); a zenoh config file's own choices stand."""
    from services.runtime.transport import SHM_POOL_BYTES

    client = to_zenoh_config(ZenohConfig())
    assert json.loads(client.get_json("transport/shared_memory/transport_optimization/pool_size")) == SHM_POOL_BYTES
    started = time.monotonic()
    with Router(port=0) as router:
        assert time.monotonic() - started < 0.4
        sender, receiver = open_session(router.client_config()), open_session(router.client_config())
        sizes = []
        receiver.declare_subscriber("mfvs/test/big", lambda sample: sizes.append(len(sample.payload.to_bytes())))
        time.sleep(0.3)
        publisher = sender.declare_publisher("mfvs/test/big")
        wanted = [300_000, 2 * SHM_POOL_BYTES, 300_000]
        for size in wanted:
            publisher.put(bytes(size))
        assert wait_for(lambda: len(sizes) == 3, timeout=10) and sizes == wanted
        sender.close()
        receiver.close()
    own = tmp_path / "zenoh.json5"
    own.write_text('{transport: {shared_memory: {transport_optimization: {pool_size: 33554432}}}}')
    from_file = to_zenoh_config(ZenohConfig(config_file=str(own)))
    assert json.loads(from_file.get_json("transport/shared_memory/transport_optimization/pool_size")) == 32 << 20
