"""Computers on one machine: Linux network namespaces, each with one veth pair into a bridge that lives in a
namespace of its own (the host's own interfaces are never touched), addressed 10.<net>.0.<n>/24. Root only;
:func:`unavailable` says why they cannot be had. :func:`stack_across` brings a multi-host profile up on them, each
computer with its own run directory, as `mfvs up --host` on real computers would."""
from __future__ import annotations

import contextlib
import ctypes
import os
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from services.paths import REPO

MFVS = str(Path(sys.executable).parent / "mfvs")
#: setns(2)'s flag for a network namespace (<sched.h>; Python has os.setns only from 3.12)
_CLONE_NEWNET = 0x40000000


def _setns(fd: int) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.setns(fd, _CLONE_NEWNET) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"setns: {os.strerror(errno)}")


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)


def unavailable() -> str:
    """Why network namespaces cannot be created here ("" when they can)."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    probe = f"mfvs-probe-{os.getpid()}"
    try:
        made = _ip("netns", "add", probe, check=False)
    except FileNotFoundError:
        return "no `ip` command (iproute2)"
    if made.returncode != 0:
        return f"`ip netns add` failed: {made.stderr.strip()}"
    _ip("netns", "del", probe, check=False)
    return ""


@dataclass
class Lab:
    """Named hosts joined by a switch. ``address(name)`` is a host's address; ``run(name, args)`` runs a command
    in it; :meth:`link` takes a host's link down or up (a cable pulled)."""

    hosts: list[str]
    net: int = 77
    tag: str = field(default_factory=lambda: str(os.getpid()))

    def ns(self, host: str) -> str:
        return f"mfvs-{host}-{self.tag}"

    @property
    def switch(self) -> str:
        return f"mfvs-switch-{self.tag}"

    def address(self, host: str) -> str:
        return f"10.{self.net}.0.{self.hosts.index(host) + 1}"

    def __enter__(self) -> "Lab":
        try:
            _ip("netns", "add", self.switch)
            _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
            _ip("-n", self.switch, "link", "set", "br0", "up")
            for i, host in enumerate(self.hosts):
                ns = self.ns(host)
                _ip("netns", "add", ns)
                _ip("-n", ns, "link", "set", "lo", "up")
                _ip("-n", ns, "link", "add", "eth0", "type", "veth", "peer", "name", f"port{i}",
                    "netns", self.switch)
                _ip("-n", self.switch, "link", "set", f"port{i}", "master", "br0", "up")
                _ip("-n", ns, "addr", "add", f"{self.address(host)}/24", "dev", "eth0")
                _ip("-n", ns, "link", "set", "eth0", "up")
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc) -> None:
        for host in self.hosts:
            _ip("netns", "del", self.ns(host), check=False)
        _ip("netns", "del", self.switch, check=False)

    def command(self, host: str, args: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.ns(host), *args]

    @contextlib.contextmanager
    def inside(self, host: str) -> Iterator[None]:
        """The calling thread on ``host`` until the block ends: the sockets it opens and the processes it starts
        meanwhile are that computer's (a network namespace is a thread's, and a child's is its parent thread's), so
        a client library that starts its own helper (Selenium's chromedriver, and the browser under it) runs there
        whole. So are the threads it starts meanwhile; the process's other threads stay where they are, and a
        socket stays on the computer it was opened on."""
        own = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
        try:
            target = os.open(f"/run/netns/{self.ns(host)}", os.O_RDONLY)
            try:
                _setns(target)
            finally:
                os.close(target)
            try:
                yield
            finally:
                _setns(own)
        finally:
            os.close(own)

    def mfvs(self, host: str, run_dir: Path, args: list[str], timeout_s: float = 60.0) -> subprocess.CompletedProcess:
        """`mfvs ARGS` on ``host``, with that computer's run directory (where its stack is recorded)."""
        return subprocess.run(self.command(host, [MFVS, *args]), capture_output=True, text=True, timeout=timeout_s,
                              env=dict(os.environ, MFVS_RUN_DIR=str(run_dir)), cwd=REPO)

    def link(self, host: str, up: bool) -> None:
        """The host's cable in (up) or out: its port on the switch."""
        _ip("-n", self.switch, "link", "set", f"port{self.hosts.index(host)}", "up" if up else "down")


@contextlib.contextmanager
def stack_across(lab: Lab, profile_file: Path, run_dirs: dict[str, Path], router_endpoint: str) -> Iterator[None]:
    """``mfvs up --profile FILE --host H --clock realtime`` on each computer of ``run_dirs`` in their order (the
    router's first), each in its own run directory and each saying it reached ``router_endpoint``; ``mfvs down`` on
    every one started, in reverse, at the end."""
    started = []
    try:
        for host, run_dir in run_dirs.items():
            out = lab.mfvs(host, run_dir, ["up", "--profile", str(profile_file), "--host", host, "--clock",
                                           "realtime"], timeout_s=180)
            started.append(host)
            if out.returncode or f"host {host}: stack up: router {router_endpoint}" not in out.stdout:
                raise RuntimeError(f"mfvs up on {host} (exit {out.returncode}): {out.stdout}{out.stderr}")
        yield
    finally:
        for host in reversed(started):
            lab.mfvs(host, run_dirs[host], ["down"])
