"""The stick's mapping as pure functions (services/jog/mapping.py), the script's file, the evdev stick on a
device's events kept in evtest's format, and the stream's stamps and schedule, with no device and no network."""
from pathlib import Path

import numpy as np
import pytest

from protocol import messages as m
from services.jog.evdev_input import AxisMap, EvdevStick, GamepadMap, parse_evtest
from services.jog.mapping import (JogMapping, SpasmFilter, SpasmFilterConfig, StickInput, StickMapper,
                                  apply_dead_band, lock_diagonals, speed_factor)
from services.jog.script import DeviceCondition, script_from_mapping, step_at
from services.jog.sender import JogStamper, script_reader, stream
from services.runtime.config import ConfigError

DATA = Path(__file__).parent / "data"


def test_the_dead_band_zeroes_a_resting_stick_and_the_rest_rises_from_zero_at_its_edge():
    out = apply_dead_band([0.05, -0.1, 0.55], 0.1)
    assert out[0] == 0.0 and out[1] == 0.0 and out[2] == pytest.approx(0.5)
    assert apply_dead_band([1.0, -1.0, 3.0], 0.1).tolist() == [1.0, -1.0, 1.0]  # full, and clipped
    assert lock_diagonals(np.array([0.3, -0.6, 0.2])).tolist() == [0.0, -0.6, 0.0]
    assert [speed_factor(level) for level in m.JOG_SPEED_LEVELS] == [0.25, 0.5, 1.0]
    with pytest.raises(ValueError, match="speed level 4"):
        speed_factor(4)


def test_the_spasm_filter_ramps_a_sudden_push_but_passes_a_release_at_once():
    config = SpasmFilterConfig(rise_s=0.25, jerk_s=0.1)
    spasm = SpasmFilter(config, n=1)
    values = [spasm(np.array([1.0]), 0.01 * i)[0] for i in range(60)]
    assert values[0] == 0.0 and 0.0 < values[5] < 0.2  # a step in, a ramp out: no jump, and the rate ramps too
    rates = np.diff(values) / 0.01
    assert rates.max() <= 1.0 / config.rise_s + 1e-9 and np.diff(rates).max() <= 1.0 / (0.25 * 0.1) * 0.01 + 1e-9
    assert values[-1] == pytest.approx(1.0)  # full within rise_s + jerk_s (0.35 s) and a little
    assert spasm(np.array([0.2]), 0.61)[0] == pytest.approx(0.2)  # let go toward the centre: at once
    assert spasm(np.array([-0.5]), 0.62)[0] == 0.0  # across the centre: through rest, then a ramp again


def test_the_mapper_gives_each_mode_its_own_motion_at_the_speed_level_and_nothing_without_the_deadman():
    mapping = JogMapping(spasm_filter=SpasmFilterConfig(enabled=False))
    mapper = StickMapper(mapping)
    motion = mapper(StickInput(axes=(1.0, 0.0, -0.55), mode=m.JogMode.TRANSLATION, speed_level=3, deadman=True), 0.0)
    assert motion.linear == pytest.approx((0.2, 0.0, -0.1)) and motion.angular == (0.0, 0.0, 0.0)
    motion = mapper(StickInput(axes=(0.0, 1.0, 0.0), mode=m.JogMode.WRIST, speed_level=2, deadman=True), 0.1)
    assert motion.angular == pytest.approx((0.0, 0.3, 0.0)) and motion.linear == (0.0, 0.0, 0.0)
    motion = mapper(StickInput(axes=(-1.0, 0.0, 0.0), mode=m.JogMode.FINGERS, speed_level=1, deadman=True), 0.2)
    assert motion.finger_rate == pytest.approx(-0.25)
    released = mapper(StickInput(axes=(1.0, 1.0, 1.0), mode=m.JogMode.TRANSLATION, speed_level=3, deadman=False), 0.3)
    assert not released.deadman and released.linear == (0.0, 0.0, 0.0)


def test_a_script_says_what_is_wrong_with_it_and_its_steps_inherit_mode_and_level():
    script = script_from_mapping({"rate_hz": 20, "speed_level": 2, "steps": [
        {"for_s": 1.0, "mode": "wrist", "axes": [0, 0, 0.5], "deadman": True},
        {"for_s": 0.5, "axes": [0, 0, 0.5], "deadman": True, "device": "frozen", "speed_level": 1},
        {"for_s": 0.5, "resume": True}]})
    assert [s.mode for s in script.steps] == [m.JogMode.WRIST] * 3 and [s.speed_level for s in script.steps] == [2, 1, 2]
    assert script.duration_s == 2.0 and step_at(script, 1.2)[0] == 1 and step_at(script, 2.0) is None
    assert script.steps[1].device is DeviceCondition.FROZEN
    for bad, why in [({"steps": []}, "at least one step"), ({"steps": [{"for_s": 0}]}, "for_s"),
                     ({"steps": [{"for_s": 1, "mode": "elbow"}]}, "steps[0].mode"),
                     ({"rate_hz": 0.5, "steps": [{"for_s": 1}]}, "rate_hz"),
                     ({"steps": [{"for_s": 1, "axes": [0, 0]}]}, "axes"),
                     ({"steps": [{"for_s": 1, "axis": [0, 0, 0]}]}, "unknown field `axis`"),
                     ({"steps": [{"for_s": 400}, {"for_s": 400}]}, "more than 600 s")]:
        with pytest.raises(ConfigError, match=why.replace("[", r"\[").replace("]", r"\]")):
            script_from_mapping(bad)


def test_the_stream_stamps_and_sequences_each_request_says_when_the_device_was_heard_and_skips_late_slots():
    script = script_from_mapping({"rate_hz": 10, "steps": [
        {"for_s": 0.3, "mode": "translation", "axes": [0.5, 0, 0], "deadman": True},
        {"for_s": 0.2, "axes": [0.5, 0, 0], "deadman": True, "device": "frozen"},
        {"for_s": 0.2, "deadman": True, "device": "silent"},
        {"for_s": 0.1, "resume": True}]})
    clock = {"t": 0.0}
    late = {0.1}  # the host stalls 0.25 s at 0.1 s: the slots it missed are skipped, not sent in a burst

    def sleep(s):
        clock["t"] += s

    def now():
        if late and clock["t"] >= 0.1 - 1e-9:
            clock["t"] += 0.25
            late.clear()
        return clock["t"]

    sent, resumes = [], []
    stamper = JogStamper("jog/test", now_ns=lambda: int(clock["t"] * 1e9))
    report = stream(script_reader(script), JogMapping(), stamper, sent.append, script.rate_hz,
                    resume=lambda: resumes.append(clock["t"]), clock=now, sleep=sleep)
    assert [j.header.seq for j in sent] == list(range(1, len(sent) + 1))  # rising, whatever was skipped
    assert report.missed >= 1 and report.sent == len(sent) and resumes and report.resumes == 1
    frozen = [j for j in sent if j.header.source_stamp_ns < j.header.stamp_ns]
    assert frozen and all(j.header.source_stamp_ns == frozen[0].header.source_stamp_ns for j in frozen)
    assert all(j.source == "jog/test" and j.mode is m.JogMode.TRANSLATION for j in sent)
    assert len(sent) < script.duration_s * script.rate_hz  # the silent step sent nothing


def test_a_gamepads_recorded_events_drive_the_stick_as_its_map_says():
    """The events of an Xbox 360 pad (the kernel's xpad driver) in evtest's format: written by hand from the
    format and the driver's ranges (no device was at hand), not recorded from a pad."""
    ranges, events = parse_evtest((DATA / "xbox_pad.evtest").read_text())
    assert ranges[0].minimum == -32768 and ranges[0].maximum == 32767 and ranges[2].maximum == 255
    stick = EvdevStick(GamepadMap(), ranges, speed_level=1)
    seen = []
    for t, kind, code, value in events:
        stick.event(kind, code, value)
        if kind == 0 and code == 0:  # at each report
            seen.append((t, stick.input(), stick.take_resume()))
    first = seen[0][1]
    assert first.deadman and first.mode is m.JogMode.TRANSLATION and abs(first.axes[0]) < 0.01
    half_up = seen[1][1]
    assert half_up.axes[0] == pytest.approx(0.5, abs=0.01)  # stick up: +X of the base (the kernel's Y inverted)
    full = seen[2][1]
    assert full.axes[0] == pytest.approx(1.0, abs=0.01) and full.axes[1] == pytest.approx(-0.25, abs=0.01)
    assert seen[3][1].mode is m.JogMode.WRIST and seen[4][1].mode is m.JogMode.WRIST  # A pressed once: one step
    # the events after a SYN_DROPPED until its report are not taken (the reader then reads the device afresh)
    assert seen[5][1].axes[1] == pytest.approx(-0.25, abs=0.01)
    assert seen[6][1].speed_level == 2 and seen[7][2] is True  # speed up; the resume button
    assert not seen[8][1].deadman
    with pytest.raises(Exception, match="no axis ABS_HAT0X"):
        EvdevStick(GamepadMap(axes=[AxisMap(code=c) for c in ("ABS_HAT0X", "ABS_X", "ABS_Y")]), ranges)
    with pytest.raises(ValueError, match="not an input event code"):
        GamepadMap(deadman="BTN_NOPE")


def test_a_virtual_gamepad_needs_uinput():
    """A virtual evdev device (python-evdev's UInput) read back by the real reader: where /dev/uinput exists."""
    import os

    if not os.path.exists("/dev/uinput"):
        pytest.skip("/dev/uinput does not exist on this machine (no uinput module, or a container without it)")
    import time

    from evdev import AbsInfo, UInput, ecodes

    from services.jog.evdev_input import DeviceReader, open_device, stick_of

    caps = {ecodes.EV_KEY: [ecodes.BTN_TL, ecodes.BTN_SOUTH, ecodes.BTN_TR, ecodes.BTN_WEST, ecodes.BTN_START],
            ecodes.EV_ABS: [(code, AbsInfo(0, -32768, 32767, 16, 128, 0))
                            for code in (ecodes.ABS_X, ecodes.ABS_Y, ecodes.ABS_RY)]}
    with UInput(caps, name="mfvs-test-pad") as pad:
        time.sleep(0.2)
        device = open_device(pad.device.path)
        reader = DeviceReader(device, stick_of(device, GamepadMap(), 1)).start()
        try:
            pad.write(ecodes.EV_KEY, ecodes.BTN_TL, 1)
            pad.write(ecodes.EV_ABS, ecodes.ABS_Y, -32768)
            pad.syn()
            time.sleep(0.2)
            with reader.lock:
                stick = reader.stick.input()
            assert stick.deadman and stick.axes[0] == pytest.approx(1.0, abs=0.01)
            assert reader.heard_within(0.1)
        finally:
            reader.stop()


@pytest.mark.parametrize("path", sorted((Path(__file__).parents[3] / "examples" / "jog").glob("*.yaml")),
                         ids=lambda p: p.name)
def test_the_shipped_scripts_load(path):
    from services.jog.script import load_script

    assert load_script(path).duration_s > 0
