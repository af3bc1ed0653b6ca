"""``mfvs check rs485``: the first hour on a real arm's actuator bus, through Kinova's USB comm layer, as a report a
person can send back. What it measures is what no public source shows and what the gateway's kinova_usb bus
relies on (docs/robot.md, docs/rs485-sources.md):

1. the device as the comm layer lists it, and the joints through Kinova's high-level API just before activation;
2. what an empty read does (its code and how long it takes: the library's own timeout is 5 s);
3. the 0x01 → 0x02 round trip: per-call latency of Write and Read, replies per request, and where 0x02 puts the
   position (float[1] against the high-level reading; the other floats reported);
4. one position-mode 0x14 to each actuator with its own position as the target (the arm holds where it is), only
   once the 0x02 positions agreed with the high-level reading: the replies each actuator sends (0x15, 0x16, 0x17,
   anything else), and their layouts against that position (0x15 float[1], 0x16 float[1] and its temperature,
   0x17 float[1]);
5. asked for only (``--torque-joint N --yes``, the arm supported): the torque handshake on that joint alone, 0x208
   with the description's torque limit (acknowledged), 0x201 validation with the model's gravity torque, 0x203 to torque mode, 0.2 s of torque commands carrying the model's
   gravity, 0x203 back; the 0x202 and 0x204 replies and how far the joint moved.

Nothing moves unless step 5 is asked for. Each step's verdict is ``agrees``, ``differs`` or ``no reply``; the
check stops at the first step whose verdict would make the next unsafe. Pure steps on a bus object (the
kinova_usb bus's surface), so the tests run them against robot_sim's emulated base.
"""
from __future__ import annotations

import json
import platform
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from protocol import rs485 as r
from services.model.arm import ArmDescription
from services.robot_gateway.kinova_usb import HIGH_LEVEL_CHECK_DEG, KinovaUsbBus, around_deg

#: how long a step waits for replies (s)
REPLY_WAIT_S = 0.05
#: plausible actuator temperatures (°C): outside, the 0x16 layout is not what the sources say
TEMPERATURE_RANGE_C = (0.0, 80.0)


@dataclass
class Step:
    name: str
    verdict: str
    detail: str
    figures: dict = field(default_factory=dict)


def _ms(seconds: list[float]) -> dict:
    values = np.asarray(seconds) * 1e3
    if values.size == 0:
        return {}
    return {"n": int(values.size), "p50_ms": round(float(np.median(values)), 3),
            "max_ms": round(float(values.max()), 3)}


def _collect(bus: KinovaUsbBus, wait_s: float) -> tuple[np.ndarray, list[float]]:
    """Everything the base sends within ``wait_s``, and how long each read took."""
    got, times = [], []
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        started = time.perf_counter()
        batch, _ = bus.recv_batch(0.0)
        times.append(time.perf_counter() - started)
        if len(batch):
            got.append(batch)
    return (np.concatenate(got) if got else r.records(0)), times


def empty_read(bus: KinovaUsbBus, reads: int = 5) -> Step:
    """What a read with nothing queued returns, and how long it takes."""
    before = bus.counters.get("usb.empty_reads")
    times = []
    for _ in range(reads):
        started = time.perf_counter()
        batch, _ = bus.recv_batch(0.0)
        times.append(time.perf_counter() - started)
        if len(batch):
            return Step("empty read", "differs", f"the base sent {len(batch)} message(s) no one asked for",
                        {"unsolicited": _records_hex(batch)})
    empty = bus.counters.get("usb.empty_reads") - before
    figures = {"read": _ms(times), "empty_reads": empty}
    slow = max(times) > 1.0
    return Step("empty read", "agrees" if empty == reads else "differs",
                f"{empty} of {reads} reads came back empty (1016/1020) in {figures['read'].get('p50_ms')} ms "
                f"(p50){'; a read that waits for the library timeout stalls the bus loop' if slow else ''}", figures)


def positions(bus: KinovaUsbBus, arm: ArmDescription, expected_deg: Optional[np.ndarray],
              rounds: int = 20) -> tuple[Step, Optional[np.ndarray]]:
    """0x01 to every actuator, ``rounds`` times: write and read latency, replies per request, and 0x02's float[1]
    against the high-level reading."""
    addresses = list(arm.bus_addresses)
    request = r.to_records(r.RS485Message(r.Command.GET_ACTUAL_POSITION, r.HOST_ADDRESS, a) for a in addresses)
    writes, reads, round_trips, counts, last = [], [], [], [], None
    for _ in range(rounds):
        started = time.perf_counter()
        bus.send_batch(request)
        writes.append(time.perf_counter() - started)
        replies, read_times = _collect(bus, REPLY_WAIT_S)
        reads += read_times
        round_trips.append(time.perf_counter() - started)
        answers = replies[replies["command"] == r.Command.SEND_ACTUAL_POSITION]
        counts.append(len(answers))
        if len(answers) == len(addresses):
            last = answers
    figures = {"write": _ms(writes), "read": _ms(reads), "round_trip": _ms(round_trips),
               "replies_per_round": counts}
    if last is None:
        return Step("0x01 → 0x02", "no reply", f"no round of {rounds} brought a 0x02 from every actuator "
                                                f"({max(counts)} of {len(addresses)} at most)", figures), None
    floats = np.zeros((len(addresses), 4))
    for record in last:
        floats[addresses.index(int(record["source"]))] = record["data"]
    position = floats[:, r.POSITION_FLOAT]
    figures["floats"] = floats.round(3).tolist()
    if expected_deg is None:
        return Step("0x01 → 0x02", "agrees", "every actuator answered (no high-level reading to compare)",
                    figures), position
    off = around_deg(position, expected_deg)
    figures["float1_minus_high_level_deg"] = off.round(3).tolist()
    agrees = bool(np.all(np.abs(off) <= HIGH_LEVEL_CHECK_DEG))
    return Step("0x01 → 0x02", "agrees" if agrees else "differs",
                f"float[1] is the position within {np.abs(off).max():.2f}° of the high-level reading"
                if agrees else f"float[1] is {np.abs(off).max():.1f}° from the high-level reading: the position is "
                               "not where the public drivers read it", figures), (position if agrees else None)


def command_replies(bus: KinovaUsbBus, arm: ArmDescription, position_deg: np.ndarray) -> Step:
    """One position-mode 0x14 to each actuator, its own position as the target: which replies come back, and their
    layouts against that position."""
    addresses = list(arm.bus_addresses)
    started = time.perf_counter()
    bus.send_batch(r.position_torque_records(addresses, position_deg))
    replies, _ = _collect(bus, REPLY_WAIT_S)
    elapsed = time.perf_counter() - started
    kinds: dict[str, dict[str, int]] = {}
    for record in replies:
        name = r.Command(int(record["command"])).name if r.known_commands(record[None])[0] else hex(record["command"])
        kinds.setdefault(f"0x{int(record['source']):02X}", {}).setdefault(name, 0)
        kinds[f"0x{int(record['source']):02X}"][name] += 1
    figures: dict = {"replies": kinds, "round_trip_ms": round(elapsed * 1e3, 3), "raw": _records_hex(replies)}
    expected = {"SEND_ALL_VALUES_1": 1, "SEND_ALL_VALUES_2": 1, "SEND_ALL_VALUES_3": 1}
    missing = [f"0x{a:02X}" for a in addresses if kinds.get(f"0x{a:02X}") != expected]
    layouts = _layouts(replies, addresses, position_deg)
    figures["layouts"] = layouts
    wrong = [name for name, ok in layouts.items() if not ok]
    if missing:
        return Step("0x14 replies", "differs", f"not one 0x15, 0x16 and 0x17 from {', '.join(missing)}", figures)
    if wrong:
        return Step("0x14 replies", "differs", f"one of each, but {', '.join(wrong)} not as the sources say",
                    figures)
    return Step("0x14 replies", "agrees", "one 0x15, 0x16 and 0x17 from every actuator, laid out as the public "
                                          "drivers read them", figures)


def _layouts(replies: np.ndarray, addresses: list[int], position_deg: np.ndarray) -> dict[str, bool]:
    """Whether each reply kind carries the position where the sources put it (and 0x16 a plausible temperature)."""
    out = {}
    for command, label in ((r.Command.SEND_ALL_VALUES_1, "0x15 float[1]"), (r.Command.SEND_ALL_VALUES_2, "0x16 float[1]"),
                           (r.Command.SEND_ALL_VALUES_3, "0x17 float[1]")):
        chosen = replies[replies["command"] == command]
        if len(chosen) == 0:
            continue
        joints = [addresses.index(int(s)) for s in chosen["source"]]
        out[label] = bool(np.all(np.abs(around_deg(chosen["data"][:, 1], position_deg[joints])) <= HIGH_LEVEL_CHECK_DEG))
        if command is r.Command.SEND_ALL_VALUES_2:
            temperature = chosen["data"].view("<i2")[:, r.TEMPERATURE_SHORT] * 0.01
            low, high = TEMPERATURE_RANGE_C
            out["0x16 temperature"] = bool(np.all((temperature >= low) & (temperature <= high)))
    return out


def _records_hex(batch: np.ndarray) -> list[str]:
    return [bytes(record.tobytes()).hex() for record in batch[:60]]


def torque_handshake(bus: KinovaUsbBus, arm: ArmDescription, joint: int, position_deg: np.ndarray,
                     gravity_physical: np.ndarray, seconds: float = 0.2) -> Step:
    """The handshake on one joint (1-based) alone: validation with the model's gravity torque, torque mode, the
    model's gravity as the torque for ``seconds``, position mode again."""
    address = arm.bus_addresses[joint - 1]
    expected = float(gravity_physical[joint - 1])
    figures: dict = {"joint": joint, "expected_torque_nm": round(expected, 3)}

    def ask(message: r.RS485Message, reply: r.Command) -> Optional[r.RS485Message]:
        bus.send_batch(r.to_records([message]))
        replies, _ = _collect(bus, REPLY_WAIT_S)
        found = [m for m in r.from_records(replies) if m.command is reply and m.source == address]
        return found[0] if found else None

    limit = ask(r.torque_config_safety(float(arm.max_torque[joint - 1]), address), r.Command.ACK)
    figures["0x208 ack"] = None if limit is None else limit.uints[0]
    if limit is None or limit.uints[0] != r.Command.TORQUE_CONFIG_SAFETY:
        return Step("torque handshake", "no reply" if limit is None else "differs",
                    "the torque limit (0x208) was not acknowledged: torque mode not asked for", figures)
    validation = ask(r.RS485Message.with_floats(r.Command.GET_TORQUE_VALIDATION_REQUEST, r.HOST_ADDRESS, address,
                                                [expected]), r.Command.SEND_TORQUE_VALIDATION)
    figures["0x202"] = None if validation is None else validation.uints[0]
    if validation is None or validation.uints[0] != 1:
        return Step("torque handshake", "no reply" if validation is None else "differs",
                    "the validation was not accepted: torque mode not asked for", figures)
    switched = ask(r.switch_mode_request(r.ControlModeRequest.TORQUE, address), r.Command.SWITCH_CONTROL_MODE_REPLY)
    figures["0x204 torque"] = None if switched is None else switched.uints[0]
    start = float(position_deg[joint - 1])
    last = start
    try:
        if switched is None or r.parse_switch_mode_reply(switched) is not r.ControlModeReply.TORQUE_OK:
            return Step("torque handshake", "differs", "torque mode refused", figures)
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            bus.send_batch(r.position_torque_records([address], [last], [expected]))
            replies, _ = _collect(bus, 0.004)
            values = replies[(replies["command"] == r.Command.SEND_ALL_VALUES_1) & (replies["source"] == address)]
            if len(values):
                last = float(values["data"][-1, 1])
    finally:
        back = ask(r.switch_mode_request(r.ControlModeRequest.POSITION, address), r.Command.SWITCH_CONTROL_MODE_REPLY)
        figures["0x204 position"] = None if back is None else back.uints[0]
    figures["moved_deg"] = round(float(around_deg(last, start)), 3)
    return Step("torque handshake", "agrees", f"validated, torque mode for {seconds:.1f} s on the model's gravity "
                                              f"(joint {joint} moved {figures['moved_deg']:+.2f}°), position mode "
                                              "again", figures)


def report_markdown(device: dict, steps: list[Step]) -> str:
    lines = ["# mfvs check rs485", "",
             f"Host: {platform.node()} ({platform.platform()}); {time.strftime('%Y-%m-%d %H:%M:%S %Z')}", "",
             "| device | |", "| --- | --- |"]
    lines += [f"| {key} | {value} |" for key, value in device.items()]
    lines += ["", "| step | verdict | detail |", "| --- | --- | --- |"]
    lines += [f"| {s.name} | {s.verdict} | {s.detail} |" for s in steps]
    lines += ["", "## Figures", "", "```json", json.dumps({s.name: s.figures for s in steps}, indent=1), "```", ""]
    return "\n".join(lines)


def run_check(arm: ArmDescription, comm_layer, command_layer=None, torque_joint: Optional[int] = None,
              torque_asked: bool = False) -> tuple[dict, list[Step]]:
    """Every step on the arm behind the comm layer (its bus opened and activated here, closed at the end): the
    device as listed, and the steps in order, stopping where going on would not be safe."""
    from services.model.kinematics import ArmKinematics
    from services.robot_gateway.kinova_usb import open_kinova_usb

    bus = open_kinova_usb(comm_layer, arm.name, arm.n_joints, command_layer=command_layer)
    try:
        device = {"serial": bus.serial, "model": bus.model, "comm layer": str(comm_layer),
                  "high-level reading (deg)": "not read (no command layer)" if bus.high_level_deg is None
                  else ", ".join(f"{v:.2f}" for v in bus.high_level_deg),
                  "dropped at activation": bus.counters.get("usb.dropped_at_activation")}
        steps = [empty_read(bus)]
        step, position = positions(bus, arm, bus.high_level_deg)
        steps.append(step)
        if position is None:
            return device, steps
        steps.append(command_replies(bus, arm, position))
        if torque_joint is not None:
            if not torque_asked:
                steps.append(Step("torque handshake", "not run", "asked for without --yes: the arm may move"))
            elif steps[-1].verdict != "agrees":
                steps.append(Step("torque handshake", "not run", "the 0x14 replies did not agree"))
            else:
                q = arm.physical_deg_to_model(position)
                gravity = arm.sign * ArmKinematics(arm).gravity(q)
                steps.append(torque_handshake(bus, arm, torque_joint, position, gravity))
        device["calls into the library (p50 / max ms)"] = ", ".join(
            f"{name} {figures['p50_ms']:.2f} / {figures['max_ms']:.2f}"
            for name, figures in ((n, d.stats()) for n, d in bus.call_times.items()) if figures["n"])
        return device, steps
    finally:
        bus.close()
