"""The console's stick as pure rules (services/console/jog.py): a page's snapshot validated (a clear refusal for
NaN, out of range, an unknown mode, wrong types), mapped by services/jog/mapping.py into jog requests, one per slot;
a silent page released once and then not acted on; a released pointer a released request; one page at a time."""
import json
import math

import pytest

from protocol import messages as m
from protocol.messages import JogMode
from services.console.core import Refused, parse_page_message
from services.console.jog import ConsoleJog, ConsoleJogConfig, JogRefused, JogSnapshot, check_snapshot
from services.jog.mapping import JogMapping, SpasmFilterConfig

MS = 1_000_000
T0 = 1_700_000_000_000_000_000


def snapshot(seq=1, axes=(0.5, 0.0, 0.0), deadman=True, mode="translation", level=3, input="stick", gamepad=None):
    message = {"type": "jog", "seq": seq, "input": input, "axes": list(axes), "deadman": deadman, "mode": mode,
               "speed_level": level}
    if gamepad is not None:
        message["gamepad"] = gamepad
    return message


def parsed(message) -> JogSnapshot:
    found = parse_page_message(json.dumps(message) if not isinstance(message, str) else message)
    assert isinstance(found, JogSnapshot)
    return found


def relay(**mapping) -> ConsoleJog:
    """No spasm filter unless asked (the mapping's own tests cover it): the first request at full deflection."""
    mapping.setdefault("spasm_filter", SpasmFilterConfig(enabled=False))
    return ConsoleJog(ConsoleJogConfig(mapping=JogMapping(**mapping)))


@pytest.mark.parametrize("text, reason", [
    (snapshot(axes=(None, 0, 0)), "jog_not_finite"),  # NaN: the page's JSON.stringify writes it as null
    (snapshot(axes=(0, 1.5, 0)), "jog_range"),
    (snapshot(axes=(0, 0, -1.01)), "jog_range"),
    (snapshot(level=4), "jog_range"),
    (snapshot(level=0), "jog_range"),
    (snapshot(mode="elbow"), "jog_mode"),
    (snapshot(axes=(0, 0)), "jog_malformed"),
    (snapshot(input="keyboard"), "jog_malformed"),
    (snapshot(input="gamepad"), "jog_malformed"),  # a pad's snapshot with nothing of the pad
    (snapshot(input="gamepad", gamepad={"connected": True, "timestamp": -5.0}), "jog_not_finite"),
])
def test_a_snapshot_out_of_range_not_finite_or_of_an_unknown_mode_is_refused_clearly(text, reason):
    message = json.dumps(text).replace("Infinity", "1e400")
    with pytest.raises(JogRefused) as refused:
        check_snapshot(parsed(message))
    assert refused.value.reason == reason and refused.value.message


@pytest.mark.parametrize("message", [
    {**snapshot(), "axes": ["0.5", 0, 0]},
    {**snapshot(), "deadman": "yes"},
    {**snapshot(), "speed_level": 2.5},
    {**snapshot(), "seq": -1},
    {**snapshot(), "extra": 1},
    {**snapshot(), "mode": 3},
])
def test_a_snapshot_of_the_wrong_types_is_refused_as_a_malformed_stick(message):
    with pytest.raises(Refused) as refused:
        parse_page_message(json.dumps(message))
    assert refused.value.reason == "jog_malformed"


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "1e400"])
def test_a_nan_or_infinite_literal_is_refused_before_it_is_a_snapshot(literal):
    with pytest.raises(Refused) as refused:
        parse_page_message(json.dumps(snapshot()).replace("0.5", literal))
    assert refused.value.reason in ("malformed", "jog_malformed")


def test_an_infinite_axis_that_got_through_is_refused_as_not_finite():
    with pytest.raises(JogRefused) as refused:
        check_snapshot(JogSnapshot(seq=1, input="stick", axes=[0.0, math.inf, 0.0], deadman=True, mode="wrist",
                                   speed_level=1))
    assert refused.value.reason == "jog_not_finite"


def test_the_stick_is_mapped_into_requests_of_its_mode_direction_and_speed_level():
    jog = relay()
    jog.offer(1, parsed(snapshot(axes=(0.0, -1.0, 0.0), level=3)), T0)
    first = jog.tick(T0 + 5 * MS)
    assert first.mode is JogMode.TRANSLATION and first.deadman and first.source == "jog/console"
    assert first.linear[0] == 0.0 and first.linear[1] == pytest.approx(-0.2) and first.linear[2] == 0.0
    assert first.header.source_stamp_ns == T0  # when the page was last heard: its snapshot's arrival
    jog.offer(1, parsed(snapshot(seq=2, axes=(0.0, 0.0, 0.55), mode="wrist", level=1)), T0 + 10 * MS)
    second = jog.tick(T0 + 20 * MS)
    assert second.mode is JogMode.WRIST and second.speed_level == 1 and not any(second.linear)
    assert second.angular[2] == pytest.approx(0.5 * 0.6 * 0.25)  # (0.55-0.1)/0.9 of 0.6 rad/s, level 1: a quarter
    assert second.header.seq > first.header.seq and second.header.stamp_ns == T0 + 20 * MS
    jog.offer(1, parsed(snapshot(seq=3, axes=(-1.0, 0.0, 0.0), mode="fingers")), T0 + 30 * MS)
    third = jog.tick(T0 + 40 * MS)
    assert third.finger_rate == pytest.approx(-1.0) and not any(third.angular)


def test_a_page_that_falls_silent_is_released_once_and_then_nothing_is_sent():
    jog = relay()
    jog.offer(1, parsed(snapshot()), T0)
    sent = [jog.tick(T0 + k * 20 * MS) for k in range(10)]  # 0 .. 180 ms after the only snapshot
    fresh, stale = sent[:6], sent[6:]
    assert all(j.deadman and j.linear[0] > 0 for j in fresh)  # within 100 ms of it: 0, 20, .. 100 ms
    assert not stale[0].deadman and stale[0].at_rest  # the first slot past 100 ms: released
    assert stale[1:] == [None, None, None]  # then silence: never motion on an old snapshot
    assert jog.counts.stale == 1 and not jog.status(T0 + 200 * MS)["sending"]
    jog.offer(1, parsed(snapshot(seq=2)), T0 + 500 * MS)  # the page is back
    again = jog.tick(T0 + 505 * MS)
    assert again.deadman and again.header.source_stamp_ns == T0 + 500 * MS


def test_releasing_the_pointer_is_a_released_request_at_once():
    jog = relay(spasm_filter=SpasmFilterConfig())  # the filter on: a release is never slowed by it
    jog.offer(1, parsed(snapshot(axes=(1.0, 0, 0))), T0)
    for k in range(1, 20):
        jog.offer(1, parsed(snapshot(seq=1 + k, axes=(1.0, 0, 0))), T0 + k * 20 * MS)
        moving = jog.tick(T0 + k * 20 * MS + MS)
    assert moving.deadman and moving.linear[0] == pytest.approx(0.2)
    jog.offer(1, parsed(snapshot(seq=30, axes=(0.0, 0, 0), deadman=False)), T0 + 400 * MS)
    released = jog.tick(T0 + 401 * MS)
    assert not released.deadman and released.at_rest and released.linear == (0.0, 0.0, 0.0)


def test_a_page_whose_stream_closes_is_released_at_the_next_slot():
    jog = relay()
    jog.offer(7, parsed(snapshot()), T0)
    assert jog.tick(T0 + MS).deadman
    jog.page_gone(7)
    assert not jog.tick(T0 + 2 * MS).deadman and jog.tick(T0 + 3 * MS) is None


def test_a_gamepad_the_browser_no_longer_calls_connected_is_released_and_not_heard():
    jog = relay()
    pad = {"connected": True, "timestamp": 1234.5, "id": "Xbox", "mapping": "standard"}
    jog.offer(1, parsed(snapshot(input="gamepad", gamepad=pad)), T0)
    held = jog.tick(T0 + MS)
    assert held.deadman and held.header.source_stamp_ns == T0
    # the same timestamp 50 ms on (a pad held still): still heard, a frozen timestamp is not a lost pad
    jog.offer(1, parsed(snapshot(seq=2, input="gamepad", gamepad=pad)), T0 + 50 * MS)
    assert jog.tick(T0 + 51 * MS).header.source_stamp_ns == T0 + 50 * MS
    gone = {**pad, "connected": False}
    jog.offer(1, parsed(snapshot(seq=3, input="gamepad", gamepad=gone)), T0 + 70 * MS)
    lost = jog.tick(T0 + 71 * MS)
    assert not lost.deadman and lost.header.source_stamp_ns == T0 + 50 * MS  # not heard since


def test_one_page_holds_the_stick_until_it_lets_go_and_sequences_must_rise():
    jog = relay()
    jog.offer(1, parsed(snapshot(seq=5)), T0)
    with pytest.raises(JogRefused) as busy:
        jog.offer(2, parsed(snapshot(seq=1, axes=(-1, 0, 0))), T0 + 10 * MS)
    assert busy.value.reason == "jog_busy"
    with pytest.raises(JogRefused) as old:
        jog.offer(1, parsed(snapshot(seq=5)), T0 + 20 * MS)
    assert old.value.reason == "jog_seq"
    jog.offer(1, parsed(snapshot(seq=6, deadman=False)), T0 + 30 * MS)
    jog.offer(2, parsed(snapshot(seq=2, axes=(-1, 0, 0))), T0 + 40 * MS)  # let go: the other page may drive
    assert jog.tick(T0 + 41 * MS).linear[0] < 0


def test_a_console_behind_authority_without_the_jog_identity_refuses_the_stick_and_sends_nothing():
    jog = ConsoleJog(ConsoleJogConfig(), enabled=False, why="no jog identity")
    with pytest.raises(JogRefused) as refused:
        jog.offer(1, parsed(snapshot()), T0)
    assert refused.value.reason == "jog_disabled" and "jog identity" in refused.value.message
    assert jog.tick(T0 + MS) is None and jog.status(T0)["enabled"] is False


def test_the_stream_stopping_holding_says_released_once():
    jog = relay()
    assert jog.release(T0) is None
    jog.offer(1, parsed(snapshot()), T0)
    jog.tick(T0 + MS)
    released = jog.release(T0 + 2 * MS)
    assert not released.deadman and jog.tick(T0 + 3 * MS) is None


def test_the_requests_are_valid_jog_messages_on_the_wire():
    jog = relay()
    jog.offer(1, parsed(snapshot(axes=(0.3, -0.4, 0.9))), T0)
    message = jog.tick(T0 + MS)
    decoded = m.decode(m.encode(message), m.Jog)
    assert decoded == message and all(math.isfinite(v) for v in decoded.linear)


def test_the_page_is_told_who_is_in_control_as_safety_says():
    from services.console.core import ConsoleModel

    model = ConsoleModel()
    model.on_safety(m.SafetyStatus(header=m.Header(), state=m.SafetyState.OK, in_control="jog/console"), 1.0)
    assert model.snapshot(1.1)["safety"]["in_control"] == "jog/console"


def test_a_resume_from_the_page_says_who_and_needs_safety_reporting():
    from services.console.core import Access, Action, ActionMessage, Situation, decide

    access = Access(listen="127.0.0.1")
    with pytest.raises(Refused) as nameless:
        decide(ActionMessage(action=Action.TASK_RESUME), access, Situation(estop_engaged=False))
    assert nameless.value.reason == "operator" and "resumes the task" in nameless.value.message
    with pytest.raises(Refused) as silent:
        decide(ActionMessage(action=Action.TASK_RESUME, operator="ann"), access, Situation(estop_engaged=None))
    assert silent.value.reason == "safety_silent"
    assert decide(ActionMessage(action=Action.TASK_RESUME, operator="ann"), access,
                  Situation(estop_engaged=False)).action is Action.TASK_RESUME
