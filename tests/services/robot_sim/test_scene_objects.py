"""The scene's typed objects: a markerless target (a textured plane, a cup), other objects on a schedule, the light;
a scene that asks for nothing new compiles to the very model it did."""
import hashlib

import cv2
import mujoco
import numpy as np
import pytest

from services.model.arm import load_arm
from services.model.frames import PoseConfig
from services.robot_sim import scene as scene_mod
from services.robot_sim.scene import LightConfig, SceneConfig, SceneObject, TargetConfig, TargetKind
from services.robot_sim.sim import OUT_OF_SCENE, Simulation
from services.robot_sim.textures import load_texture, procedural_texture, texture_image

ARM = load_arm("j2s7s300")
AHEAD = PoseConfig(xyz=(0.0, 0.0, 0.2888), rpy_deg=(180.0, 0.0, 0.0))


def model_bytes(model: mujoco.MjModel) -> bytes:
    buffer = np.zeros(mujoco.mj_sizeModel(model), np.uint8)
    mujoco.mj_saveModel(model, None, buffer)
    return buffer.tobytes()


def test_a_scene_that_asks_for_nothing_new_compiles_to_the_same_model():
    plain = model_bytes(scene_mod.build_model(SceneConfig(), ARM))
    spelled = model_bytes(scene_mod.build_model(SceneConfig(objects=[], light=LightConfig(), target=TargetConfig(
        kind=TargetKind.TAG)), ARM))
    assert plain == spelled
    # an object added leaves the arm and the target numbered as they were (bodies, joints, actuators, the camera)
    more = scene_mod.build_model(SceneConfig(objects=[SceneObject(name="clutter", pose_in_camera=AHEAD)]), ARM)
    base = scene_mod.build_model(SceneConfig(), ARM)
    for kind in (mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_JOINT, mujoco.mjtObj.mjOBJ_ACTUATOR):
        names = [mujoco.mj_id2name(base, kind, i) for i in range({mujoco.mjtObj.mjOBJ_BODY: base.nbody,
                                                                   mujoco.mjtObj.mjOBJ_JOINT: base.njnt,
                                                                   mujoco.mjtObj.mjOBJ_ACTUATOR: base.nu}[kind])]
        assert all(mujoco.mj_name2id(more, kind, n) == i for i, n in enumerate(names))
    # objects without a mass are mocap bodies: no degrees of freedom beside the arm's joints and the fingers' hinges
    assert more.nv == base.nv == ARM.n_joints + ARM.hand.n_fingers
    # and the contact options a grasp needs are the free objects' alone
    assert base.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL and base.opt.impratio == 1.0


def cup_on_the_table(name="cup", xy=(0.5, 0.1), mass_kg=0.35, friction=1.0) -> SceneObject:
    height, top = scene_mod.CupShape().height_m, scene_mod.TableConfig().top_z_m
    return SceneObject(name=name, kind="cup", mass_kg=mass_kg, friction=friction,
                       pose_in_base=PoseConfig(xyz=(*xy, top + height / 2 + 0.002), rpy_deg=(90.0, 0.0, 0.0)))


def test_a_free_object_falls_onto_the_table_and_rests_there_and_off_it_lands_on_the_floor():
    table = scene_mod.TableConfig()
    off_the_table = (table.centre_xy_m[0] - table.size_xy_m[0] / 2 - 0.2, 0.0)
    scene = SceneConfig(table=table, objects=[cup_on_the_table(), cup_on_the_table("falling", off_the_table)])
    sim = Simulation(scene, arm=ARM, render=False)
    assert sim.model.nv == ARM.n_joints + ARM.hand.n_fingers + 2 * 6  # a free joint each, after the fingers
    assert sim.model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC and sim.model.opt.impratio == scene_mod.IMPRATIO
    for _ in range(250):  # 0.5 s
        sim.cycle()
    cup = sim.object_pose("cup")
    assert cup[2, 3] == pytest.approx(table.top_z_m + scene_mod.CupShape().height_m / 2, abs=1e-3)  # on it, upright
    assert cup[:3, 1] @ [0.0, 0.0, 1.0] > 0.999
    assert np.linalg.norm(cup[:2, 3] - [0.5, 0.1]) < 1e-3
    assert sim.object_pose("falling")[2, 3] < scene.floor_z_m + 0.1  # past the table's edge: down on the floor
    assert scene.floor_z_m == pytest.approx(table.top_z_m - table.height_m)


def test_a_free_objects_mass_is_its_shapes_alone_and_its_friction_is_what_its_contacts_use():
    sim = Simulation(SceneConfig(table=scene_mod.TableConfig(), objects=[cup_on_the_table(mass_kg=0.35, friction=0.2)]),
                     arm=ARM, render=False)
    body = sim.model.body("object_cup")
    assert body.mass[0] == pytest.approx(0.35)  # the print and the handle weigh nothing
    shape = sim.model.geom("object_cup_shape")
    assert shape.friction[0] == pytest.approx(0.2) and shape.priority[0] > sim.model.geom("table").priority[0]


def test_free_objects_are_refused_what_only_a_mocap_body_can_do():
    with pytest.raises(ValueError, match="moves only as it is pushed"):
        SceneObject(name="cup", mass_kg=0.3, velocity_mps=(0.1, 0.0, 0.0), pose_in_camera=AHEAD)
    with pytest.raises(ValueError, match="mass_kg within"):
        SceneObject(name="cup", mass_kg=float("nan"), pose_in_camera=AHEAD)
    with pytest.raises(ValueError, match="friction within"):
        SceneObject(name="cup", mass_kg=0.3, friction=0.0, pose_in_camera=AHEAD)
    with pytest.raises(ValueError, match="named twice"):
        SceneConfig(objects=[cup_on_the_table(), cup_on_the_table()]).check(ARM)


def test_the_procedural_print_is_the_same_from_the_same_seed_and_rich_in_keypoints():
    a, b, c = procedural_texture(7), procedural_texture(7), procedural_texture(8)
    assert hashlib.sha256(a).digest() == hashlib.sha256(b).digest() and not np.array_equal(a, c)
    keypoints = cv2.SIFT_create().detect(cv2.cvtColor(a, cv2.COLOR_RGB2GRAY))
    assert len(keypoints) > 300
    assert texture_image(None, 7, aspect=2.5).shape == (410, 1024, 3)  # a wall's shape kept, within the bound


def test_a_photograph_texture_is_read_and_a_bad_one_is_refused_naming_it(tmp_path):
    photo = tmp_path / "photo.jpg"
    cv2.imwrite(str(photo), np.full((2000, 3000, 3), 120, np.uint8))
    assert load_texture(photo).shape == (683, 1024, 3)  # scaled to its longer side's bound
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image")
    with pytest.raises(ValueError, match="junk.png: not an image"):
        load_texture(junk)
    with pytest.raises(ValueError, match="no such file"):
        load_texture(tmp_path / "missing.png")
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(ValueError, match="at least 64"):
        load_texture(small)


@pytest.mark.parametrize("kind", [TargetKind.PLANE, TargetKind.CUP])
def test_a_markerless_target_is_rendered_printed_where_the_scene_puts_it(kind):
    sim = Simulation(SceneConfig(target=TargetConfig(kind=kind, pose_in_camera=AHEAD)), arm=ARM)
    try:
        image = cv2.cvtColor(sim.render(), cv2.COLOR_RGB2GRAY)
    finally:
        sim.close()
    camera = sim.scene.camera
    outline = scene_mod.target_outline(sim.scene.target)
    T = AHEAD.matrix()
    P = outline @ T[:3, :3].T + T[:3, 3]
    px = np.column_stack([camera.fx * P[:, 0] / P[:, 2] + 319.5, camera.fy * P[:, 1] / P[:, 2] + 239.5])
    lo, hi = np.floor(px.min(axis=0)).astype(int), np.ceil(px.max(axis=0)).astype(int)
    inside = image[lo[1] + 10:hi[1] - 10, lo[0] + 10:hi[0] - 10]
    assert inside.std() > 20  # printed, not flat grey
    assert image[5:40, 5:40].std() < 3  # the floor's plain grey around it
    assert len(cv2.SIFT_create().detect(inside)) >= 60  # enough to teach it (services/vision/teach.py: 60)


def test_objects_arrive_move_and_leave_on_their_schedule_and_the_target_can_leave():
    scene = SceneConfig(target=TargetConfig(kind=TargetKind.PLANE, pose_in_camera=AHEAD, leaves_at_s=0.05),
                        objects=[SceneObject(name="swap", pose_in_camera=AHEAD, arrives_at_s=0.05),
                                 SceneObject(name="hand", kind="box", size_m=(0.05, 0.3, 0.02),
                                             pose_in_camera=PoseConfig(xyz=(-0.2, 0.0, 0.2), rpy_deg=(180, 0, 0)),
                                             velocity_mps=(0.0, 1.0, 0.0))],
                        floor=False)
    sim = Simulation(scene, arm=ARM, render=False)
    mocap = {name: sim.model.body(name).mocapid[0] for name in ("target", "object_swap", "object_hand")}
    start_target, start_hand = sim.data.mocap_pos[mocap["target"]].copy(), sim.data.mocap_pos[mocap["object_hand"]].copy()
    assert np.array_equal(sim.data.mocap_pos[mocap["object_swap"]], OUT_OF_SCENE)
    for _ in range(30):  # 60 ms
        sim.cycle()
    assert np.array_equal(sim.data.mocap_pos[mocap["target"]], OUT_OF_SCENE)
    assert np.linalg.norm(sim.data.mocap_pos[mocap["object_swap"]] - start_target) < 1e-9
    assert np.allclose(sim.data.mocap_pos[mocap["object_hand"]] - start_hand, [0.0, 0.06, 0.0], atol=1e-9)
    sim.reset()
    assert np.array_equal(sim.data.mocap_pos[mocap["target"]], start_target)


def test_the_light_changes_the_image_and_a_bad_one_is_refused():
    images = []
    for light in (LightConfig(), LightConfig(intensity=1.5, direction=(0.5, 0.2, -1.0))):
        sim = Simulation(SceneConfig(target=TargetConfig(kind=TargetKind.PLANE, pose_in_camera=AHEAD), light=light),
                         arm=ARM)
        try:
            images.append(sim.render().astype(float))
        finally:
            sim.close()
    assert images[1].mean() > images[0].mean() + 5
    with pytest.raises(ValueError, match="intensity"):
        LightConfig(intensity=-1.0)
    with pytest.raises(ValueError, match="exactly one"):
        SceneObject(name="x")


@pytest.mark.parametrize("kind", [TargetKind.PLANE, TargetKind.CUP])
def test_a_markerless_target_is_blurred_by_its_motion_through_the_webcam(kind):
    """The webcam's motion blur follows the target's face (a plane's, a cup's box across its axis), as a tag's."""
    from services.robot_sim.camera import FrameRenderer
    from services.robot_sim.imaging import ImagingConfig, target_corners_px

    scene = SceneConfig(target=TargetConfig(kind=kind, pose_in_camera=AHEAD))
    sim = Simulation(scene, arm=ARM, render=False)
    renderer = FrameRenderer(sim.model, sim.camera_id, 640, 480, imaging=ImagingConfig(),
                             camera_matrix=scene.camera.matrix())
    try:
        end = (sim.data.qpos.copy(), sim.data.mocap_pos.copy(), sim.data.mocap_quat.copy())
        moved = sim.data.mocap_pos.copy()
        moved[0] += np.array([0.01, 0.0, 0.0])
        start = (end[0], moved, end[2])
        corners = target_corners_px(sim.model, sim.data, sim.camera_id, scene.camera.matrix())
        assert corners.shape == (4, 2) and np.ptp(corners[:, 0]) > 100  # the face, not a point
        sharp = renderer.render(*end, stamp_ns=1).astype(float)
        blurred = renderer.render(*end, start=start, stamp_ns=1).astype(float)
        assert np.abs(blurred - sharp).mean() > 1.0
    finally:
        renderer.close()
        sim.close()


def test_a_target_stuck_on_a_free_object_goes_where_the_object_goes():
    radius = scene_mod.CupShape().radius_m
    card = PoseConfig(xyz=(0.0, 0.0, radius + 0.001), rpy_deg=(0.0, 0.0, 0.0))
    scene = SceneConfig(table=scene_mod.TableConfig(), objects=[cup_on_the_table()],
                        target=TargetConfig(size_m=0.03, on_object="cup", pose_in_object=card))
    sim = Simulation(scene, arm=ARM, render=False)
    assert np.allclose(sim.target_pose(), sim.object_pose("cup") @ card.matrix())
    for _ in range(100):  # it falls the 2 mm it stood above the table; the card with it
        sim.cycle()
    assert np.allclose(sim.target_pose(), sim.object_pose("cup") @ card.matrix(), atol=1e-9)
    with pytest.raises(ValueError, match="goes where the object goes"):
        sim.set_target_pose(np.eye(4))
    with pytest.raises(ValueError, match="not a free object"):
        SceneConfig(objects=[SceneObject(name="cup", pose_in_camera=AHEAD)],
                    target=TargetConfig(on_object="cup", pose_in_object=card)).check(ARM)
    with pytest.raises(ValueError, match="needs both"):
        TargetConfig(on_object="cup")
