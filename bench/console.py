"""The console's camera in a real browser: how many frames a second a headless Chromium page draws, and how far
behind their capture (p50, p99), on a stack in realtime, idle and then with its task running (the arm moving, every
service a process, the console one more, the browser one more: all on this machine's cores).

``python -m bench.console [--json] [--seconds S] [--profile sim|gateway] [--arm NAME]`` or ``mfvs bench console``. The delay is
from the frame's capture stamp (robot_sim's camera) to the page's clock once the frame is decoded and drawn; both
clocks are this machine's. ``console_to_page_ms`` is the part from the console's receiving the frame. ``--json``
prints ``{"profile", "arm", "seconds", "idle": PHASE, "task": PHASE}``, each PHASE ``{"fps", "frames",
"delay_ms": {p50, p99, max, n}, "console_to_page_ms": {...}, "camera_hz", "encoded_hz", "drawn_hz", "dropped"}``.

Debian's Chromium and chromedriver (``deploy/install.sh``) are driven by Selenium, started as this machine needs
(headless, no sandbox as root, no background networking: the machine has no internet).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Optional

from bench.latency import stats
from bench.stack import profile_on_arm, servoing_stack, unknown_arm
from protocol import messages as m
from protocol.keys import Keys
from services.cli.options import add_arm_option
from services.stack.launcher import stack_task
from services.runtime.service import query_health
from services.runtime.transport import ZenohConfig, open_session
from services.stack.local import ConsoleProcess

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
CERTUTIL = "certutil"
#: headless, as root (no sandbox), and nothing that reaches for the internet
CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage")


class Browser:
    """Headless Chromium driven by Selenium through chromedriver, in a fresh profile: a context manager giving the
    driver (``width`` × ``height`` window).

    ``trust_ca`` (a PEM file): the browser also trusts that certificate authority, as a tablet does once the
    deployment's ``ca.pem`` is installed on it. Chromium on Linux takes the CAs a user added from the NSS database
    in ``$HOME/.pki/nssdb``; this browser gets a HOME of its own whose database holds that CA alone (written with
    ``certutil``, Debian's libnss3-tools). Nothing turns certificate checks off."""

    def __init__(self, width: int = 1280, height: int = 900, trust_ca: Optional[str] = None) -> None:
        self.width, self.height = width, height
        self.trust_ca = trust_ca
        self._files = ""
        self.driver = None

    def __enter__(self):
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service

        options = webdriver.ChromeOptions()
        options.binary_location = CHROMIUM
        self._files = tempfile.mkdtemp(prefix="mfvs-chromium-")
        profile = Path(self._files) / "profile"
        for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={self.width},{self.height}"):
            options.add_argument(flag)
        try:
            env = None
            if self.trust_ca is not None:
                home = Path(self._files) / "home"
                trust_only(home / ".pki" / "nssdb", self.trust_ca)
                env = dict(os.environ, HOME=str(home))
            self.driver = webdriver.Chrome(service=Service(CHROMEDRIVER, env=env), options=options)
        except Exception:
            shutil.rmtree(self._files, ignore_errors=True)
            raise
        return self.driver

    def __exit__(self, *exc) -> None:
        if self.driver is not None:
            self.driver.quit()
            self.driver = None
        shutil.rmtree(self._files, ignore_errors=True)


def trust_only(nss_database: Path, ca_pem: str) -> None:
    """A new NSS database at ``nss_database`` (no password) whose only added certificate is the CA ``ca_pem``,
    trusted to identify web sites ("C,,")."""
    if shutil.which(CERTUTIL) is None:
        raise RuntimeError(f"no {CERTUTIL} (Debian's libnss3-tools; deploy/install.sh installs it)")
    nss_database.mkdir(parents=True)
    for args in (["-N", "--empty-password"], ["-A", "-t", "C,,", "-n", "mfvs deployment CA", "-i", str(ca_pem)]):
        done = subprocess.run([CERTUTIL, "-d", f"sql:{nss_database}", *args], capture_output=True, text=True)
        if done.returncode:
            raise RuntimeError(f"certutil {' '.join(args)}: {done.stderr.strip() or done.stdout.strip()}")


def page_stats(driver) -> dict:
    """What the console's page counted (``window.mfvsConsole.stats``)."""
    return driver.execute_script("return window.mfvsConsole.stats;")


def wait_for_frames(driver, count: int, timeout_s: float = 30.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        seen = page_stats(driver)
        if seen["frames"] >= count:
            return seen
        time.sleep(0.2)
    raise RuntimeError(f"the page drew {page_stats(driver)['frames']} frames in {timeout_s:g} s")


def measure(url: str, seconds: float, phases: dict, figures=dict) -> dict:
    """Open ``url`` in headless Chromium and, phase after phase (its name → what begins it), count what the page
    draws over ``seconds``, after its first frames; ``figures()`` (read at each phase's end) are added."""
    out = {}
    with Browser() as driver:
        driver.get(url)
        wait_for_frames(driver, 10)
        for name, begin in phases.items():
            begin()
            before = page_stats(driver)
            time.sleep(seconds)
            after = page_stats(driver)
            frames = after["frames"] - before["frames"]
            span_s = (after["lastAt"] - before["lastAt"]) / 1e3 if frames else 0.0
            # the page keeps its last 5000 figures: those of the measured frames are the last ``frames`` of them
            out[name] = {"fps": round(frames / span_s, 2) if span_s > 0 else 0.0, "frames": frames,
                         "delay_ms": stats(after["delaysMs"][-frames:] if frames else []),
                         "console_to_page_ms": stats(after["consoleMs"][-frames:] if frames else []), **figures()}
    return out


def console_rates(endpoint: str, robot_id: str = "jaco") -> dict:
    session = open_session(ZenohConfig(connect=[endpoint]))
    try:
        health = query_health(session, Keys(robot_id)).get("console")
    finally:
        session.close()
    if health is None:
        return {}
    return {"camera_hz": round(health.rates_hz.get("image", 0.0), 1),
            "encoded_hz": round(health.rates_hz.get("frames.encoded", 0.0), 1),
            "drawn_hz": round(health.rates_hz.get("frames.drawn", 0.0), 1),
            "dropped": {k: v for k, v in health.errors.items() if k.startswith("dropped.")}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench console", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=10.0, help="how long to count (after the first frames)")
    parser.add_argument("--profile", default="sim", help="sim (default) or gateway")
    add_arm_option(parser)
    args = parser.parse_args(argv)
    if unknown_arm(parser, args):
        return 2
    with servoing_stack(profile_on_arm(args.profile, args.arm), operator="bench-console", start_task=False) as endpoint:
        with ConsoleProcess(endpoint) as console:
            phases = {"idle": lambda: None,
                      "task": lambda: stack_task(m.START_TASK, operator="bench-console")}
            result = {"profile": args.profile, "arm": args.arm, "seconds": args.seconds,
                      **measure(console.url, args.seconds, phases, lambda: console_rates(endpoint))}
    if args.json:
        print(json.dumps(result))
    else:
        print(f"console ({args.profile}, {args.arm}, {args.seconds:g} s a phase, headless Chromium):")
        for phase in phases:
            r = result[phase]
            delay, part = r["delay_ms"], r["console_to_page_ms"]
            print(f"  {phase:4s}: {r['fps']:.1f} frames/s drawn (camera {r.get('camera_hz', 0):.1f} Hz, encoded "
                  f"{r.get('encoded_hz', 0):.1f} Hz); capture → page p50 {delay['p50']} ms, p99 {delay['p99']} ms, "
                  f"max {delay['max']} ms ({delay['n']} frames); console → page p50 {part['p50']} ms, p99 "
                  f"{part['p99']} ms; dropped {r.get('dropped', {})}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
