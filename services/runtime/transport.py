"""Zenoh sessions from config, and a zenoh router that runs in-process on a chosen loopback port.

Multicast scouting is off by default: a stack finds its router through configured endpoints, so two stacks on
one network never join by accident. Extra zenoh settings (access control, TLS) come from a zenoh JSON5 file
named by ``config_file``; the fields here are applied on top of it.
"""
from __future__ import annotations

import json
import random
import socket
import threading
from pathlib import Path
from typing import Literal

import msgspec
import zenoh

from services.runtime.config import ConfigError, ConfigStruct

DEFAULT_ROUTER_PORT = 7447


def loopback_endpoint(port: int, host: str = "127.0.0.1", scheme: str = "tcp") -> str:
    return f"{scheme}/{host}:{port}"


#: the shared-memory pool of a session that publishes large messages: four 640×480 RGB frames (a larger message
#: than the pool has room for goes without shared memory, as any message under zenoh's threshold does)
SHM_POOL_BYTES = 4 << 20


class ZenohConfig(ConfigStruct):
    #: client: talk through the router (the deployment default, where access control lives); peer; router
    mode: Literal["client", "peer", "router"] = "client"
    connect: list[str] = msgspec.field(default_factory=lambda: [loopback_endpoint(DEFAULT_ROUTER_PORT)])
    listen: list[str] = []
    multicast_scouting: bool = False
    #: a zenoh JSON5 config file merged underneath (access control, TLS certificates)
    config_file: str | None = None


def _load_file(config_file: str) -> zenoh.Config:
    path = Path(config_file)
    if not path.is_file():
        raise ConfigError(str(path), "zenoh config file not found", "zenoh.config_file")
    try:
        return zenoh.Config.from_file(str(path))
    except Exception as exc:  # zenoh raises its own error type with the parser's message
        raise ConfigError(str(path), f"invalid zenoh config ({exc})", "zenoh.config_file") from None


def file_endpoints(config_file: str, which: str) -> list[str]:
    """The ``connect`` or ``listen`` endpoints a zenoh config file sets ([] when it leaves them to zenoh)."""
    value = json.loads(_load_file(config_file).get_json(f"{which}/endpoints"))
    return list(value) if isinstance(value, list) else []


def file_access_control(config_file: str) -> bool:
    """Whether a zenoh config file turns on access control (a router that refuses unknown identities)."""
    return json.loads(_load_file(config_file).get_json("access_control/enabled") or "false") is True


def _endpoints(wanted: list[str], default: list[str], in_file: list[str], which: str, config_file: str) -> list[str]:
    """The file's endpoints win over the built-in default; endpoints given as well must agree with them (a
    service that silently joined another router than its file names would be worse than one that fails)."""
    if not in_file or not wanted or wanted == default:
        return wanted if not in_file else []
    if sorted(wanted) != sorted(in_file):
        raise ConfigError(config_file, f"{which} endpoints {wanted} conflict with the file's {in_file}",
                          f"zenoh.{which}")
    return []


def to_zenoh_config(cfg: ZenohConfig) -> zenoh.Config:
    conf = _load_file(cfg.config_file) if cfg.config_file else zenoh.Config()
    connect, listen = cfg.connect, cfg.listen
    if cfg.config_file:
        connect = _endpoints(cfg.connect, ZenohConfig().connect, file_endpoints(cfg.config_file, "connect"),
                             "connect", cfg.config_file)
        listen = _endpoints(cfg.listen, [], file_endpoints(cfg.config_file, "listen"), "listen", cfg.config_file)
    try:
        conf.insert_json5("mode", json.dumps(cfg.mode))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
        if connect:
            conf.insert_json5("connect/endpoints", json.dumps(connect))
        if listen:
            conf.insert_json5("listen/endpoints", json.dumps(listen))
        if not cfg.config_file:  # a file's own choices stand
            # images go through zenoh's shared memory: a pool of a few in flight, not zenoh's 16 MiB, whose pages
            # every session on the way (the publisher, the router, each subscriber) ended up holding resident
            conf.insert_json5("transport/shared_memory/transport_optimization/pool_size", str(SHM_POOL_BYTES))
            if cfg.mode == "router" and not cfg.multicast_scouting:
                # nobody to scout for: zenoh's default waits half a second for peers before the router opens
                conf.insert_json5("scouting/delay", "0")
    except Exception as exc:
        raise ConfigError("zenoh", f"rejected by zenoh ({exc})", "zenoh") from None
    return conf


def open_session(cfg: ZenohConfig) -> zenoh.Session:
    return zenoh.open(to_zenoh_config(cfg))


class GuardedPublisher:
    """A zenoh publisher that callback threads may keep using while it is undeclared: a put after (or during)
    undeclare is dropped instead of racing the undeclare (which the binding refuses with "Already borrowed")."""

    def __init__(self, publisher: zenoh.Publisher) -> None:
        self._publisher = publisher
        self._lock = threading.Lock()
        self._closed = False

    @classmethod
    def declare(cls, session: zenoh.Session, key: str, **options) -> "GuardedPublisher":
        return cls(session.declare_publisher(key, **options))

    def put(self, payload: bytes, **options) -> bool:
        """``options``: zenoh's put options (an attachment)."""
        with self._lock:
            if self._closed:
                return False
            self._publisher.put(payload, **options)
            return True

    @property
    def matching(self) -> bool:
        return self._publisher.matching_status.matching

    def undeclare(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self._publisher.undeclare()


def publisher_options(key: str, lockstep: bool = False) -> dict:
    """zenoh's publisher options for a key: a control-path topic (protocol.topics: features, twists, commands,
    e-stop, states) goes out at once rather than batched (``express``) and at a priority above the images, so a
    300-kB frame queued in a session or the router never holds a command back; anything else, zenoh's defaults.

    ``lockstep``: every message blocks rather than being dropped when a queue on its way is full (zenoh's default
    drops, and does on a CPU-starved host: 3 runs in 30 lost one of 200 states with three CPU hogs beside). In
    realtime the newest message is what matters and a publisher must never wait; in lockstep the loop waits for its
    answer anyway, and a message lost to an observer (the runner's trajectory log takes each frame's state from
    the bus) changes what a run records, which lockstep promises it never does."""
    from protocol.topics import UnknownTopic, topic_of

    options = {"congestion_control": zenoh.CongestionControl.BLOCK} if lockstep else {}
    try:
        control_path = topic_of(key).control_path
    except UnknownTopic:
        return options
    return {**options, "express": True, "priority": zenoh.Priority.INTERACTIVE_HIGH} if control_path else options


#: where free_loopback_port looks first: below the kernel's ephemeral range, with room for many listeners
LISTEN_PORTS_FROM = 10000
#: (the OS's randomness: a test that seeds ``random`` must not make two processes pick the same ports)
_PORT_CHOICE = random.SystemRandom()


def _ephemeral_ports() -> tuple[int, int]:
    """The kernel's range for the local ports of outgoing connections (Linux's default where it cannot be read)."""
    try:
        low, high = (int(v) for v in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
        return low, high
    except (OSError, ValueError):
        return 32768, 60999


def free_loopback_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on the loopback interface right now, outside the ephemeral range where it can be:
    a port the kernel handed out (bind to 0) is one it may hand again, as the local port of any process's next
    outgoing connection, before our listener binds it (a bus hub then found its port taken by a client's
    connection, "Address already in use")."""
    low, _ = _ephemeral_ports()
    if low - LISTEN_PORTS_FROM >= 1000:
        for port in _PORT_CHOICE.sample(range(LISTEN_PORTS_FROM, low), 50):
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                try:
                    s.bind((host, port))
                except OSError:
                    continue
                return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class Router:
    """A zenoh router in this process (eclipse-zenoh in router mode), listening on a loopback port.

    Use as a context manager, or ``start()``/``close()``. ``port=0`` picks a free port.
    """

    def __init__(self, port: int | None = 0, host: str = "127.0.0.1", config_file: str | None = None,
                 scheme: str = "tcp") -> None:
        """``port=None`` with a config file: listen where the file says (its first listen endpoint); a port given
        as well must be the file's."""
        self.config_file = None if config_file is None else str(config_file)
        listen = file_endpoints(self.config_file, "listen") if self.config_file else []
        if listen:
            file_scheme, address = listen[0].split("/", 1)
            file_host, file_port = address.rsplit(":", 1)
            if port and (int(file_port), file_scheme) != (port, scheme):
                raise ConfigError(self.config_file, f"port {port} ({scheme}) conflicts with the file's listen "
                                  f"endpoint {listen[0]}", "listen.endpoints")
            host, port, scheme = file_host, int(file_port), file_scheme
        self.host = host
        self.port = port or free_loopback_port(host)
        self.scheme = scheme
        self._session: zenoh.Session | None = None
        self._lock = threading.Lock()

    @property
    def endpoint(self) -> str:
        return loopback_endpoint(self.port, self.host, self.scheme)

    def client_config(self, **overrides) -> ZenohConfig:
        """A client config that connects to this router (``config_file=`` for credentials or certificates)."""
        return ZenohConfig(mode="client", connect=[self.endpoint], **overrides)

    def start(self) -> "Router":
        with self._lock:
            if self._session is None:
                listen = [] if self.config_file and file_endpoints(self.config_file, "listen") else [self.endpoint]
                cfg = ZenohConfig(mode="router", connect=[], listen=listen, config_file=self.config_file)
                self._session = open_session(cfg)
        return self

    @property
    def zid(self) -> str:
        if self._session is None:
            raise RuntimeError("router not started")
        return str(self._session.info.zid())

    def close(self) -> None:
        with self._lock:
            if self._session is not None:
                self._session.close()
                self._session = None

    def __enter__(self) -> "Router":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
