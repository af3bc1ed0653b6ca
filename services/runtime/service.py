"""The service runtime every mfvs service stands on.

:class:`Service` owns one zenoh session and gives a service:

* lifecycle: ``start()`` (session, liveliness token ``…/alive/<name>``, health), ``stop()``, and ``run()`` which
  starts, waits for SIGTERM/SIGINT or :meth:`request_stop`, and stops cleanly;
* periodic health on ``…/health/<name>`` (also answered on query) with state, rates and error counters;
* validated input: :meth:`subscribe` decodes every sample with the protocol codec; bad payloads are dropped,
  counted (``rejected.<stream>``) and logged rate-limited, and handler failures are counted, never fatal;
* typed output: :meth:`publisher` encodes messages; :meth:`header` stamps them and extends the per-hop trace.

Subclasses implement ``on_start``/``on_stop`` and optionally ``check_health``. Algorithms stay outside.
"""
from __future__ import annotations

import itertools
import logging
import os
import signal
import threading
import time
from dataclasses import dataclass
from typing import Callable, Optional, TypeVar

import msgspec
import zenoh

from protocol.conventions import ClockMode
from protocol.keys import Keys, last_chunk
from protocol.messages import Header, Hop, ProtocolError, ServiceHealth, SimClock, decode, encode
from services.runtime.clock import SimulatedClock, WallClock, make_clock
from services.runtime.config import ConfigStruct
from services.runtime.logs import RateLimitedLogger
from services.runtime.metrics import Counters, Rates
from services.runtime.ports import EVERY_SERVICE, Ports, UndeclaredPort
from services.runtime.threads import start_thread, wait_until_set
from services.runtime.faults import FaultInjector
from services.runtime import iteration_profile
from services.runtime.transport import GuardedPublisher, ZenohConfig, open_session, publisher_options

M = TypeVar("M", bound=msgspec.Struct)


class StartupError(RuntimeError):
    """A service cannot start for a reason its user can act on (a device or library missing, a refused arm): its
    message is one line saying what to do. ``service_main`` prints it and exits 2, without a traceback."""


class ServiceConfig(ConfigStruct):
    robot_id: str = "jaco"
    clock: ClockMode = ClockMode.REALTIME
    zenoh: ZenohConfig = msgspec.field(default_factory=ZenohConfig)
    health_period_s: float = 1.0
    log_level: str = "info"
    #: a fault plan to inject into this service's outputs (drop, delay per key; services/runtime/faults.py), reread
    #: when it changes: for tests and soaks, never for a robot in service
    faults_file: str | None = None


class TypedPublisher:
    """A zenoh publisher that takes messages, encodes them, and counts what it sends. Safe to use from callback
    threads while the service stops (see GuardedPublisher). With a :class:`FaultInjector`, what it sends may be
    dropped or held back as the injector's plan says."""

    def __init__(self, publisher: zenoh.Publisher, rates: Rates, key: str, stream: str,
                 faults: FaultInjector | None = None) -> None:
        self._publisher = GuardedPublisher(publisher)
        self._rates = rates
        self._name = f"pub.{stream}"
        self._key = key
        self._stream = stream
        self._faults = faults

    def put(self, message: msgspec.Struct) -> None:
        payload = encode(message)
        if self._faults is None:
            self._put_now(payload)
        else:
            self._faults.send(self._key, self._stream, self._put_now, payload)

    def _put_now(self, payload: bytes) -> None:
        if self._publisher.put(payload):
            self._rates.tick(self._name)

    @property
    def matching(self) -> bool:
        """Whether any subscriber currently matches this publisher's key."""
        return self._publisher.matching

    def undeclare(self) -> None:
        self._publisher.undeclare()


@dataclass(frozen=True)
class DeclaredInput:
    """One subscription of a service: its key, the message type it decodes, and the stream that names its rate
    and its ``rejected.<stream>`` counter."""

    key: str
    message_type: type
    stream: str


def query_health(session: zenoh.Session, keys: Keys, timeout_s: float = 2.0) -> dict[str, ServiceHealth]:
    """Every service's health that answers on ``keys.health_all`` within ``timeout_s``, by service name (an
    answer that does not decode is left out)."""
    found = {}
    for reply in session.get(keys.health_all, timeout=timeout_s):
        if reply.ok is None:
            continue
        try:
            health = decode(reply.ok.payload.to_bytes(), ServiceHealth)
        except ProtocolError:
            continue
        found[health.service] = health
    return found


class NoAnswer(RuntimeError):
    """Nobody answered a query in time (the service is not running, or this identity may not ask it)."""


def ask(session: zenoh.Session, key: str, payload: bytes | None, reply_type: type[M], timeout_s: float) -> M:
    """The first answer to a query on ``key``, decoded as ``reply_type``; asked again until ``timeout_s`` (a service
    that just started may not be known to the router yet: every function asked so is idempotent). NoAnswer when
    none came."""
    deadline = time.monotonic() + timeout_s
    while True:
        for reply in session.get(key, payload=payload, timeout=max(0.1, deadline - time.monotonic())):
            if reply.ok is not None:
                return decode(reply.ok.payload.to_bytes(), reply_type)
        if time.monotonic() >= deadline:
            raise NoAnswer(f"no answer on {key} within {timeout_s:g} s")
        time.sleep(0.05)


def service_condition(health: ServiceHealth | None) -> str:
    """How a service is doing, by its health: ``healthy``, ``degraded`` (running, not keeping up: the reasons are in
    ``health.degraded``), ``unhealthy`` (it says it is not), or ``unknown`` (alive, no health heard)."""
    if health is None:
        return "unknown"
    if not health.healthy:
        return "unhealthy"
    return "degraded" if health.degraded else "healthy"


def alive_services(session: zenoh.Session, keys: Keys, timeout_s: float = 1.0) -> list[str]:
    """The services whose liveliness tokens the router knows now, by name."""
    return sorted(last_chunk(r.ok.key_expr)
                  for r in session.liveliness().get(keys.liveliness_all, timeout=timeout_s) if r.ok)


def query_argument(query: zenoh.Query, function: str, message_type: type[M] | None) -> M | None:
    """A query's argument: a ``message_type`` decoded from its payload; for a function without an argument
    (``message_type`` None), nothing, and a payload is an error (garbage must not run such a function). Raises
    :class:`ProtocolError` with the reason, which the queryable answers with its own error reply."""
    payload = query.payload.to_bytes() if query.payload is not None else b""
    if message_type is None:
        if payload:
            raise ProtocolError(function, f"takes no argument, got {len(payload)} bytes")
        return None
    return decode(payload, message_type)


class Service:
    #: service name: key chunk for liveliness/health, and the name in trace hops
    name = "service"
    #: what the service consumes, produces and answers (services.runtime.ports); the service can use no other key
    #: (beyond what every service does: EVERY_SERVICE). None: not declared (a test's ad-hoc service)
    PORTS: Optional[Ports] = None
    #: in lockstep, take simulated time from the simulator's clock messages (the simulator itself does not)
    follows_sim_clock = True
    #: in lockstep, every input the service acts on is stamped by the simulator (``subscribe(sim_stamped=True)``),
    #: and its clock follows them alone: the clock's own messages (one every DSP tick, 3.3 a frame) would only move
    #: it to where its next input moves it anyway (the robot waits for the pipeline's answer at every tick)
    clock_from_inputs = False

    def __init__(self, config: ServiceConfig | None = None, *, name: str | None = None, clock=None) -> None:
        self.config = config or ServiceConfig()
        if name is not None:
            self.name = name
        self.keys = Keys(self.config.robot_id)
        self.keys.health(self.name)  # validates the name as a key chunk now, not at start
        self.clock: WallClock | SimulatedClock = clock or make_clock(self.config.clock)
        self.log = logging.getLogger(f"mfvs.{self.name}")
        self.limited_log = RateLimitedLogger(self.log)
        self.counters = Counters()
        self.rates = Rates()
        self.state = "created"
        self.session: zenoh.Session | None = None
        self._owns_session = True
        self._declared: list = []
        #: what the service takes from the network, as declared in on_start (each validated and counted)
        self.inputs: list[DeclaredInput] = []
        self.queryables: list[str] = []
        self._token = None
        self._stop_event = threading.Event()
        self._health_thread: threading.Thread | None = None
        self._started_monotonic = time.monotonic()
        self._seq: dict[str, itertools.count] = {}
        self._seq_lock = threading.Lock()
        self._lifecycle_lock = threading.Lock()
        #: loops whose rate and overruns say whether the service keeps up (declare_loop)
        self._loops: dict[str, tuple[float, tuple[str, ...]]] = {}
        self._overruns_seen: dict[str, int] = {}
        self._degraded: list[str] = []
        self._faults: FaultInjector | None = None

    # ------------------------------------------------------------------ hooks
    def on_start(self) -> None:
        """Declare subscribers, publishers and queryables."""

    def on_stop(self) -> None:
        """Release what on_start acquired beyond zenoh declarations (threads, files)."""

    def check_health(self) -> tuple[bool, str]:
        """(healthy, detail) beyond the lifecycle state."""
        return True, ""

    # ------------------------------------------------------------------ lifecycle
    def start(self, session: zenoh.Session | None = None) -> "Service":
        """``session``: a zenoh session to declare on instead of opening one from the config's ``zenoh`` (the
        services of a composed lockstep stack share one, :mod:`services.stack.composed`); it stays open when the service
        stops (whoever opened it closes it)."""
        with self._lifecycle_lock:
            if self.state != "created":
                raise RuntimeError(f"{self.name}: start() in state {self.state}")
            self.state = "starting"
            self._started_monotonic = time.monotonic()
            self._owns_session = session is None
            self.session = open_session(self.config.zenoh) if session is None else session
            if self.config.faults_file:
                self._faults = FaultInjector(self.config.faults_file, self.counters, self.log, self.name)
            try:
                if isinstance(self.clock, SimulatedClock) and self.follows_sim_clock and not self.clock_from_inputs:
                    self.subscribe(self.keys.clock, SimClock, self._on_sim_clock, "sim_clock")
                self.on_start()
                self._token = self.session.liveliness().declare_token(self.keys.liveliness(self.name))
                self.queryable(self.keys.health(self.name), self._answer_health)
                self._health_publisher = self.session.declare_publisher(self.keys.health(self.name))
                self._declared.append(self._health_publisher)
                self.state = "running"
                self._health_thread = start_thread(self._health_loop, f"{self.name}-health")
            except BaseException:
                self._stop_event.set()  # what on_start began stops (in a process of its own, the process ends too)
                self._teardown()
                self.state = "failed"
                raise
        self.log.info("%s started (robot %s, clock %s)", self.name, self.config.robot_id, self.clock.mode.value)
        return self

    def request_stop(self) -> None:
        self._stop_event.set()

    @property
    def stop_requested(self) -> bool:
        return self._stop_event.is_set()

    def stop(self) -> None:
        with self._lifecycle_lock:
            if self.state in ("stopped", "created"):
                self.state = "stopped"
                return
            self.state = "stopping"
            self._stop_event.set()
            try:
                self.on_stop()
            finally:
                self._teardown()
                self.state = "stopped"
        self.log.info("%s stopped", self.name)

    def _teardown(self) -> None:
        if self._health_thread is not None and self._health_thread is not threading.current_thread():
            self._health_thread.join(timeout=2.0)
        if self._faults is not None:
            self._faults.close()
            self._faults = None
        # inputs first (subscribers, queryables), then outputs, so no callback publishes on an undeclared publisher
        ordered = [e for e in reversed(self._declared) if not isinstance(e, TypedPublisher)] + \
                  [e for e in reversed(self._declared) if isinstance(e, TypedPublisher)]
        for entity in ordered:
            try:
                entity.undeclare()
            except Exception:  # already gone with a closed session
                pass
        self._declared.clear()
        if self._token is not None:
            try:
                self._token.undeclare()
            except Exception:
                pass
            self._token = None
        if self.session is not None:
            if self._owns_session:
                self.session.close()
            self.session = None

    def run(self) -> int:
        """Start, serve until SIGTERM/SIGINT or request_stop(), stop. Returns a process exit code."""
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda *_: self.request_stop())
        self.start()
        try:
            wait_until_set(self._stop_event)
        finally:
            self.stop()
        return 0

    def __enter__(self) -> "Service":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ I/O helpers
    def subscribe(self, key: str, message_type: type[M], handler: Callable[[M, int], None], stream: str,
                  sim_stamped: bool = False) -> None:
        """Deliver decoded, validated messages of ``message_type`` on ``key`` to ``handler(message, recv_ns)``.

        ``sim_stamped``: the simulator publishes these, stamped with its time. A service that follows the
        simulated clock then takes such a message as proof that the simulation reached its stamp: zenoh orders
        nothing between keys, so the clock tick may arrive just after the frame it announced."""
        assert self.session is not None, "subscribe() belongs in on_start()"
        self._check_port("consumes", key, message_type)
        follows = sim_stamped and isinstance(self.clock, SimulatedClock) and self.follows_sim_clock

        literal = not any(c in key for c in "*$")

        def on_sample(sample: zenoh.Sample) -> None:
            recv_ns = self.clock.now_ns()
            if literal and str(sample.key_expr) != key:
                # published on a wildcard that intersects our key (robot/*, robot/**, comm$*): whoever did that
                # is not the key's writer, whatever the router let through; a second line behind its ACL
                self.refuse(f"{stream}.key", f"published on {str(sample.key_expr)[:80]!r}, not on {key!r}")
                return
            self.rates.tick(stream)
            try:
                message = decode(sample.payload.to_bytes(), message_type)
            except ProtocolError as exc:
                self.refuse(stream, str(exc))
                return
            if follows and message.header.stamp_ns > recv_ns:
                self.clock.advance_to(message.header.stamp_ns)
                recv_ns = message.header.stamp_ns
            try:
                handler(message, recv_ns)
            except Exception:
                self.counters.inc("errors.handler")
                self.limited_log.error(f"handler:{stream}", "%s: handler for %s failed", self.name, stream)
                self.log.debug("handler failure", exc_info=True)

        self._declared.append(self.session.declare_subscriber(key, on_sample))
        self.inputs.append(DeclaredInput(key, message_type, stream))

    def publisher(self, key: str, stream: str, **options) -> TypedPublisher:
        assert self.session is not None, "publisher() belongs in on_start()"
        self._check_port("produces", key)
        options = {**publisher_options(key, lockstep=self.clock.mode is ClockMode.LOCKSTEP), **options}
        typed = TypedPublisher(self.session.declare_publisher(key, **options), self.rates, key, stream, self._faults)
        self._declared.append(typed)
        return typed

    def queryable(self, key: str, handler: Callable[[zenoh.Query], None]) -> None:
        assert self.session is not None, "queryable() belongs in on_start()"
        self._check_port("answers", key)
        self._declared.append(self.session.declare_queryable(key, handler))
        self.queryables.append(key)

    def _check_port(self, kind: str, key: str, message_type: Optional[type] = None) -> None:
        if self.PORTS is None:
            return
        try:
            (self.PORTS | EVERY_SERVICE).find(kind, self.keys, key, message_type)
        except UndeclaredPort as exc:
            raise UndeclaredPort(f"{self.name} ({type(self).__name__}): {exc}") from None

    def refuse(self, stream: str, reason: str) -> None:
        """Count and log (rate-limited) an input that was dropped."""
        self.counters.inc(f"rejected.{stream}")
        self.limited_log.warning(f"refuse:{stream}", "%s: refused %s: %s", self.name, stream, reason)

    def header(self, stream: str, *, stamp_ns: int | None = None, source: Header | None = None,
               recv_ns: int | None = None, source_stamp_ns: int | None = None) -> Header:
        """A header for the next message on ``stream``: its own sequence number; the source stamp and trace of
        the input it derives from (if any) with this service's hop appended. A message that originates data (an
        image) gives its own ``source_stamp_ns``."""
        with self._seq_lock:
            counter = self._seq.setdefault(stream, itertools.count())
            seq = next(counter)
        now = self.clock.now_ns()
        trace = list(source.trace) if source is not None else []
        if source is not None or recv_ns is not None:
            trace.append(Hop(service=self.name, recv_ns=recv_ns if recv_ns is not None else now, pub_ns=now))
        return Header(
            seq=seq,
            stamp_ns=now if stamp_ns is None else stamp_ns,
            source_stamp_ns=(source_stamp_ns if source_stamp_ns is not None
                             else source.source_stamp_ns if source is not None else 0),
            trace=trace,
        )

    def _on_sim_clock(self, tick: SimClock, _recv_ns: int) -> None:
        self.clock.advance_to(tick.sim_time_ns)  # ticks are re-sent; time never runs backwards
        self.on_sim_clock(tick)

    def on_sim_clock(self, tick: SimClock) -> None:
        """A tick of the simulator's clock (lockstep followers), after the service's clock moved to it."""

    # ------------------------------------------------------------------ health
    #: a loop below this fraction of its nominal rate is degraded
    DEGRADED_RATE_FRACTION = 0.95

    def declare_loop(self, rate: str, nominal_hz: float, overruns: tuple[str, ...] = ()) -> None:
        """A periodic loop whose rate (``self.rates.tick(rate)`` each period) should be ``nominal_hz`` and whose
        ``overruns`` counters should not grow: otherwise the service is *degraded* (running, not keeping up)."""
        self._loops[rate] = (nominal_hz, tuple(overruns))

    def degraded_reasons(self) -> list[str]:
        """Why the service does not keep up now: a declared loop below DEGRADED_RATE_FRACTION of its nominal rate
        (once it has run a full rate window), or overruns since the last look (a health period)."""
        reasons = []
        rates = self.rates.snapshot()
        settled = time.monotonic() - self._started_monotonic > self.rates.window_s
        for name, (nominal, overruns) in self._loops.items():
            rate = rates.get(name, 0.0)
            if settled and rate < self.DEGRADED_RATE_FRACTION * nominal:
                reasons.append(f"{name} at {rate:.1f} Hz (nominal {nominal:g})")
            for counter in overruns:
                value = self.counters.get(counter)
                grown = value - self._overruns_seen.get(counter, 0)
                self._overruns_seen[counter] = value
                if grown > 0:
                    reasons.append(f"{counter} +{grown}")
        return reasons

    def health(self) -> ServiceHealth:
        ok, detail = (False, "") if self.state != "running" else self.check_health()
        degraded = self._degraded if self.state == "running" else []
        return ServiceHealth(
            header=self.header("health"),
            service=self.name,
            pid=os.getpid(),
            healthy=bool(ok),
            state=self.state,
            uptime_s=max(0.0, time.monotonic() - self._started_monotonic),
            rates_hz=self.rates.snapshot(),
            errors=self.counters.snapshot(),
            detail=detail[:512],
            degraded=[reason[:256] for reason in degraded[:16]],
        )

    def _health_loop(self) -> None:
        while not self._stop_event.is_set():
            self._degraded = self.degraded_reasons()  # over the last health period, whoever asks
            try:
                self._health_publisher.put(encode(self.health()))
            except Exception:
                self.limited_log.error("health", "%s: could not publish health", self.name)
            self._stop_event.wait(self.config.health_period_s)

    def _answer_health(self, query: zenoh.Query) -> None:
        try:
            query.reply(self.keys.health(self.name), encode(self.health()))
        except Exception:
            self.limited_log.error("health-query", "%s: could not answer a health query", self.name)


def service_main(service_type: type[Service], config_type: type[ServiceConfig], argv: list[str] | None = None,
                 description: str = "", prepare: Callable[[ServiceConfig], dict] | None = None) -> int:
    """The command line every service's ``python -m`` entry shares: ``--config FILE``, ``--clock``,
    ``--connect ENDPOINT``, ``--robot-id``. Overrides are applied before validation, so they are checked too.
    ``prepare(config)``, when given, runs first of all, before the process asks for realtime priority: what the
    service needs from the computer before anything else (robot_gateway: Kinova's SDK and the arm), so that a
    :class:`StartupError` there is the one line the process prints; it returns keyword arguments for the service."""
    import argparse
    import sys

    from services.runtime.config import ConfigError, config_from_mapping, config_mapping
    from services.runtime.logs import setup_logging

    parser = argparse.ArgumentParser(prog=f"python -m services.{service_type.name}", description=description)
    parser.add_argument("--config", help="YAML config file (missing keys take their documented defaults)")
    parser.add_argument("--clock", choices=[m.value for m in ClockMode], help="override the clock mode")
    parser.add_argument("--connect", action="append", help="zenoh endpoint of the router (repeatable)")
    parser.add_argument("--robot-id", help="override the robot id (key prefix mfvs/<robot_id>/)")
    parser.add_argument("--zenoh-config", help="zenoh client config file (credentials, certificates)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override one config key (dotted path, YAML value), e.g. bus.channel=127.0.0.1:7448")
    args = parser.parse_args(argv)
    import faulthandler

    faulthandler.enable()  # a crash in a native library (EGL, MuJoCo, zenoh) says where, on stderr (the log)
    try:
        data = config_mapping(args.config, args.set)
        if args.clock:
            data["clock"] = args.clock
        if args.robot_id:
            data["robot_id"] = args.robot_id
        if args.connect or args.zenoh_config:
            data.setdefault("zenoh", {})
            if not isinstance(data["zenoh"], dict):
                raise ConfigError(args.config, "zenoh must be a mapping", "zenoh")
            if args.connect:
                data["zenoh"]["connect"] = args.connect
            if args.zenoh_config:
                data["zenoh"]["config_file"] = args.zenoh_config
        config = config_from_mapping(data, config_type, args.config or "<command line>")
        Keys(config.robot_id)
    except (ConfigError, ValueError) as exc:
        print(f"{service_type.name}: {exc}", file=sys.stderr)
        return 2
    setup_logging(config.log_level)
    iteration_profile.install(service_type.name)  # mfvs bench lockstep's timers; nothing unless it asks
    code = 1
    try:
        prepared = prepare(config) if prepare is not None else {}
        # lockstep at normal priority: nothing in it waits on wall time, and a lockstep loop is CPU-bound (a realtime
        # one starves the other processes of its own stack, and of every stack beside it, mfvs experiment --jobs)
        priority = 0 if ClockMode(config.clock) is ClockMode.LOCKSTEP else getattr(config, "realtime_priority", 0)
        if priority > 0:
            # the whole process, before zenoh starts its threads (they inherit it), all at one priority: a loop at
            # realtime priority that waits for the interpreter lock held by a thread of lower priority would wait
            # behind whatever preempts that thread (the rest of the host, or another realtime process)
            from services.runtime.pacing import request_realtime

            request_realtime(priority, f"{service_type.name} process")
        try:
            service = service_type(config, **prepared)
        except (ValueError, OSError) as exc:  # what the config names cannot be had: a file, a device
            raise StartupError(str(exc)) from exc
        code = service.run()
    except StartupError as exc:  # the service could not start, and says why in one line
        print(f"{service_type.name}: {exc}", file=sys.stderr)
        code = 2
    finally:
        _record_exit(code)
    return code


#: where a service started by ``mfvs up`` leaves its exit code, for ``mfvs status`` to report (a process killed
#: outright leaves none)
EXIT_FILE_ENV = "MFVS_EXIT_FILE"


def _record_exit(code: int) -> None:
    import os

    path = os.environ.get(EXIT_FILE_ENV)
    if path:
        try:
            with open(path, "w") as f:
                f.write(f"{code}\n")
        except OSError:
            pass
