"""The console in a real browser (Debian's Chromium, headless, driven by Selenium) on a running sim stack in
realtime, every service a process and the console one more, as deployed. What the page does is checked where it
matters: motion and rest on the robot's own states, the task on the controller's answer, the e-stop on safety's
status. Screenshots at a phone's and a desktop's width are kept (the directory is printed; MFVS_TEST_ARTIFACTS
chooses it)."""
import os
import time
from pathlib import Path

import pytest

from bench.console import Browser, page_stats, wait_for_frames
from protocol import messages as m
from protocol.conventions import ClockMode
from services.controller.task_client import call_task
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics
from services.robot.dsp import DSPConfig
from services.robot_sim.service import RobotSimConfig
from services.runtime.transport import open_session
from services.stack.local import ConsoleProcess, LocalStack, StackConfig
from tests.services.safety.test_service_processes import ESTOP_DELIVERY_BUDGET_S, ee_speed, rest_bound, time_to_rest
from tests.stack import KEYS, Recorder, wait_for

TOKEN = "a token for the browser test"
PHONE, DESKTOP = (390, 844), (1280, 1000)
#: from the page's click handler to the e-stop leaving the console (the page's WebSocket, the console's worker
#: thread) on a shared 2-core machine with the stack and the browser busy: generous; the safety budget counts from
#: there
CONSOLE_BUDGET_S = 0.5
#: from the page's click handler to safety's status saying the e-stop is engaged (issue 49)
SAFETY_CONFIRMS_S = 0.25
#: the page's wall clock (performance.timeOrigin + performance.now(), coarsened to 0.1 ms) against the console's
#: (time.time_ns()): the same machine's clock read two ways, a press and its e-stop may be under a millisecond apart
CLOCKS_MS = 2.0

CANVAS_CHECKSUM = """
const c = document.getElementById("camera"), d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
let s = 0; for (let i = 0; i < d.length; i += 61) s = (s * 31 + d[i]) >>> 0; return s;"""


@pytest.fixture(scope="module")
def artefacts(tmp_path_factory):
    directory = Path(os.environ.get("MFVS_TEST_ARTIFACTS") or tmp_path_factory.mktemp("console-screenshots"))
    directory.mkdir(parents=True, exist_ok=True)
    print(f"\nconsole screenshots in {directory}")
    return directory


@pytest.fixture(scope="module")
def shared_stack():
    with LocalStack(StackConfig(clock=ClockMode.REALTIME)) as stack:
        session = open_session(stack.router.client_config())
        states = Recorder(session, KEYS.robot_state, m.RobotState)
        safety = Recorder(session, KEYS.safety_status, m.SafetyStatus)
        estops = Recorder(session, KEYS.estop, m.EStop)
        try:
            yield stack, session, states, safety, estops
        finally:
            for recorder in (states, safety, estops):
                recorder.close()
            session.close()


@pytest.fixture
def sim_stack(shared_stack):
    """The module's stack, left idle with the e-stop released by each test, whatever became of it: a test that
    failed half-way leaves no task running for the next one to find."""
    yield shared_stack
    _, session, _, _, _ = shared_stack
    from services.safety.estop_client import EStopClient

    call_task(session, KEYS, m.STOP_TASK, m.TaskRequest(operator="test", reason="test ended"))
    with EStopClient(session, KEYS) as client:
        client.send(reset=True, operator="test", reason="test ended", timeout_s=5)


def screenshots(driver, artefacts: Path, name: str) -> None:
    for label, (width, height) in (("phone", PHONE), ("desktop", DESKTOP)):
        driver.set_window_size(width, height)
        driver.execute_script("window.scrollTo(0, 0)")
        time.sleep(0.6)
        driver.save_screenshot(str(artefacts / f"console-{name}-{label}.png"))


def click(driver, element_id: str) -> None:
    """A person's click (the browser's own, at the element's place), the element first scrolled to the middle of
    the screen, clear of the bar that stays at its top."""
    from selenium.webdriver.common.by import By

    element = driver.find_element(By.ID, element_id)
    driver.execute_script("arguments[0].scrollIntoView({block: 'center'})", element)
    element.click()


def text(driver, element_id: str) -> str:
    from selenium.webdriver.common.by import By

    return driver.find_element(By.ID, element_id).text


def task_state(session) -> m.TaskState:
    return call_task(session, KEYS, m.GET_TASK).state


def estop_engaged(safety) -> bool:
    return safety.last().state is m.SafetyState.ESTOP


def requests(estops) -> set[int]:
    """The e-stop requests heard (each put again, the same message, until safety confirms it), by their stamps."""
    return {e.header.stamp_ns for e in estops.snapshot()}


def refusals(driver) -> list[str]:
    return [r["reason"] for r in page_stats(driver)["refusals"]]


def test_the_console_shows_the_arm_starts_the_task_stops_the_arm_and_releases_only_on_confirmation(sim_stack,
                                                                                                 artefacts):
    from selenium.webdriver.common.by import By

    stack, session, states, safety, estops = sim_stack
    assert wait_for(lambda: len(states) > 0, timeout=30)
    kin, dsp = ArmKinematics(load_arm(states.last().arm)), DSPConfig()  # the arm the robot declares
    with ConsoleProcess(stack.endpoint) as console, Browser(*DESKTOP) as driver:
        driver.get(console.url)
        first = wait_for_frames(driver, 5)
        assert "mfvs" in driver.title
        later = wait_for_frames(driver, first["frames"] + 5)
        assert later["lastCapture"] > first["lastCapture"]  # new frames, not one drawn again
        assert wait_for(lambda: "idle" in text(driver, "task-state"), timeout=10)
        shows_the_arm_the_robot_declares(driver, load_arm(states.last().arm), states)
        screenshots(driver, artefacts, "idle")

        # start: the task runs (the controller says so) and the arm moves (its states say so)
        driver.find_element(By.ID, "operator").send_keys("tester")
        driver.find_element(By.ID, "reason").send_keys("browser test")
        click(driver, "start")
        assert wait_for(lambda: task_state(session) is m.TaskState.RUNNING, timeout=15)
        assert call_task(session, KEYS, m.GET_TASK).by == "tester"
        assert wait_for(lambda: ee_speed(kin, states.last()) > 0.05, timeout=30), "the arm did not move"
        moving = driver.execute_script(CANVAS_CHECKSUM)
        assert wait_for(lambda: driver.execute_script(CANVAS_CHECKSUM) != moving, timeout=5)  # the image changes

        # the e-stop: the arm at rest within the safety budget, from when the console sent it (at the speed it had
        # then). The page's own click event, dispatched while the arm moves: WebDriver's native click waits for the
        # busy page (1.4-1.7 s at 0.65 of a core), by when the arm had come to rest (0.004 m/s when the e-stop was
        # sent) and the stop measured nothing. The token test clicks the button as a person does.
        assert wait_for(lambda: ee_speed(kin, states.last()) > 0.05, timeout=30), "the arm is not moving"
        clicked_ns = time.time_ns()
        driver.execute_script("document.getElementById('estop').click()")
        assert wait_for(lambda: len(estops) > 0, timeout=5)
        sent_ns = estops.snapshot()[0].header.stamp_ns
        # from the button's click handler on the page (WebDriver's own dispatch of the click, before it, is the
        # test's machinery) to the e-stop leaving the console
        pressed_ms = page_stats(driver)["sent"][-1]["at"]
        assert -CLOCKS_MS <= sent_ns / 1e6 - pressed_ms < CONSOLE_BUDGET_S * 1e3
        time.sleep(1.0)
        # the speed when the e-stop left, which the bound is made from: on a slowed host the arm moves in bursts
        # (safety holds it while frames come late) and may have been near rest then; the bound still holds it to rest
        v0 = ee_speed(kin, [s for s in states.snapshot() if s.header.stamp_ns <= sent_ns][-1])
        elapsed = time_to_rest(states, kin, sent_ns)
        bound = rest_bound(v0, dsp.emergency_linear_decel_mps2, ESTOP_DELIVERY_BUDGET_S)
        print(f"e-stop from the page at {v0:.3f} m/s: sent {(sent_ns - clicked_ns) / 1e6:.0f} ms after the click "
              f"command ({sent_ns / 1e6 - pressed_ms:.0f} ms after the page's handler), at rest {elapsed * 1e3:.0f} "
              f"ms after (bound {bound * 1e3:.0f} ms)")
        assert elapsed <= bound
        assert wait_for(lambda: estop_engaged(safety), timeout=5)
        # and safety said so within its budget of the press, while the frames flow
        confirmed = next(s for s in safety.snapshot() if s.state is m.SafetyState.ESTOP)
        confirmed_ms = confirmed.header.stamp_ns / 1e6 - pressed_ms
        print(f"safety confirmed the e-stop {confirmed_ms:.0f} ms after the press")
        assert confirmed_ms < SAFETY_CONFIRMS_S * 1e3
        assert wait_for(lambda: text(driver, "estop") == "E-STOP ENGAGED", timeout=5)

        # refused while engaged: a second e-stop, a start; said on the page, nothing moves
        click(driver, "estop")
        assert wait_for(lambda: "already_engaged" in refusals(driver), timeout=5)
        click(driver, "start")
        assert wait_for(lambda: "estop_engaged" in refusals(driver), timeout=5)
        assert "release it before starting" in text(driver, "toast")
        # one request (the console repeats it until safety confirms it: as often as safety takes to)
        assert len(requests(estops)) == 1 and ee_speed(kin, states.last()) < 1e-3

        # release asks first: cancelled, it stays engaged; confirmed, safety releases it
        click(driver, "release")
        assert driver.find_element(By.ID, "confirm-release").get_attribute("open") is not None
        screenshots(driver, artefacts, "release-confirmation")
        driver.set_window_size(*DESKTOP)
        click(driver, "release-cancel")
        time.sleep(0.5)
        assert estop_engaged(safety) and all(not e.reset for e in estops.snapshot())
        click(driver, "release")
        click(driver, "release-confirm")
        assert wait_for(lambda: not estop_engaged(safety), timeout=10)
        # (the release and safety's status reach this process by two subscriptions, in either order)
        assert wait_for(lambda: estops.last().reset, timeout=5) and estops.last().operator == "tester"
        assert wait_for(lambda: "running" in text(driver, "task-state"), timeout=10)
        screenshots(driver, artefacts, "running")  # released, the task goes on
        driver.set_window_size(*DESKTOP)

        click(driver, "stop")
        assert wait_for(lambda: task_state(session) is m.TaskState.IDLE, timeout=15)
        assert wait_for(lambda: "idle" in text(driver, "task-state"), timeout=10)
        screenshots(driver, artefacts, "after")

        # the console restarts on its port: the page left open reconnects and draws again
        port = console.url.rsplit(":", 1)[1].strip("/")
        drawn = page_stats(driver)["frames"]
        console.__exit__(None, None, None)
        with ConsoleProcess(stack.endpoint, "--port", port):
            assert wait_for(lambda: page_stats(driver)["connects"] >= 2, timeout=30)
            wait_for_frames(driver, drawn + 5)
    assert console.process is None


def shows_the_arm_the_robot_declares(driver, arm, states) -> None:
    """The page names the arm the robot declares, draws each of its joints against the ranges of its description
    and in the degrees GetAngularPosition reports (the page's code is the same for every arm: the 6-DoF arm's
    ranges and degrees are the core's, tests/services/console/test_core.py, and the slow test below shows them)."""
    from selenium.webdriver.common.by import By

    assert wait_for(lambda: arm.name in text(driver, "arm"), timeout=15), text(driver, "arm")
    assert "GetAngularPosition" in text(driver, "arm") and arm.title in text(driver, "arm")
    rows = driver.find_elements(By.CSS_SELECTOR, "#joints .joint")
    assert [r.find_element(By.CSS_SELECTOR, ".label").text for r in rows] == list(arm.joint_names)
    shown = driver.execute_script("return window.mfvsConsole.page.status.joints")
    reported = arm.model_to_physical_deg(states.last().q)
    assert [j["deg"] for j in shown] == pytest.approx(list(reported), abs=0.5)
    ranges = [r.find_element(By.CSS_SELECTOR, ".track").get_attribute("title") for r in rows]
    for title, joint in zip(ranges, arm.joints):
        if joint.continuous:
            assert title.startswith("continuous"), title
        else:
            assert title == f"{joint.lower_deg:.0f}° … {joint.upper_deg:.0f}°", title
    # the emulated arm reports its hand: each finger where it is and the target it holds
    assert wait_for(lambda: all(name in text(driver, "fingers") for name in arm.hand.finger_names), timeout=15), \
        text(driver, "fingers")
    assert "units" in text(driver, "fingers") and " A" in text(driver, "fingers")


def test_with_a_token_nothing_is_shown_and_every_action_is_refused_without_it(sim_stack, artefacts):
    stack, session, states, safety, estops = sim_stack
    heard = requests(estops)
    with ConsoleProcess(stack.endpoint, "--token", TOKEN) as console, Browser(*PHONE) as driver:
        driver.get(console.url)
        assert wait_for(lambda: driver.execute_script(
            "return document.getElementById('token-dialog').open"), timeout=15)
        driver.save_screenshot(str(artefacts / "console-token-phone.png"))
        # the page's own controls (each refusal asks for the token again), and requests written by hand with a
        # wrong token: all refused
        for count, button in enumerate(("start", "stop", "estop"), start=1):
            driver.execute_script("document.getElementById('token-dialog').close()")
            click(driver, button)
            assert wait_for(lambda: refusals(driver).count("token") >= count, timeout=10), refusals(driver)
        driver.execute_script("""
            for (const action of ["task_start", "estop_engage", "estop_release"])
              window.mfvsConsole.page.ws.send(JSON.stringify({type: "action", action, operator: "eve",
                                                              confirm: true, token: "guessed token"}));""")
        assert wait_for(lambda: refusals(driver).count("token") >= 6, timeout=10), refusals(driver)
        time.sleep(1.0)
        assert page_stats(driver)["frames"] == 0  # no image without the token
        assert task_state(session) is m.TaskState.IDLE and requests(estops) == heard
        assert not estop_engaged(safety)
        # with it, the page shows the arm
        driver.execute_script("document.getElementById('token-dialog').showModal()")
        from selenium.webdriver.common.by import By

        driver.find_element(By.ID, "token").send_keys(TOKEN)
        click(driver, "token-ok")
        wait_for_frames(driver, 3)


@pytest.mark.slow  # a realtime stack of its own; the same page code is checked on the 7-DoF stack above
def test_a_console_following_a_6_dof_stack_shows_its_six_joints_in_the_degrees_the_arm_reports(artefacts):
    """A stack on the j2n6s300 (the controller and safety take the robot's arm from its states, as the console
    does): the page names the arm, draws its six joints against the ranges of its description, in the degrees
    GetAngularPosition reports, and starts its task."""
    from selenium.webdriver.common.by import By

    six = load_arm("j2n6s300")
    with LocalStack(StackConfig(clock=ClockMode.REALTIME, robot=RobotSimConfig(arm=six.name))) as stack:
        session = open_session(stack.router.client_config())
        states = Recorder(session, KEYS.robot_state, m.RobotState)
        try:
            with ConsoleProcess(stack.endpoint) as console, Browser(*DESKTOP) as driver:
                driver.get(console.url)
                wait_for_frames(driver, 3)
                shows_the_arm_the_robot_declares(driver, six, states)
                ranges = [r.get_attribute("title") for r in driver.find_elements(By.CSS_SELECTOR, "#joints .track")]
                assert ranges[1:3] == ["47° … 313°", "19° … 341°"] and ranges[0].startswith("continuous")
                driver.find_element(By.ID, "operator").send_keys("tester")
                click(driver, "start")
                assert wait_for(lambda: task_state(session) is m.TaskState.RUNNING, timeout=15)
                assert wait_for(lambda: "running" in text(driver, "task-state"), timeout=10)
                screenshots(driver, artefacts, "j2n6s300")
                click(driver, "stop")
                assert wait_for(lambda: task_state(session) is m.TaskState.IDLE, timeout=15)
                assert not [r for r in page_stats(driver)["refusals"]]
        finally:
            states.close()
            session.close()
