"""The console's camera in a real browser: how many frames a second a headless Chromium page draws, and how far
behind their capture (p50, p99), on a stack in realtime with its task running (the arm moving, every service a
process, the console one more, the browser one more: all on this machine's cores).

``python -m bench.console [--json] [--seconds S] [--profile sim|gateway]`` or ``mfvs bench console``. The delay is
from the frame's capture stamp (robot_sim's camera) to the page's clock once the frame is decoded and drawn; both
clocks are this machine's. ``console_to_page_ms`` is the part from the console's receiving the frame. ``--json``
prints ``{"fps", "delay_ms": {p50, p99, max, n}, "console_to_page_ms": {...}, "camera_hz", "encoded_hz",
"dropped", "seconds"}``.

Debian's Chromium and chromedriver (``deploy/install.sh``) are driven by Selenium, started as this machine needs
(headless, no sandbox as root, no background networking: the machine has no internet).
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time

from bench.latency import stats
from bench.stack import servoing_stack
from protocol.keys import Keys
from services.launcher import load_profile
from services.runtime.service import query_health
from services.runtime.transport import ZenohConfig, free_loopback_port, open_session
from services.stack import ConsoleProcess

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
#: headless, as root (no sandbox), and nothing that reaches for the internet
CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage")


class Browser:
    """Headless Chromium driven by Selenium through chromedriver, in a fresh profile: a context manager giving the
    driver (``width`` × ``height`` window)."""

    def __init__(self, width: int = 1280, height: int = 900) -> None:
        self.width, self.height = width, height
        self._profile = ""
        self.driver = None

    def __enter__(self):
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service

        options = webdriver.ChromeOptions()
        options.binary_location = CHROMIUM
        self._profile = tempfile.mkdtemp(prefix="mfvs-chromium-")
        for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={self._profile}", f"--window-size={self.width},{self.height}"):
            options.add_argument(flag)
        try:
            self.driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
        except Exception:
            shutil.rmtree(self._profile, ignore_errors=True)
            raise
        return self.driver

    def __exit__(self, *exc) -> None:
        if self.driver is not None:
            self.driver.quit()
            self.driver = None
        shutil.rmtree(self._profile, ignore_errors=True)


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


def measure(url: str, seconds: float, while_open=dict) -> dict:
    """Open ``url`` in headless Chromium and count what its page draws over ``seconds``, after its first frames;
    ``while_open()``'s figures (read before the page closes) are added."""
    with Browser() as driver:
        driver.get(url)
        before = wait_for_frames(driver, 10)
        time.sleep(seconds)
        after = page_stats(driver)
        extra = while_open()
    frames = after["frames"] - before["frames"]
    span_s = (after["lastAt"] - before["lastAt"]) / 1e3
    # the page keeps its last 5000 figures: those of the measured frames are the last ``frames`` of them
    return {"fps": round(frames / span_s, 2) if span_s > 0 else 0.0, "frames": frames,
            "delay_ms": stats(after["delaysMs"][-frames:] if frames else []),
            "console_to_page_ms": stats(after["consoleMs"][-frames:] if frames else []), **extra}


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
            "dropped": {k: v for k, v in health.errors.items() if k.startswith("dropped.")}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench console", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=10.0, help="how long to count (after the first frames)")
    parser.add_argument("--profile", default="sim", help="sim (default) or gateway")
    args = parser.parse_args(argv)
    profile = load_profile(args.profile, free_loopback_port(), free_loopback_port())
    with servoing_stack(profile, operator="bench-console") as endpoint:
        with ConsoleProcess(endpoint) as console:
            result = {"profile": args.profile, "seconds": args.seconds,
                      **measure(console.url, args.seconds, lambda: console_rates(endpoint))}
    if args.json:
        print(json.dumps(result))
    else:
        delay, part = result["delay_ms"], result["console_to_page_ms"]
        print(f"console ({args.profile}, {args.seconds:g} s, headless Chromium): {result['fps']:.1f} frames/s drawn "
              f"(camera {result.get('camera_hz', 0):.1f} Hz, encoded {result.get('encoded_hz', 0):.1f} Hz)")
        print(f"  capture → page: p50 {delay['p50']} ms, p99 {delay['p99']} ms, max {delay['max']} ms "
              f"({delay['n']} frames)")
        print(f"  console → page: p50 {part['p50']} ms, p99 {part['p99']} ms; dropped {result.get('dropped', {})}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
