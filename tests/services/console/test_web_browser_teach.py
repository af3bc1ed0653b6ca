"""The console's teach in a real browser (headless Chromium), against a realtime stack of its own: in a module of its
own, so that it never shares the host's two cores with test_web_browser.py's shared stack (two realtime stacks and a
browser starved the teach's probe past its minute)."""
import time

import numpy as np

from protocol import messages as m
from protocol.conventions import ClockMode
from services.robot_sim.service import RobotSimConfig
from services.runtime.transport import open_session
from services.stack.local import ConsoleProcess, LocalStack, StackConfig
from tests.services.console.test_web_browser import (DESKTOP, Browser, artefacts, click, screenshots,  # noqa: F401
                                                    task_state, text, wait_for_frames, page_stats)
from tests.stack import KEYS, Recorder, wait_for


def test_the_console_teaches_the_view_in_the_box_drawn_on_it_and_servos_to_it(artefacts, tmp_path):
    """A markerless object before the arm (a textured box face at Table 2's goal, realtime, every service a
    process): a box dragged on the page's image, the teach confirmed, the arm's probe and return, the goal kept in
    the goals folder and vision on the keypoint front end; the task then starts on it."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    from services.robot_sim.scene import SceneConfig, TargetConfig, TargetKind
    from services.vision.taught import read_goal
    from bench.markerless_rig import GOAL_IN_CAMERA

    scene = SceneConfig(target=TargetConfig(kind=TargetKind.PLANE, pose_in_camera=GOAL_IN_CAMERA))
    features = []
    with LocalStack(StackConfig(clock=ClockMode.REALTIME, robot=RobotSimConfig(scene=scene))) as stack:
        session = open_session(stack.router.client_config())
        seen = Recorder(session, KEYS.features, m.Features)
        try:
            with ConsoleProcess(stack.endpoint, "--goals-dir", str(tmp_path)) as console, \
                    Browser(*DESKTOP) as driver:
                driver.get(console.url)
                wait_for_frames(driver, 3)
                driver.find_element(By.ID, "operator").send_keys("tester")
                driver.find_element(By.ID, "goal-name").send_keys("box")
                canvas = driver.find_element(By.ID, "camera")
                driver.execute_script("arguments[0].scrollIntoView({block: 'center'})", canvas)
                width = canvas.size["width"]
                scale = width / 640.0  # the box in the image's pixels: 130..510 × 90..390, as drawn on the page
                (ActionChains(driver).move_to_element_with_offset(canvas, int((130 - 320) * scale), int((90 - 240) * scale))
                 .click_and_hold().move_by_offset(int(380 * scale), int(300 * scale)).release().perform())
                assert "box will be taught" in text(driver, "teach-state")
                click(driver, "teach")
                click(driver, "teach-confirm")
                assert wait_for(lambda: list(tmp_path.glob("box.mfvsgoal")), timeout=60), page_stats(driver)
                goal, _ = read_goal(tmp_path / "box.mfvsgoal")
                region = np.asarray(goal.file.region_px)
                assert np.allclose(region.min(axis=0), [130, 90], atol=6) and np.allclose(region.max(axis=0),
                                                                                          [510, 390], atol=6)
                assert goal.file.planar and len(goal.points_camera) >= 100
                assert wait_for(lambda: "taught box" in text(driver, "teach-state"), timeout=10)
                assert wait_for(lambda: any(f.front_end is m.FrontEnd.KEYPOINTS and f.status in
                                            m.USABLE_FEATURE_STATUSES for f in seen.snapshot()[-5:]), timeout=10)
                screenshots(driver, artefacts, "taught")
                click(driver, "start")
                assert wait_for(lambda: task_state(session) is m.TaskState.RUNNING, timeout=15)
                features = seen.snapshot()[-10:]
                time.sleep(1.0)
                screenshots(driver, artefacts, "servoing-to-a-taught-view")
                click(driver, "stop")
                assert wait_for(lambda: task_state(session) is m.TaskState.IDLE, timeout=15)
        finally:
            seen.close()
            session.close()
    assert all(f.keypoints.goal == "box" for f in features if f.keypoints is not None)
