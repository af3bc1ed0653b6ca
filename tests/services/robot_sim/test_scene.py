"""The simulated scene: MuJoCo rendering (EGL) of the AprilTag seen by the eye-in-hand camera."""
import cv2
import numpy as np
import pytest

from services.model import tag as tags
from services.robot_sim.service import RobotSimConfig
from services.robot_sim.scene import CameraConfig, PoseConfig, SceneConfig, TargetConfig, build_model
from services.robot_sim.sim import Simulation
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")


def detect(image, family="tag36h11"):
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(tags.dictionary(family), params)
    corners, ids, _ = detector.detectMarkers(image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
    return corners, ids


def projected_corners(sim, cfg):
    T_cb = np.linalg.inv(sim.camera_pose())
    T_ct = T_cb @ sim.target_pose()
    corners = (T_ct[:3, :3] @ tags.corners_in_tag(cfg.target.size_m).T).T + T_ct[:3, 3]
    K = cfg.camera.matrix()
    uv = (K @ (corners / corners[:, 2:3]).T).T
    return uv[:, :2]


CASES = [
    # (camera, target pose in the camera frame)
    (CameraConfig(), PoseConfig(xyz=(0.0, 0.0, 0.5), rpy_deg=(180.0, 0.0, 0.0))),
    (CameraConfig(), PoseConfig(xyz=(0.05, -0.03, 0.35), rpy_deg=(160.0, 15.0, 30.0))),
    (CameraConfig(), PoseConfig(xyz=(-0.08, 0.06, 0.65), rpy_deg=(200.0, -20.0, -60.0))),
    (CameraConfig(width=1280, height=720, fx=920.0, fy=925.0, cx=650.0, cy=350.0),
     PoseConfig(xyz=(0.02, 0.01, 0.6), rpy_deg=(170.0, 10.0, 100.0))),
]


@pytest.mark.parametrize("layout", list(tags.TagLayout))
@pytest.mark.parametrize("camera, pose", CASES)
def test_rendered_tag_is_detected_at_its_pinhole_projection(camera, pose, layout):
    """Each corner where the pinhole model puts it, in the tag's order: OpenCV's own for its drawing, turned back
    to the official image's for the official one."""
    cfg = SceneConfig(camera=camera, target=TargetConfig(id=3, pose_in_camera=pose, layout=layout))
    sim = Simulation(cfg)
    try:
        image = sim.render()
    finally:
        sim.close()
    assert image.shape == (camera.height, camera.width, 3) and image.dtype == np.uint8
    corners, ids = detect(image)
    assert ids is not None and ids.ravel().tolist() == [3]
    expected = projected_corners(sim, cfg)
    found = corners[0][0] if layout is tags.TagLayout.OPENCV else tags.official_order(corners[0][0])
    error = np.linalg.norm(found - expected, axis=1)
    assert error.max() < 1.0, error


def test_target_pose_in_camera_resolves_at_the_initial_configuration():
    pose = PoseConfig(xyz=(0.01, 0.02, 0.4), rpy_deg=(180.0, 0.0, 10.0))
    cfg = SceneConfig(target=TargetConfig(pose_in_camera=pose))
    sim = Simulation(cfg, render=False)
    T_ct = np.linalg.inv(sim.camera_pose()) @ sim.target_pose()
    assert np.allclose(T_ct, pose.matrix(), atol=1e-9)


def test_camera_is_mounted_as_configured():
    cfg = SceneConfig()
    sim = Simulation(cfg, render=False)
    T_ec = np.linalg.inv(sim.ee_pose()) @ sim.camera_pose()
    assert np.allclose(T_ec, cfg.camera.camera_in_ee.matrix(), atol=1e-9)
    # the default mount looks along the approach axis with the image upright at home
    R_bc = sim.camera_pose()[:3, :3]
    assert abs(R_bc[2, 0]) < 1e-6 and R_bc[2, 1] < -0.5


def test_moving_target_moves_at_its_velocity():
    cfg = SceneConfig(target=TargetConfig(velocity_mps=(0.02, 0.0, -0.01)))
    sim = Simulation(cfg, render=False)
    p0 = sim.target_pose()[:3, 3]
    for _ in range(500):  # 1 s of 2 ms bus cycles
        sim.cycle()
    assert sim.target_pose()[:3, 3] - p0 == pytest.approx([0.02, 0.0, -0.01], abs=1e-9)


def test_torque_limits_are_the_actuators():
    model = build_model(SceneConfig(), ARM)
    assert model.actuator_ctrlrange[: ARM.n_joints, 1].tolist() == ARM.max_torque.tolist()  # (the fingers follow)
    assert model.opt.timestep <= 0.001


def test_scene_config_validation():
    with pytest.raises(ValueError, match="initial_joints_deg has 6 angles; the j2s7s300 has 7 joints"):
        SceneConfig(initial_joints_deg=[0.0] * 6).check(ARM)
    with pytest.raises(ValueError, match="outside the j2s7s300's joint limits"):
        SceneConfig(initial_joints_deg=[0, 20, 0, 180, 0, 180, 0]).check(ARM)  # joint 2 below 47°
    SceneConfig(initial_joints_deg=[0.0] * 6, floor=False)  # a scene alone does not know its arm ...
    with pytest.raises(ValueError, match="scene.initial_joints_deg has 6 angles; the j2s7s300 has 7 joints"):
        RobotSimConfig(scene=SceneConfig(initial_joints_deg=[0.0] * 6))  # ... the robot's config does
    with pytest.raises(ValueError):
        TargetConfig(pose_in_base=PoseConfig(), pose_in_camera=PoseConfig())
    with pytest.raises(ValueError):
        CameraConfig(fx=-1.0)
    with pytest.raises(ValueError):
        SceneConfig(timestep_s=0.01)


@pytest.mark.parametrize("name", ["j2s7s300", "j2n6s300"])
def test_the_emulated_arm_is_its_description_heavier_where_its_emulation_says_and_with_friction(name, rng):
    """The simulated arm's gravity is Pinocchio's of the description with the links scaled as the description's
    emulation section says (the model the controllers use is wrong by exactly that, on purpose), the last link's
    mass split between the palm and the fingers (open), where the description has them; its joints carry
    a fraction of the actuators' smallest backdriving torque as Coulomb friction (which the firmware applies in
    torque mode only: test_firmware.py), and its motors their peak torques."""
    import mujoco
    import pinocchio as pin

    from services.model.arm import load_arm
    from services.model.kinematics import ArmKinematics

    arm = load_arm(name)
    sim = Simulation(render=False, arm=arm)
    true_model = arm.load_pinocchio().model.copy()
    for i, scale in enumerate(arm.true_link_mass_scale, start=1):
        true_model.inertias[i] = pin.Inertia(true_model.inertias[i].mass * scale, true_model.inertias[i].lever,
                                             true_model.inertias[i].inertia * scale)
    # the last link: the palm as the truth weighs it, and the fingers (open) where the description has them
    hand = arm.hand
    palm_mass = arm.joints[-1].link_mass_kg * arm.true_link_mass_scale[-1] - hand.n_fingers * hand.finger_mass_kg
    mass, centre, inertia = arm.palm_inertia(palm_mass)
    last = pin.Inertia(mass, centre, inertia)
    for finger_mass, at in arm.finger_masses_in_last_link():  # point masses: gravity needs no more
        last = last + pin.Inertia(finger_mass, at, np.zeros((3, 3)))
    true_model.inertias[arm.n_joints] = last
    true_data, nominal = true_model.createData(), ArmKinematics(arm)
    n = arm.n_joints
    differs = False
    for _ in range(20):
        q = random_q_for(arm, rng)
        sim.data.qpos[:n] = q
        sim.data.qvel[:] = 0
        mujoco.mj_forward(sim.model, sim.data)
        assert np.allclose(sim.data.qfrc_bias[:n], pin.computeGeneralizedGravity(true_model, true_data, q), atol=1e-6)
        differs |= not np.allclose(sim.data.qfrc_bias[:n], nominal.gravity(q), atol=1e-3)
    assert differs  # the hand's extra mass shows in gravity
    assert sim.model.dof_frictionloss[:n].tolist() == pytest.approx(
        [arm.torque_mode_friction_fraction * j.spec.backdriving_torque_nm[0] for j in arm.joints])
    assert 0.0 < arm.torque_mode_friction_fraction < 1.0
    assert sim.model.actuator_ctrlrange[:n, 1].tolist() == [j.spec.peak_torque_nm for j in arm.joints]


def random_q_for(arm, rng):
    lower, upper = arm.model_limits()
    q = rng.uniform(-np.pi, np.pi, arm.n_joints)
    limited = np.isfinite(lower)
    q[limited] = rng.uniform(lower[limited] + 0.05, upper[limited] - 0.05)
    return q


def test_target_below_the_floor_is_refused():
    cfg = SceneConfig(target=TargetConfig(pose_in_base=PoseConfig(xyz=(0.0, -0.6, -0.1))))
    with pytest.raises(ValueError, match="below the floor"):
        build_model(cfg, ARM)


@pytest.mark.parametrize("encoding", ["rgb8", "mono8"])
def test_camera_renders_in_its_own_process_the_frame_the_simulation_would(encoding):
    """MuJoCo's renderer holds the interpreter lock for a whole frame (3-5 ms): in robot_sim's process it stalled
    the emulated actuators' 2 ms loop every frame. The camera renders in a child process, bit for bit the image the
    simulation renders itself (grey: as vision converts it), and the process ends with the camera."""
    import os

    from protocol.messages import CHANNELS, Header, ImageEncoding
    from services.robot_sim.camera import SimCamera

    cfg = SceneConfig(camera=CameraConfig(encoding=ImageEncoding(encoding)),
                      target=TargetConfig(pose_in_camera=PoseConfig(xyz=(0.02, -0.01, 0.4), rpy_deg=(170, 5, 20))))
    sim = Simulation(cfg)
    images, failures = [], []
    camera = SimCamera(sim, images.append, lambda *_, **kw: Header(**kw), lambda: failures.append(1))
    camera.start()
    try:
        pid = camera.renderer_pid
        assert pid is not None and pid != os.getpid()
        sim.data.qpos[:] += 0.01  # a state of its own, not the initial one
        done = camera.capture(stamp_ns=123)
        assert done is not None and done.wait(30.0)
        assert not failures and len(images) == 1
        image = images[0]
        assert image.header.source_stamp_ns == 123
        assert image.encoding is ImageEncoding(encoding)
        pixels = np.frombuffer(image.data, dtype=np.uint8).reshape(image.height, image.width, -1).squeeze()
        assert pixels.size == image.height * image.width * CHANNELS[image.encoding]
        expected = sim.render()
        if image.encoding is ImageEncoding.MONO8:
            expected = cv2.cvtColor(expected, cv2.COLOR_RGB2GRAY)
        assert np.array_equal(pixels, expected)
        assert detect(pixels)[1] is not None  # the tag is in the frame: the comparison is not of two blank images
    finally:
        camera.stop()
        sim.close()
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_the_realtime_camera_starts_one_process_its_renderer_and_no_other():
    """The render process is a plain subprocess: multiprocessing's spawn also started a resource tracker (a third
    interpreter, 13 MB resident) for shared memory nobody used."""
    import json
    import re
    import subprocess
    import sys
    from services.paths import REPO

    script = (
        "import glob, json, os\n"
        "from protocol.messages import Header\n"
        "from services.robot_sim.camera import SimCamera\n"
        "from services.robot_sim.sim import Simulation\n"
        "sim = Simulation()\n"
        "camera = SimCamera(sim, lambda image: None, lambda *_, **kw: Header(**kw), lambda: None)\n"
        "camera.start()\n"
        "children = {c for f in glob.glob(f'/proc/{os.getpid()}/task/*/children') for c in open(f).read().split()}\n"
        "print(json.dumps([open(f'/proc/{c}/cmdline').read().replace(chr(0), ' ').strip() for c in children]))\n"
        "camera.stop()\n"
        "sim.close()\n")
    out = subprocess.run([sys.executable, "-c", script], cwd=REPO, text=True,
                         capture_output=True, timeout=120, check=True).stdout
    children = json.loads(out.strip().splitlines()[-1])
    assert len(children) == 1 and re.fullmatch(r".* -m services\.robot_sim\.render_server \d+", children[0]), children


@pytest.mark.parametrize("encoding", ["rgb8", "mono8"])
def test_in_lockstep_the_loop_renders_the_frame_the_render_process_would(encoding):
    """Lockstep's loop waits for each frame's answer anyway: it renders the frame itself (no render process, no
    thread, no pipe), the same pixels as the render process, in the thread that delivers it, which also frees the
    renderer (its GL context is that thread's)."""
    import multiprocessing
    import threading

    from protocol.messages import Header, ImageEncoding
    from services.robot_sim.camera import LoopCamera, SimCamera

    cfg = SceneConfig(camera=CameraConfig(encoding=ImageEncoding(encoding)),
                      target=TargetConfig(pose_in_camera=PoseConfig(xyz=(0.02, -0.01, 0.4), rpy_deg=(170, 5, 20))))
    sim = Simulation(cfg)
    sim.data.qpos[:] += 0.01
    header = lambda *_, **kw: Header(**kw)  # noqa: E731
    in_process, in_loop, failures = [], [], []
    reference = SimCamera(sim, in_process.append, header, lambda: failures.append("process"))
    reference.start()
    try:
        done = reference.capture(stamp_ns=7)
        reference.deliver(done, timeout_s=30.0)
    finally:
        reference.stop()
    camera = LoopCamera(sim, in_loop.append, header, lambda: failures.append("loop"))
    camera.start()
    rendering_threads = []

    def loop():  # as robot_sim's loop: capture at the boundary, deliver at the tick, free the renderer at its end
        frame = camera.capture(stamp_ns=7)
        sim.data.qpos[:] += 0.05  # physics moves on after the boundary: the frame is the snapshot's
        camera.deliver(frame, timeout_s=0.0)
        rendering_threads.append(threading.current_thread().name)
        camera.close_renderer()

    thread = threading.Thread(target=loop, name="robot-loop")
    thread.start()
    thread.join()
    camera.stop()
    sim.close()
    assert not failures and len(in_process) == len(in_loop) == 1
    assert camera.renderer_pid is None and not multiprocessing.active_children()
    assert in_loop[0].data == in_process[0].data and in_loop[0].header.source_stamp_ns == 7
    assert camera.last_image is in_loop[0] and rendering_threads == ["robot-loop"]


def test_the_renderer_holds_no_shadow_map_and_a_scene_buffer_its_size_for_the_same_pixels():
    """No light casts shadows: MuJoCo's default 4096² shadow map (64 MB in every GL context) and its 10,000-geom
    scene buffer (9 MB) bought nothing. The frames are the ones the defaults gave."""
    import mujoco

    from services.robot_sim import scene as scene_mod

    sim = Simulation(SceneConfig())
    sim.data.qpos[:] += 0.02
    mujoco.mj_forward(sim.model, sim.data)
    assert sim.model.vis.quality.shadowsize == 0
    height, width = sim.scene.camera.height, sim.scene.camera.width
    frames = []
    for shadowsize, make in ((0, scene_mod.renderer), (4096, mujoco.Renderer)):
        sim.model.vis.quality.shadowsize = shadowsize
        renderer = make(sim.model, height, width)
        try:
            renderer.update_scene(sim.data, camera=sim.camera_id)
            frames.append(renderer.render().copy())
            if make is scene_mod.renderer:
                assert renderer.scene.maxgeom < 1000 and renderer.scene.ngeom <= renderer.scene.maxgeom
        finally:
            renderer.close()
    sim.model.vis.quality.shadowsize = 0
    sim.close()
    assert frames[0].any() and np.array_equal(frames[0], frames[1])


def test_a_link_the_emulation_makes_heavier_has_its_inertia_scaled_with_its_mass():
    """(arm.true_link_mass_scale: the URDF gives MuJoCo each link's full inertia, which is what must be scaled.)"""
    import dataclasses

    from services.model.arm import load_arm

    arm = load_arm("j2s7s300")
    scale = np.ones(arm.n_joints)
    scale[2] = 1.5
    heavier = dataclasses.replace(arm, hand=None, true_link_mass_scale=scale)
    bare = arm.load_mujoco()
    model = build_model(SceneConfig(), heavier)
    assert model.body("link_3").mass[0] == pytest.approx(1.5 * bare.body("link_3").mass[0])
    assert model.body("link_3").inertia == pytest.approx(1.5 * bare.body("link_3").inertia)
    assert model.body("link_2").inertia == pytest.approx(bare.body("link_2").inertia)
