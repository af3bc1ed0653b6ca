"""A Linux gamepad or joystick as a stick (``mfvs jog --device /dev/input/eventN``), read from the kernel's input
events with python-evdev.

:class:`EvdevStick` is pure: it takes events (type, code, value) and says what the stick is (its axes normalised by
each axis's range as the kernel reports it, its buttons), so it is tested on recorded events with no device
(tests/services/jog/). :func:`open_device` and :class:`DeviceReader` are the thin part: a thread that waits on the
device and hands its events over; the device is *heard* at every wait that ended without an error (the kernel sends
nothing while a stick is held still, so silence is no sign of a lost device; an error is: an unplugged device's
read fails with ENODEV). A SYN_DROPPED (the kernel's buffer overflowed) discards the events up to the next report and
reads the device's state afresh, as the kernel's documentation asks.

The default map (:class:`GamepadMap`) is ours, for an Xbox-style pad as the kernel's ``xpad`` driver names it: the
left stick's X and Y and the right stick's Y are the three axes (up is negative on the kernel's Y axes, so those
are inverted), the left shoulder button is the dead-man (held by a finger, as teleop_twist_joy's enable button), A
cycles the modes, the right and left shoulder-near buttons step the speed level, Start resumes a paused task.
"""
from __future__ import annotations

import errno
import os
import select
import threading
import time
from dataclasses import dataclass
from typing import Iterable, Optional

import msgspec

from protocol.messages import JOG_SPEED_LEVELS, JogMode
from services.jog.mapping import MODE_CYCLE, StickInput
from services.runtime.config import ConfigStruct

EV_SYN, EV_KEY, EV_ABS = 0x00, 0x01, 0x03
SYN_REPORT, SYN_DROPPED = 0, 3


class DeviceError(RuntimeError):
    """The device cannot be read (absent, not permitted, unplugged), or is not a stick the map fits."""


class AxisMap(ConfigStruct):
    #: the kernel's name of the axis (ABS_X, ABS_Y, ABS_RX, ABS_RY, ABS_Z, ...)
    code: str
    invert: bool = False


class GamepadMap(ConfigStruct):
    """Which of a device's axes and buttons do what (kernel names: linux/input-event-codes.h)."""

    axes: list[AxisMap] = msgspec.field(default_factory=lambda: [
        AxisMap(code="ABS_Y", invert=True), AxisMap(code="ABS_X", invert=True), AxisMap(code="ABS_RY", invert=True)])
    deadman: str = "BTN_TL"
    mode: str = "BTN_SOUTH"
    speed_up: str = "BTN_TR"
    speed_down: str = "BTN_WEST"
    resume: str = "BTN_START"

    def __post_init__(self) -> None:
        if len(self.axes) != 3:
            raise ValueError("axes: the stick's three (translation X, Y, Z; wrist about x, y, z)")
        for name in (*[a.code for a in self.axes], self.deadman, self.mode, self.speed_up, self.speed_down,
                     self.resume):
            code_of(name)

    def buttons(self) -> dict[str, int]:
        return {role: code_of(getattr(self, role)) for role in ("deadman", "mode", "speed_up", "speed_down", "resume")}


def code_of(name: str) -> int:
    """The kernel's code for an axis or button name (evdev's table of linux/input-event-codes.h)."""
    from evdev import ecodes

    code = ecodes.ecodes.get(name)
    if code is None or not (name.startswith("ABS_") or name.startswith("BTN_") or name.startswith("KEY_")):
        raise ValueError(f"{name!r} is not an input event code the kernel names (ABS_*, BTN_*, KEY_*)")
    return code


@dataclass
class AxisRange:
    """An axis's range as the kernel reports it (struct input_absinfo's min, max, flat)."""

    minimum: int
    maximum: int
    flat: int = 0

    def normalised(self, value: int) -> float:
        """-1 at the minimum, +1 at the maximum (0 at the centre)."""
        span = self.maximum - self.minimum
        if span <= 0:
            return 0.0
        return max(-1.0, min(1.0, 2.0 * (value - self.minimum) / span - 1.0))


class EvdevStick:
    """The stick as its events say it is. Pure: :meth:`event` for each, :meth:`input` for the stick now."""

    def __init__(self, gamepad: GamepadMap, ranges: dict[int, AxisRange], speed_level: int = JOG_SPEED_LEVELS[-1],
                 values: Optional[dict[int, int]] = None, pressed: Iterable[int] = ()) -> None:
        self.gamepad = gamepad
        self.axis_codes = [code_of(a.code) for a in gamepad.axes]
        missing = [a.code for a, c in zip(gamepad.axes, self.axis_codes) if c not in ranges]
        if missing:
            raise DeviceError(f"the device has no axis {', '.join(missing)} (its map: jog.yaml gamepad.axes)")
        self.ranges = ranges
        self.buttons = gamepad.buttons()
        self.values = {code: int((r.minimum + r.maximum) / 2) for code, r in ranges.items()}
        self.values.update(values or {})
        self.pressed = set(pressed)
        self.mode_index = 0
        self.speed_level = speed_level
        #: resume presses not yet taken by :meth:`take_resume`
        self._resumes = 0
        #: a SYN_DROPPED: events are ignored until the next report, then the state is read afresh
        self.dropped = False
        self.events = 0

    def event(self, kind: int, code: int, value: int) -> None:
        self.events += 1
        if kind == EV_SYN:
            if code == SYN_DROPPED:
                self.dropped = True
            elif code == SYN_REPORT and self.dropped:
                self.dropped = False  # the caller resynchronises (DeviceReader reads the state afresh)
            return
        if self.dropped:
            return
        if kind == EV_ABS and code in self.ranges:
            self.values[code] = value
        elif kind == EV_KEY:
            self._key(code, value)

    def _key(self, code: int, value: int) -> None:
        was = code in self.pressed
        if value:
            self.pressed.add(code)
        else:
            self.pressed.discard(code)
        if value != 1 or was:  # only a press (not a release, not a repeat) steps a mode or a level
            return
        if code == self.buttons["mode"]:
            self.mode_index = (self.mode_index + 1) % len(MODE_CYCLE)
        elif code == self.buttons["speed_up"]:
            self.speed_level = min(self.speed_level + 1, JOG_SPEED_LEVELS[-1])
        elif code == self.buttons["speed_down"]:
            self.speed_level = max(self.speed_level - 1, JOG_SPEED_LEVELS[0])
        elif code == self.buttons["resume"]:
            self._resumes += 1

    def resync(self, values: dict[int, int], pressed: Iterable[int]) -> None:
        """The device's state read afresh (after a SYN_DROPPED): axes and held buttons, no presses invented."""
        self.values.update({code: v for code, v in values.items() if code in self.ranges})
        self.pressed = set(pressed)

    def take_resume(self) -> bool:
        taken, self._resumes = self._resumes > 0, 0
        return taken

    @property
    def mode(self) -> JogMode:
        return MODE_CYCLE[self.mode_index]

    def input(self) -> StickInput:
        axes = []
        for axis, code in zip(self.gamepad.axes, self.axis_codes):
            value = self.ranges[code].normalised(self.values[code])
            axes.append(-value if axis.invert else value)
        return StickInput(axes=tuple(axes), mode=self.mode, speed_level=self.speed_level,
                          deadman=self.buttons["deadman"] in self.pressed)


def open_device(path: str):
    """The evdev device at ``path``, or a DeviceError saying why it cannot be read."""
    from evdev import InputDevice

    try:
        return InputDevice(path)
    except FileNotFoundError:
        raise DeviceError(f"{path}: no such input device (evdev.list_devices() lists what there is)") from None
    except PermissionError:
        raise DeviceError(f"{path}: not permitted (add the user to the 'input' group, or a udev rule)") from None
    except OSError as exc:
        raise DeviceError(f"{path}: {exc.strerror or exc}") from None


def stick_of(device, gamepad: GamepadMap, speed_level: int) -> EvdevStick:
    """An EvdevStick for an opened device: its axes' ranges and state as the kernel has them now."""
    ranges, values = {}, {}
    for code, info in device.capabilities().get(EV_ABS, []):
        ranges[code] = AxisRange(info.min, info.max, info.flat)
        values[code] = info.value
    return EvdevStick(gamepad, ranges, speed_level, values, device.active_keys())


class DeviceReader:
    """A thread that waits on the device, feeds its events to the stick and notes when the device was last heard
    (time.monotonic()); on an error (unplugged) it stops and says why."""

    #: the longest a wait lasts: how stale "heard" can be on a healthy device (well inside safety's 0.25 s)
    POLL_S = 0.02

    def __init__(self, device, stick: EvdevStick) -> None:
        self.device = device
        self.stick = stick
        self.lock = threading.Lock()
        self.heard_s = time.monotonic()
        self.gone = ""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="jog-device", daemon=True)

    def start(self) -> "DeviceReader":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)

    def heard_within(self, budget_s: float) -> bool:
        with self.lock:
            return not self.gone and time.monotonic() - self.heard_s <= budget_s

    def _run(self) -> None:
        fd = self.device.fd
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([fd], [], [], self.POLL_S)
                events = list(self.device.read()) if ready else []
            except BlockingIOError:
                events = []
            except OSError as exc:
                with self.lock:
                    self.gone = f"the device is gone ({errno.errorcode.get(exc.errno, exc.errno)}: " \
                                f"{exc.strerror or os.strerror(exc.errno or 0)})"
                return
            with self.lock:
                for event in events:
                    was_dropped = self.stick.dropped
                    self.stick.event(event.type, event.code, event.value)
                    if was_dropped and not self.stick.dropped:  # the report after a SYN_DROPPED: read afresh
                        self._resync()
                self.heard_s = time.monotonic()

    def _resync(self) -> None:
        values = {code: info.value for code, info in self.device.capabilities().get(EV_ABS, [])}
        self.stick.resync(values, self.device.active_keys())


def parse_evtest(text: str) -> tuple[dict[int, AxisRange], list[tuple[float, int, int, int]]]:
    """The axes' ranges and the events of a log in the format the ``evtest`` tool prints (its header's
    ``Event code N (ABS_X)`` with ``Min``/``Max``/``Flat`` lines, then ``Event: time T, type K (…), code C (…),
    value V`` lines, and ``-------------- SYN_REPORT ------------`` / ``>>>>>>>>>>>>>> SYN_DROPPED <<<<<<<<<<<<``
    for the synchronisation events): what a person's device sent, kept in a file (a bug report's, a test's)."""
    import re

    ranges: dict[int, AxisRange] = {}
    events = []
    in_abs, code, fields = False, None, {}

    def close_axis() -> None:
        if code is not None and "Min" in fields and "Max" in fields:
            ranges[code] = AxisRange(fields["Min"], fields["Max"], fields.get("Flat", 0))

    syn_codes = {"SYN_REPORT": SYN_REPORT, "SYN_DROPPED": SYN_DROPPED}
    for line in text.splitlines():
        syn = re.match(r"Event: time (\d+\.\d+), [-+>]+ (SYN_\w+) [-+<]+", line.strip())
        if syn:
            if syn.group(2) in syn_codes:
                events.append((float(syn.group(1)), EV_SYN, syn_codes[syn.group(2)], 0))
            continue
        event = re.match(r"Event: time (\d+\.\d+), type (\d+) \([^)]*\), code (\d+) \([^)]*\), value (-?\d+)",
                         line.strip())
        if event:
            events.append((float(event.group(1)), int(event.group(2)), int(event.group(3)), int(event.group(4))))
            continue
        if re.match(r"\s*Event type 3 \(EV_ABS\)", line):
            in_abs = True
            continue
        if re.match(r"\s*Event type \d+", line):
            close_axis()
            in_abs, code, fields = False, None, {}
            continue
        if in_abs:
            axis = re.match(r"\s*Event code (\d+) \(", line)
            if axis:
                close_axis()
                code, fields = int(axis.group(1)), {}
                continue
            value = re.match(r"\s*(Value|Min|Max|Fuzz|Flat|Resolution)\s+(-?\d+)", line)
            if value:
                fields[value.group(1)] = int(value.group(2))
    close_axis()
    return ranges, events
