"""The console's stick in a real browser (Debian's Chromium, headless, driven by Selenium): a gamepad read through
the page's Gamepad API, and the on-screen stick dragged with the browser's own pointer, each sent by the console as
jog requests on ``jog/request`` (read back by a zenoh subscriber on the test's router).

Chromium's own gamepad layer (its reading of a device under /dev/input) is not tested: no device is at hand, and a
headless browser has none. A scripted ``navigator.getGamepads`` (installed before the page's own script by Chrome
DevTools' ``Page.addScriptToEvaluateOnNewDocument``) stands in for it, returning a standard-mapping pad whose axes
and buttons the test sets; everything from there on (the page's polling and map, the WebSocket, the console's
checks, mapping, stamping and stream) is the code as shipped."""
import time

import pytest

from bench.console import Browser
from protocol import messages as m
from protocol.messages import JogMode
from services.runtime.transport import Router, open_session
from services.stack.local import ConsoleProcess
from tests.stack import KEYS, Recorder, wait_for


#: a standard-mapping pad (the W3C Gamepad spec's layout: 4 axes, 17 buttons) whose state the test sets
SCRIPTED_PAD = """
window.__pad = { id: "scripted standard pad (test)", index: 0, connected: true, mapping: "standard", timestamp: 1000,
                 axes: [0, 0, 0, 0],
                 buttons: Array.from({ length: 17 }, () => ({ pressed: false, touched: false, value: 0 })) };
window.__padPresent = true;
window.__setPad = (axes, pressed) => {
  window.__pad.axes = axes.slice();
  window.__pad.buttons = Array.from({ length: 17 }, (_, i) => {
    const on = pressed.includes(i);
    return { pressed: on, touched: on, value: on ? 1 : 0 };
  });
  window.__pad.timestamp += 16;  // the Gamepad API moves it only when the pad's state changes
};
Object.defineProperty(Navigator.prototype, "getGamepads", {
  configurable: true,
  value: function () { return [window.__padPresent ? window.__pad : null, null, null, null]; },
});
"""
LEFT_BUMPER, A, RIGHT_BUMPER = 4, 0, 5


def set_pad(driver, axes=(0, 0, 0, 0), pressed=()):
    driver.execute_script("window.__setPad(arguments[0], arguments[1])", list(axes), list(pressed))


def since(recorder: Recorder, start: int) -> list[m.Jog]:
    return recorder.snapshot()[start:]


def wait_for_jog(recorder: Recorder, start: int, predicate, timeout=5.0) -> m.Jog:
    found = []
    assert wait_for(lambda: found.extend(j for j in since(recorder, start) if predicate(j)) or found, timeout=timeout), \
        [(j.mode.value, j.deadman, j.linear, j.angular) for j in since(recorder, start)[-5:]]
    return found[0]


def held_after(recorder: Recorder, start: int) -> list[m.Jog]:
    return [j for j in since(recorder, start) if j.deadman]


def quiet(recorder: Recorder, seconds: float) -> int:
    """How many requests arrived within ``seconds`` (after the stream had its time to stop)."""
    before = len(recorder)
    time.sleep(seconds)
    return len(recorder) - before


def test_a_gamepad_and_the_on_screen_stick_in_the_browser_become_jog_requests_and_stop_on_release(tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    with Router() as router:
        session = open_session(router.client_config())
        jogs = Recorder(session, KEYS.desired_jog, m.Jog)
        try:
            with ConsoleProcess(router.endpoint) as console, Browser(1280, 1000) as driver:
                driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": SCRIPTED_PAD})
                driver.get(console.url)
                assert wait_for(lambda: driver.execute_script("return window.mfvsConsole.jog.enabled"), timeout=10)

                # the pad's dead-man (left bumper) held, its left stick pushed up: +X of the base, translation
                start = len(jogs)
                set_pad(driver, axes=(0, -0.8, 0, 0), pressed=[LEFT_BUMPER])
                first = wait_for_jog(jogs, start, lambda j: j.deadman and j.linear[0] > 0)
                assert first.mode is JogMode.TRANSLATION and first.source == "jog/console" and first.speed_level == 1
                assert first.linear[1] == 0.0 and first.linear[2] == 0.0 and not any(first.angular)
                assert "gamepad scripted standard pad" in driver.find_element(By.ID, "jog-state").text
                assert "HELD" in driver.find_element(By.ID, "jog-state").text
                # at full ramp: (0.8 - 0.1) / 0.9 of 0.2 m/s at level 1 of 3 (a quarter)
                full = wait_for_jog(jogs, start, lambda j: j.deadman and j.linear[0] >= 0.0388)
                assert full.linear[0] == pytest.approx(0.7 / 0.9 * 0.2 * 0.25, rel=1e-6)
                assert all(b.header.seq > a.header.seq for a, b in zip(since(jogs, start), since(jogs, start)[1:]))

                # A cycles the mode (to wrist), the right bumper steps the level up twice; the right stick's Y
                # turns about the hand's z
                for buttons in ([LEFT_BUMPER, A], [LEFT_BUMPER], [LEFT_BUMPER, RIGHT_BUMPER], [LEFT_BUMPER],
                                [LEFT_BUMPER, RIGHT_BUMPER], [LEFT_BUMPER]):
                    set_pad(driver, pressed=buttons)
                    time.sleep(0.08)
                start = len(jogs)
                set_pad(driver, axes=(0, 0, 0, -1.0), pressed=[LEFT_BUMPER])
                turn = wait_for_jog(jogs, start, lambda j: j.deadman and j.angular[2] > 0)
                assert turn.mode is JogMode.WRIST and turn.speed_level == 3 and not any(turn.linear)
                # full stick at the top level: 0.6 rad/s once the spasm filter's ramp is through
                assert wait_for_jog(jogs, start, lambda j: j.deadman and j.angular[2] >= 0.6 - 1e-9).angular[2] \
                    == pytest.approx(0.6)

                # the dead-man released: a released request, and no more motion
                start = len(jogs)
                set_pad(driver, axes=(0, 0, 0, -1.0), pressed=[])
                released = wait_for_jog(jogs, start, lambda j: not j.deadman)
                assert released.at_rest
                time.sleep(0.3)
                after = since(jogs, start)
                first_release = next(i for i, j in enumerate(after) if not j.deadman)
                assert not any(j.deadman for j in after[first_release:])

                # the pad unplugged: one released snapshot from the page, then silence (the console stops sending)
                driver.execute_script("window.__padPresent = false")
                time.sleep(0.3)
                assert quiet(jogs, 0.5) == 0
                assert "input: none" in driver.find_element(By.ID, "jog-state").text

                # the on-screen stick: held and dragged up with the browser's pointer, in translation mode
                driver.find_element(By.ID, "jog-translation").click()
                pad = driver.find_element(By.ID, "jog-pad")
                driver.execute_script("arguments[0].scrollIntoView({block: 'center'})", pad)
                start = len(jogs)
                chain = ActionChains(driver).move_to_element(pad).click_and_hold()
                chain.move_by_offset(0, -int(pad.size["height"] * 0.45)).perform()
                dragged = wait_for_jog(jogs, start, lambda j: j.deadman and j.linear[0] > 0.1)
                assert dragged.mode is JogMode.TRANSLATION and abs(dragged.linear[1]) < 0.2 * dragged.linear[0]
                assert "on-screen stick" in driver.find_element(By.ID, "jog-state").text
                start = len(jogs)
                ActionChains(driver).release().perform()  # the pointer up: the dead-man let go
                assert wait_for_jog(jogs, start, lambda j: not j.deadman).at_rest
                time.sleep(0.3)
                assert not held_after(jogs, len(jogs)) and quiet(jogs, 0.5) == 0
                stats = driver.execute_script("return window.mfvsConsole.stats.refusals")
                assert not [r for r in stats if r.get("jog")], stats
        finally:
            jogs.close()
            session.close()


def test_behind_authority_the_stick_is_off_without_the_jog_identity_and_drives_as_it_with_its_config(tmp_path):
    """`mfvs authority init`'s deployment (user/password, access control on the router): the console as the
    operator alone has its stick off, says why on the page, and refuses a snapshot sent anyway; given the jog
    identity's config (--jog-zenoh-config) the pad's requests go through the router's access control as jog's."""
    from selenium.webdriver.common.by import By

    from services.runtime.authority import write_deployment
    from services.runtime.transport import ZenohConfig, free_loopback_port

    deployment = write_deployment(tmp_path / "authority", port=free_loopback_port())
    operator, jog = (str(deployment.client_configs[name]) for name in ("operator", "jog"))
    with Router(port=None, config_file=deployment.router_config):
        session = open_session(ZenohConfig(connect=[deployment.endpoint],
                                           config_file=str(deployment.client_configs["safety"])))
        jogs = Recorder(session, KEYS.desired_jog, m.Jog)
        try:
            with Browser(1280, 1000) as driver:
                driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": SCRIPTED_PAD})
                with ConsoleProcess(deployment.endpoint, "--zenoh-config", operator) as console:
                    driver.get(console.url)
                    why = driver.find_element(By.ID, "jog-why")
                    assert wait_for(lambda: why.is_displayed() and "--jog-zenoh-config" in why.text, timeout=10)
                    assert "off" in driver.find_element(By.ID, "jog-pad").get_attribute("class")
                    set_pad(driver, axes=(0, -1, 0, 0), pressed=[LEFT_BUMPER])
                    driver.execute_script("""window.mfvsConsole.page.ws.send(JSON.stringify({type: "jog", seq: 1,
                        input: "stick", axes: [1, 0, 0], deadman: true, mode: "translation", speed_level: 1}))""")
                    assert wait_for(lambda: "jog_disabled" in [r["reason"] for r in driver.execute_script(
                        "return window.mfvsConsole.stats.refusals")], timeout=5)
                    assert quiet(jogs, 0.5) == 0 and len(jogs) == 0
                with ConsoleProcess(deployment.endpoint, "--zenoh-config", operator,
                                    "--jog-zenoh-config", jog) as console:
                    driver.get(console.url)
                    assert wait_for(lambda: driver.execute_script("return window.mfvsConsole.jog.enabled"),
                                    timeout=10)
                    assert not driver.find_element(By.ID, "jog-why").is_displayed()
                    set_pad(driver, axes=(0, -1, 0, 0), pressed=[LEFT_BUMPER])
                    moving = wait_for_jog(jogs, 0, lambda j: j.deadman and j.linear[0] > 0)
                    assert moving.source == "jog/console"
                    set_pad(driver, axes=(0, -1, 0, 0), pressed=[])
                    assert wait_for_jog(jogs, len(jogs), lambda j: not j.deadman).at_rest
        finally:
            jogs.close()
            session.close()
