"""``mfvs doctor [--json]``: what this host can sustain, measured here, and what to change where it cannot.

It measures what the realtime stack spends a core's time on (issue 49): a camera frame rendered at the camera's
resolution (robot_sim's EGL renderer), the tag found in it (vision's detector), one 2 ms cycle of the emulated
arm (physics and firmware, robot_sim's bus loop), the console's JPEG of a frame (what it does for each frame a
page draws: the console is an option of each profile, so its need is told apart), and looks at the host: cores and their clock, memory, whether
realtime priority is granted, and for a real arm Kinova's SDK, libusb, the udev rule and the arm on USB. Then
:func:`assess`, a pure function of those figures, says which of them limits the host, which profiles it will hold
and what to change. A browser's decoding and drawing of the page is not measured here (it needs a stack and a
browser running): ``mfvs bench console`` measures the frames a page shows, idle and with a task.

Our choices, not measurements (each is where the assessment draws its line): a loop holds its rate when one of
its periods' work takes at most half the period (the other half is for the rest of the stack on the same core and
the OS); the realtime stack holds when what it needs of the cores each second is at most 70 % of them (the rest
for zenoh, the services' Python around the measured work and the router; the stack's processes measured by
``mfvs bench cpu`` spend about a third of their time outside the three measured parts).
"""
from __future__ import annotations

import ctypes.util
import glob
import json
import os
import statistics
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

#: a loop holds its rate when one period's work takes at most this share of the period (our choice: above)
PERIOD_SHARE = 0.5
#: the realtime stack holds when it needs at most this share of the cores (our choice: above)
CORE_SHARE = 0.7
#: the emulated arm's cycle and the DSP's (services.robot.hardware: the 500 Hz bus, the 100 Hz DSP)
ARM_CYCLE_S = 0.002
#: Kinova's USB vendor id (deploy/udev/60-mfvs-kinova-arm.rules)
KINOVA_VENDOR = "22cd"
UDEV_RULE = Path("/etc/udev/rules.d/60-mfvs-kinova-arm.rules")
#: less than this much memory available (MB) is named: the sim profile's stack is about 500 MB PSS
#: (docs/benchmarks.md, `mfvs bench cpu`), a browser beside it as much again
MEMORY_NEEDED_MB = 1500


@dataclass
class Figures:
    """What :func:`measure` found (times in ms: rendering and the arm's cycle the p50 of the repeats, detection
    their mean, whose full-frame searches every 30th frame are part of its cost)."""

    #: the cores this process may run on, or the cores' worth its cgroup's CPU quota allows where that is less
    cores: float
    cpu_model: str
    cpu_mhz: Optional[float]
    memory_available_mb: Optional[float]
    camera: dict
    render_ms: float
    detect_ms: float
    arm_cycle_ms: float
    realtime: dict
    #: the console's JPEG of one whole frame (its default quality), the work it does for each frame a page draws
    encode_ms: float = 0.0
    real_arm: Optional[dict] = None
    repeats: int = 0
    notes: list = field(default_factory=list)


# ------------------------------------------------------------------------------------------------ measuring
def _cpu() -> tuple[str, Optional[float]]:
    model, mhz = "unknown", []
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name":
                model = value.strip()
            elif key.strip() == "cpu MHz":
                mhz.append(float(value))
    except OSError:
        pass
    return model, (round(statistics.mean(mhz)) if mhz else None)


def cpu_quota_cores(cgroup_file: str = "/proc/self/cgroup", root: str = "/sys/fs/cgroup") -> Optional[float]:
    """The cores' worth of CPU time this process's cgroup may use (a container's `--cpus`, a CFS quota: v1's
    cpu.cfs_quota_us / cpu.cfs_period_us, v2's cpu.max), or None where none is set: a quota slows the stack as
    fewer cores would, whatever the machine has."""
    try:
        lines = Path(cgroup_file).read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        _, controllers, path = line.split(":", 2)
        try:
            if "cpu" in controllers.split(","):  # v1
                base = Path(root) / "cpu" / path.lstrip("/")
                quota = int((base / "cpu.cfs_quota_us").read_text())
                period = int((base / "cpu.cfs_period_us").read_text())
                if quota > 0 and period > 0:
                    return quota / period
            elif controllers == "":  # v2
                quota, period = (Path(root) / path.lstrip("/") / "cpu.max").read_text().split()
                if quota != "max":
                    return int(quota) / int(period)
        except (OSError, ValueError):
            continue
    return None


def _memory_available_mb() -> Optional[float]:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return round(int(line.split()[1]) / 1024)
    except OSError:
        pass
    return None


def realtime_granted() -> dict:
    """Whether SCHED_FIFO is granted here (tried on a thread of ours, which then ends)."""
    outcome = {}

    def attempt() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            outcome.update(granted=True, why="SCHED_FIFO granted")
        except (OSError, AttributeError) as exc:
            outcome.update(granted=False, why=f"SCHED_FIFO refused ({exc})")

    thread = threading.Thread(target=attempt)
    thread.start()
    thread.join()
    return outcome


def real_arm_readiness(sdk: Optional[str]) -> dict:
    """For a real arm: Kinova's comm and command layers where ``sdk`` (else $MFVS_KINOVA_SDK) says, libusb, the
    udev rule, and the Kinova devices on USB."""
    from services.robot_gateway.kinova_sdk import ArmStartError
    from services.robot_gateway.kinova_usb import has_command_layer, locate_comm_layer

    try:
        comm_layer = str(locate_comm_layer(sdk))
    except ArmStartError as exc:
        comm_layer = None
        missing = str(exc)
    else:
        missing = ""
    devices = [Path(p).parent.name for p in glob.glob("/sys/bus/usb/devices/*/idVendor")
               if Path(p).read_text().strip().lower() == KINOVA_VENDOR]
    return {"comm_layer": comm_layer, "comm_layer_missing": missing,
            "command_layer": bool(comm_layer) and has_command_layer(sdk),
            "libusb": ctypes.util.find_library("usb-1.0"), "udev_rule": UDEV_RULE.is_file(), "devices": devices}


def measure(camera=None, repeats: int = 30, sdk: Optional[str] = None, arm: Optional[str] = None) -> Figures:
    """The figures of this host: ``camera`` is robot_sim's camera section (default: the shipped robot_sim.yaml's)."""
    import numpy as np

    from services.model.arm import load_arm
    from services.paths import REPO
    from services.robot_sim.scene import SceneConfig
    from services.robot_sim.service import RobotSimConfig
    from services.robot_sim.sim import Simulation
    from services.runtime.config import load_config
    import cv2

    from protocol import messages as m
    from services.camera.core import image_message
    from services.console.service import ConsoleConfig
    from services.observe.foxglove_view import jpeg
    from services.vision.features import TagDetector, TagTracker

    shipped = load_config(REPO / "services" / "robot_sim" / "robot_sim.yaml", RobotSimConfig)
    camera = camera or shipped.scene.camera
    sim = Simulation(SceneConfig(camera=camera), render=True, arm=load_arm(arm) if arm else None)
    renders, cycles, detects, encodes = [], [], [], []
    quality = ConsoleConfig().jpeg_quality
    # as vision finds it: in a window around its last corners, the whole frame every 30th (its RoiConfig)
    tracker = TagTracker(TagDetector())
    try:
        for _ in range(repeats + 2):  # the first two warm the renderer and the caches up
            start = time.perf_counter()
            image = sim.render()
            renders.append(time.perf_counter() - start)
            gray = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)  # as vision takes an rgb8 frame
            start = time.perf_counter()
            tracker.find(gray, sim.scene.target.id)
            detects.append(time.perf_counter() - start)
            # the frame as robot_sim's camera publishes it (grey or rgb8), as the console receives and encodes it
            shown = gray if camera.encoding is m.ImageEncoding.MONO8 else np.ascontiguousarray(image)
            start = time.perf_counter()
            jpeg(image_message(shown, camera.encoding, m.Header()), quality)
            encodes.append(time.perf_counter() - start)
            for _ in range(5):  # a DSP tick's worth of the arm's cycles
                start = time.perf_counter()
                sim.cycle()
                cycles.append(time.perf_counter() - start)
    finally:
        sim.close()
    model, mhz = _cpu()
    cores, quota = len(os.sched_getaffinity(0)), cpu_quota_cores()
    p50 = lambda values: round(1e3 * statistics.median(values[2:] if len(values) > 4 else values), 3)  # noqa: E731
    return Figures(cores=min(cores, quota) if quota else cores, cpu_model=model, cpu_mhz=mhz,
                   memory_available_mb=_memory_available_mb(),
                   camera={"width": camera.width, "height": camera.height, "rate_hz": camera.rate_hz},
                   render_ms=p50(renders), detect_ms=round(1e3 * statistics.mean(detects[2:]), 3),
                   arm_cycle_ms=p50(cycles[10:]), encode_ms=p50(encodes),
                   realtime=realtime_granted(), real_arm=real_arm_readiness(sdk) if sdk is not None or
                   os.environ.get("MFVS_KINOVA_SDK") else None, repeats=repeats)


# ------------------------------------------------------------------------------------------------ the verdict
def assess(f: Figures) -> dict:
    """Which of the measured parts limits the host (the largest share of its own deadline), the realtime stack's
    need of the cores, which profiles it holds, and what to change. Pure: a function of ``f`` alone."""
    period_ms = 1e3 / f.camera["rate_hz"]
    parts = {
        # rendering and detection share the camera's period (robot_sim renders, vision detects, a frame each)
        "rendering": {"ms": f.render_ms, "period_ms": period_ms},
        "detection": {"ms": f.detect_ms, "period_ms": period_ms},
        "the arm's 2 ms cycle": {"ms": f.arm_cycle_ms, "period_ms": ARM_CYCLE_S * 1e3},
    }
    for part in parts.values():
        part["share_of_period"] = round(part["ms"] / part["period_ms"], 3)
        part["cores"] = part["share_of_period"]  # one period's work every period: that share of one core
    sim_cores = sum(p["cores"] for p in parts.values())
    # the gateway profile runs the arm's cycle twice over (the emulated actuators, and the gateway's own loop)
    gateway_cores = sim_cores + parts["the arm's 2 ms cycle"]["cores"]
    limiting_name = max(parts, key=lambda name: parts[name]["share_of_period"])
    limiting = {"what": limiting_name, **parts[limiting_name]}
    # the console is an option of each profile: a JPEG for every frame a page draws, at most the camera's rate
    console = {"ms": f.encode_ms, "period_ms": period_ms, "share_of_period": round(f.encode_ms / period_ms, 3)}
    console["cores"] = console["share_of_period"]
    available = CORE_SHARE * f.cores
    advice, holds = [], {}
    for profile, cores, used in (("sim", sim_cores, parts), ("gateway", gateway_cores, parts),
                                 ("sim with the console", sim_cores + console["cores"],
                                  {**parts, "the console's encoding": console})):
        reasons = [f"{name}: {p['ms']:.2f} ms of its {p['period_ms']:.1f} ms period"
                   for name, p in used.items() if p["share_of_period"] > PERIOD_SHARE]
        if cores > available:
            reasons.append(f"the stack needs {cores:.2f} of the {f.cores:g} cores' {available:.2f} it may use")
        if not f.realtime.get("granted"):
            reasons.append("no realtime priority: its 500 Hz loop is late whenever another program runs")
        holds[profile] = {"holds": not reasons, "cores_needed": round(cores, 2), "why_not": reasons}
    if parts["rendering"]["share_of_period"] > PERIOD_SHARE or limiting_name == "rendering" and not all(
            h["holds"] for h in holds.values()):
        advice.append(f"rendering a {f.camera['width']}×{f.camera['height']} frame takes {f.render_ms:.1f} ms: lower "
                      "the camera's resolution or rate (robot_sim scene.camera.width/height/rate_hz, e.g. "
                      "examples/scenarios/table2_qvga.yaml's 320×240), and run experiments in lockstep (their "
                      "default), whose result does not depend on the host's speed")
    if console["share_of_period"] > PERIOD_SHARE or not holds["sim with the console"]["holds"] and \
            holds["sim"]["holds"]:
        advice.append(f"the console's JPEG of a frame takes {f.encode_ms:.1f} ms: it halves frames while its pages "
                      "are behind, and a lower jpeg_quality or camera rate helps; or watch from another computer")
    if parts["detection"]["share_of_period"] > PERIOD_SHARE:
        advice.append(f"finding the tag takes {f.detect_ms:.1f} ms a frame: a lower resolution or rate helps here too")
    if parts["the arm's 2 ms cycle"]["share_of_period"] > PERIOD_SHARE:
        advice.append(f"one 2 ms cycle of the emulated arm takes {f.arm_cycle_ms:.2f} ms: this host cannot emulate "
                      "the arm in realtime; use lockstep (`mfvs servo`, `mfvs experiment`)")
    if not f.realtime.get("granted"):
        advice.append("realtime priority is refused: run the stack as root or grant CAP_SYS_NICE (an rtprio limit "
                      "in /etc/security/limits.conf, or `setcap cap_sys_nice+ep` on the interpreter)")
    if f.cores < 2:
        advice.append("one core: run services in one process where you can (`mfvs servo` composes them by "
                      "default; leave out --processes), and nothing else beside the stack")
    if any(not h["holds"] for h in holds.values()):
        advice.append("keep the console's browser on another computer (a page drawing the camera costs as much "
                      "as a service)")
    if f.memory_available_mb is not None and f.memory_available_mb < MEMORY_NEEDED_MB:
        advice.append(f"{f.memory_available_mb:.0f} MB available: the sim stack takes about 500 MB, a browser as "
                      "much again")
    if f.real_arm is not None:
        arm = f.real_arm
        for ok, fix in ((arm["comm_layer"], arm["comm_layer_missing"] or "Kinova's comm layer not found"),
                        (arm["command_layer"], "Kinova's command layer (USBCommandLayerUbuntu.so) is not beside the "
                                               "comm layer"),
                        (arm["libusb"], "libusb-1.0 is missing: bash deploy/install.sh installs it"),
                        (arm["udev_rule"], f"the udev rule is not installed: sudo cp deploy/udev/{UDEV_RULE.name} "
                                           "/etc/udev/rules.d/ (README)"),
                        (arm["devices"], "no Kinova arm on USB (vendor 22cd): powered and plugged in?")):
            if not ok:
                advice.append(fix)
    return {"limiting": limiting, "parts": parts, "console": console, "profiles": holds, "advice": advice}


def report_text(f: Figures, verdict: dict) -> str:
    lines = [f"host: {f.cores:g} cores ({f.cpu_model}{f', {f.cpu_mhz:.0f} MHz' if f.cpu_mhz else ''}), "
             f"{f.memory_available_mb} MB available, realtime priority: {f.realtime.get('why')}"]
    for name, p in verdict["parts"].items():
        lines.append(f"  {name}: {p['ms']:.2f} ms of its {p['period_ms']:.1f} ms period ({100 * p['share_of_period']:.0f} %)")
    c = verdict["console"]
    lines.append(f"  the console's encoding (with a page open): {c['ms']:.2f} ms of its {c['period_ms']:.1f} ms period "
                 f"({100 * c['share_of_period']:.0f} %)")
    lim = verdict["limiting"]
    lines.append(f"what limits this host: {lim['what']} ({lim['ms']:.2f} ms, {100 * lim['share_of_period']:.0f} % of "
                 f"its period)")
    for profile, h in verdict["profiles"].items():
        lines.append(f"  {profile} profile in realtime: {'holds' if h['holds'] else 'will not hold'} (needs "
                     f"{h['cores_needed']:.2f} cores)" + "".join(f"; {r}" for r in h["why_not"]))
    lines.append("  lockstep (mfvs servo, mfvs experiment): holds on any host; its results do not depend on speed")
    if f.real_arm is not None:
        lines.append(f"real arm: {json.dumps(f.real_arm)}")
    lines += [f"change: {a}" for a in verdict["advice"]] or ["nothing to change"]
    return "\n".join(lines)


def add_parser(sub) -> None:
    doctor = sub.add_parser("doctor", help="what this host can sustain (rendering, detection, the arm's cycle, "
                                           "cores, realtime priority, a real arm's SDK and USB), and what to change")
    doctor.add_argument("--json", action="store_true", help="one JSON object: the figures and the verdict")
    doctor.add_argument("--repeats", type=int, default=30, help="frames rendered and detected (default 30)")
    doctor.add_argument("--sdk", default=None, metavar="DIR",
                        help="check a real arm's side too: Kinova's SDK here (default: $MFVS_KINOVA_SDK, if set)")
    doctor.add_argument("--arm", default=None, metavar="NAME", help="the arm rendered (default j2s7s300)")
    doctor.set_defaults(func=run_command)


def run_command(args) -> int:
    if args.repeats < 1:
        print("mfvs doctor: --repeats must be at least 1", file=sys.stderr)
        return 2
    if args.arm is not None:
        from services.model.arm import check_arm_name
        try:
            check_arm_name(args.arm)
        except ValueError as exc:
            print(f"mfvs doctor: {exc}", file=sys.stderr)
            return 2
    figures = measure(repeats=args.repeats, sdk=args.sdk, arm=args.arm)
    verdict = assess(figures)
    if args.json:
        print(json.dumps({"figures": asdict(figures), **verdict}))
    else:
        print(report_text(figures, verdict))
    return 0
