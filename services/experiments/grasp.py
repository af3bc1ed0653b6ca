"""``mfvs experiment grasp``: reach, grasp and lift an object standing on the table, from placements nobody tuned.

Each placement (seeded) puts the object on the table in front of the arm, turned within ±15° from facing where the
hand comes from, with a tag card stuck on that side (a 3 cm AprilTag: today's pre-grasp view is taught with a tag; the
markerless one is the next step). The arm starts at its ready pose, which is the pre-grasp view of the middle of the
table's placements. The grasp task (``mfvs task start --grasp``) then runs through the real services, composed, in
lockstep: the visual servo to the pre-grasp view (the taught view: the camera where it is when the hand, ``approach_m``
back along its tool's axis from holding the object, looks at the card), the approach, the fingers closed until the
grasp detector says the hand holds it, the lift, the hold. After ``HOLD_S`` of hold the run stops the task (the
fingers keep their targets: a task that ends never opens the hand) and shakes the object: ±3 cm sideways and back,
two move tasks. With ``--perturb estop``, an emergency stop comes 1 s into the hold and the run measures whether the
object dropped.

Each run's figures are MuJoCo's (robot_sim's ``sim/objects``: the object's pose at every DSP tick): ``lifted_m`` (the
object above where it stood), ``held_s``, ``slip_mm`` (how far it moved in the hand over the hold and the shake),
``dropped`` (back on the table or the floor), and the detector's verdict with its time after the first contact.

The hand grasps from the side, the approach axis horizontal: the KG-3's palm is narrower than a mug (its hinges are
3 cm from its axis), so from above its fingers close on the rim (measured: tests/services/robot_sim/
test_sim_grasp.py). The camera is mounted as the seeds' is (on top of the hand, 6.5 cm off the approach axis),
turned toward the axis so that it looks at the object at the pre-grasp view (:func:`grasp_camera`): looking along the
axis, the card of an object ``approach_m`` ahead lay at the image's edge.
"""
from __future__ import annotations

import json
import math
import random
import threading
import time
from pathlib import Path
from typing import Optional

import msgspec
import numpy as np

from protocol import messages as m
from protocol.keys import Keys
from services.controller.phases import GraspConfig
from services.controller.task_client import call_task
from services.experiments.markerless import wilson_interval
from services.experiments.pool import RunTask, run_tasks
from services.experiments.report import write_results
from services.model import frames
from services.model.arm import load_arm
from services.model.frames import PoseConfig
from services.model.kinematics import ArmKinematics, inverse_kinematics
from services.robot_sim.scene import CameraConfig, CupShape, SceneObject, TableConfig, TargetConfig
from services.servo.scenario import Scenario, stack_config
from services.vision.service import GoalConfig

OBJECTS = ("cup", "box", "slippery", "none")
#: what may happen during the hold: an emergency stop. (A killed controller or a stale command are not here yet: in
#: lockstep the arm waits up to 2 s for each frame's answer from a controller that is gone, 60 times slower than the
#: frames; the lockstep gate would have to know which services a frame's answer needs.)
PERTURBATIONS = ("estop",)

#: the tag card: a 3 cm tag (our choice: it fits a mug's wall and a carton's face), 1 mm off the object's face
CARD_TAG_M = 0.03
CARD_OFFSET_M = 0.001
#: the objects (each in its frame: y up, z toward the arm): a mug without a handle (the emulated handle touches
#: nothing), 0.35 kg (the issue's); a carton 6 × 10 × 6 cm, 0.3 kg; the same carton wet (friction 0.1: its 25 N grip
#: holds it on the table, and 0.1 × 25 N is less than its weight: it slips out when lifted)
CUP = CupShape(radius_m=0.04, height_m=0.095, handle=False)
CUP_KG, BOX_KG = 0.35, 0.3
BOX_M = (0.06, 0.10, 0.06)
DRY_FRICTION, WET_FRICTION = 1.0, 0.1
#: the hand holds the object this far ahead of the end effector's origin along its approach axis (m): its axis in
#: front of the palm's face, where the fingers' distal links close across it (tests/services/robot_sim/
#: test_sim_grasp.py measures the grasp there)
HOLD_AHEAD_M = 0.03
#: the placements: the object's centre within this box on the table (base frame, m), turned within this (deg) from
#: facing where the hand comes from (:data:`FACING_DEG`); our choice: in front of the arm, where both arms reach
#: from the side, and all of it in the camera's view from the ready pose (the pre-grasp view of its middle)
PLACE_X_M, PLACE_Y_M, PLACE_TURN_DEG = (0.52, 0.62), (-0.15, -0.05), 15.0
#: where the hand comes from: the card faces this far to the right of the way toward the arm's base (deg; our choice:
#: the hand reaches the object from its side, elbow out, which both arms reach with their joints 40° and more from
#: their limits at the grasp and at the pre-grasp view; straight from the base, the pre-grasp view 0.2 m back has the
#: wrist folded against the shoulder, out of the arms' reach)
FACING_DEG = -60.0
#: the camera's mount: the seeds' place on the hand (6.5 cm off the axis, 2 cm behind the end effector), upright for
#: the side grasp (the image's x across the approach, its y down) and turned toward the approach axis so that the card
#: is in the middle of the image at the pre-grasp view (:func:`grasp_camera`)
CAMERA_IN_EE_XYZ = (0.065, 0.0, -0.02)
#: the hold before the shake (s; the issue's 5 s), the shake (m, each way), and when a perturbation comes (s into
#: the hold)
HOLD_S = 5.0
SHAKE_M = 0.03
PERTURB_AT_S = 1.0
#: lifted: at least this far above where it stood (m; the issue's target)
LIFTED_M = 0.10
#: a run gives up after this much simulated time (s)
SIM_TIME_LIMIT_S = 90.0
#: an object back on the table (or below it) after the hold: dropped (m above where it stood)
DROPPED_BELOW_M = 0.02


def grasp_camera(grasp: GraspConfig) -> CameraConfig:
    """The seeds' camera (services/robot_sim/scene.py) at its place on the hand, its image upright when the hand is
    beside an object (optical x = the end effector's −x, y = its −y) and its axis turned toward the approach axis by
    the angle under which it sees a cup's card from the pre-grasp view."""
    x, _, z = CAMERA_IN_EE_XYZ
    ahead = HOLD_AHEAD_M + grasp.approach_m - (CUP.radius_m + CARD_OFFSET_M) - z
    tilt = math.atan2(x, ahead)
    R = frames.rot_z(math.pi) @ frames.rot_y(tilt)
    return msgspec.structs.replace(CameraConfig(), camera_in_ee=PoseConfig(
        xyz=CAMERA_IN_EE_XYZ, rpy_deg=tuple(float(v) for v in np.degrees(frames.matrix_to_euler_xyz(R)))))


def object_height(kind: str) -> float:
    return CUP.height_m if kind == "cup" else BOX_M[1]


def card_in_object(kind: str) -> np.ndarray:
    """The tag card on the object's face toward the arm (its frame's +z), upright (the tag's +y the object's)."""
    front = CUP.radius_m if kind == "cup" else BOX_M[2] / 2
    return frames.homogeneous(np.eye(3), [0.0, 0.0, front + CARD_OFFSET_M])


def object_in_base(placement: dict, kind: str, table: TableConfig) -> np.ndarray:
    """The object's frame where the placement puts it: standing on the table (its y up), its z toward the arm."""
    x, y, turn = placement["x_m"], placement["y_m"], math.radians(FACING_DEG + placement["turn_deg"])
    toward = math.atan2(-y, -x) + turn  # from the object toward the arm's base, turned to where the hand comes from
    z_axis = np.array([math.cos(toward), math.sin(toward), 0.0])
    y_axis = np.array([0.0, 0.0, 1.0])
    R = np.column_stack([np.cross(y_axis, z_axis), y_axis, z_axis])
    return frames.homogeneous(R, [x, y, table.top_z_m + object_height(kind) / 2])


#: the end effector holding the object, in the object's frame: its approach axis into the object (−z), its y up
EE_IN_OBJECT_R = np.diag([-1.0, 1.0, -1.0])


def hand_in_object(back_m: float) -> np.ndarray:
    """The end effector ``back_m`` behind where it holds the object, along its approach axis (object frame)."""
    return frames.homogeneous(EE_IN_OBJECT_R, [0.0, 0.0, HOLD_AHEAD_M + back_m])


def taught_view(kind: str, grasp: GraspConfig, camera: CameraConfig) -> PoseConfig:
    """The pre-grasp view as a goal: the camera in the card's frame when the hand is ``approach_m`` back."""
    camera_in_card = (np.linalg.inv(card_in_object(kind)) @ hand_in_object(grasp.approach_m)
                      @ camera.camera_in_ee.matrix())
    return PoseConfig(xyz=tuple(float(v) for v in camera_in_card[:3, 3]),
                      rpy_deg=tuple(float(v) for v in np.degrees(frames.matrix_to_euler_xyz(camera_in_card[:3, :3]))))


def _joints_at(kin: ArmKinematics, q0, T: np.ndarray) -> Optional[np.ndarray]:
    """Joints that put the end effector at ``T`` from ``q0`` (a continuous joint within half a turn of ``q0``'s:
    the solver's steps may wind one by turns), or None."""
    q, ok = inverse_kinematics(kin, q0, T[:3, :3], T[:3, 3])
    if not ok or not kin.arm.within_limits(q):
        return None
    q0 = np.asarray(q0, dtype=float)
    for i, joint in enumerate(kin.arm.joints):
        if joint.continuous:
            q[i] = q0[i] + math.remainder(q[i] - q0[i], 2.0 * math.pi)
    return q


#: the inverse kinematics' starts for the ready pose: the arm's home, and it turned at its first joint (deg), a
#: local solver landing elsewhere from each
READY_SEED_TURNS_DEG = (0.0, -30.0, 30.0, -60.0, 60.0)


def ready_joints(arm_name: str, grasp: GraspConfig, table: TableConfig) -> np.ndarray:
    """The arm's ready pose: the pre-grasp view of the middle of the placements, the solution farthest from the
    joints' limits of those found from :data:`READY_SEED_TURNS_DEG`."""
    arm = load_arm(arm_name)
    kin = ArmKinematics(arm)
    middle = {"x_m": sum(PLACE_X_M) / 2, "y_m": sum(PLACE_Y_M) / 2, "turn_deg": 0.0}
    T = object_in_base(middle, "cup", table) @ hand_in_object(grasp.approach_m)
    found = []
    for turn in READY_SEED_TURNS_DEG:
        seed = arm.home.copy()
        seed[0] += math.radians(turn)
        q = _joints_at(kin, seed, T)
        if q is not None:
            found.append((float(np.min(arm.limit_margins_deg(q), initial=np.inf)), turn, q))
    if not found:
        raise ValueError(f"the {arm_name} does not reach the ready pose")
    return max(found, key=lambda f: (f[0], -abs(f[1])))[2]


def draw_placements(arm_name: str, count: int, seed: int, kind: str, grasp: GraspConfig,
                    table: TableConfig) -> list[dict]:
    """``count`` placements from ``seed``; one whose grasp, pre-grasp view or lift the arm cannot reach (from its
    ready pose, within its joint limits) is drawn again, and counted."""
    rng = random.Random(seed)
    arm = load_arm(arm_name)
    kin = ArmKinematics(arm)
    q_ready = ready_joints(arm_name, grasp, table)
    placements, redrawn = [], 0
    while len(placements) < count:
        placement = {"x_m": round(rng.uniform(*PLACE_X_M), 4), "y_m": round(rng.uniform(*PLACE_Y_M), 4),
                     "turn_deg": round(rng.uniform(-PLACE_TURN_DEG, PLACE_TURN_DEG), 2)}
        T = object_in_base(placement, kind if kind != "none" else "cup", table)
        lifted = frames.homogeneous(np.eye(3), [0.0, 0.0, grasp.lift_m]) @ T @ hand_in_object(0.0)
        q = _joints_at(kin, q_ready, T @ hand_in_object(grasp.approach_m))
        reachable = q is not None and all(_joints_at(kin, q, pose) is not None
                                          for pose in (T @ hand_in_object(0.0), lifted))
        if not reachable:
            redrawn += 1
            if redrawn > 10 * count:
                raise ValueError(f"no reachable placement in {redrawn} draws")
            continue
        placements.append({"index": len(placements), "seed": seed, **placement, "redrawn_before": redrawn})
    return placements


def grasp_scenario(base: Scenario, placement: dict, kind: str) -> Scenario:
    """The base scenario with the object where the placement puts it, its card the target, the pre-grasp view the
    goal, and the arm at its ready pose."""
    scenario = msgspec.convert(msgspec.to_builtins(base), Scenario)
    table = scenario.table or TableConfig()
    scenario.table = table
    scenario.camera = grasp_camera(scenario.grasp)
    arm = load_arm(scenario.robot.arm)
    shape = kind if kind != "none" else "cup"
    T = object_in_base(placement, shape, table)
    pose = PoseConfig(xyz=tuple(float(v) for v in T[:3, 3]),
                      rpy_deg=tuple(float(v) for v in np.degrees(frames.matrix_to_euler_xyz(T[:3, :3]))))
    card = card_in_object(shape)
    card_pose = PoseConfig(xyz=tuple(float(v) for v in card[:3, 3]), rpy_deg=(0.0, 0.0, 0.0))
    if kind == "none":  # the card alone where the cup's would be, nothing behind it
        Tc = T @ card
        scenario.target = TargetConfig(size_m=CARD_TAG_M, pose_in_base=PoseConfig(
            xyz=tuple(float(v) for v in Tc[:3, 3]),
            rpy_deg=tuple(float(v) for v in np.degrees(frames.matrix_to_euler_xyz(Tc[:3, :3])))))
        scenario.objects = []
    else:
        obj = (SceneObject(name="cup", kind="cup", cup=CUP, mass_kg=CUP_KG, friction=DRY_FRICTION, pose_in_base=pose)
               if kind == "cup" else
               SceneObject(name="box", kind="box", size_m=BOX_M, mass_kg=BOX_KG,
                           friction=WET_FRICTION if kind == "slippery" else DRY_FRICTION, pose_in_base=pose))
        scenario.objects = [obj]
        scenario.target = TargetConfig(size_m=CARD_TAG_M, on_object=obj.name, pose_in_object=card_pose)
    scenario.goal = GoalConfig(features=None, camera_in_tag=taught_view(shape, scenario.grasp, scenario.camera))
    q = ready_joints(scenario.robot.arm, scenario.grasp, table)
    scenario.robot = msgspec.structs.replace(scenario.robot, initial_joints_deg=[
        float(v) for v in arm.model_to_physical_deg(q)])
    return scenario


# ------------------------------------------------------------------------------------------------ one placement
class _View:
    """What the run sees of the stack: the controller's statuses and the simulator's objects, as they come."""

    def __init__(self, session, keys: Keys) -> None:
        self.lock = threading.Condition()
        self.statuses: list[m.ControllerStatus] = []
        self.objects: list[tuple[int, dict]] = []
        self._subs = [
            session.declare_subscriber(keys.controller_status, lambda s: self._on(
                self.statuses, m.decode(s.payload.to_bytes(), m.ControllerStatus))),
            session.declare_subscriber(keys.sim_objects, lambda s: self._on_objects(
                m.decode(s.payload.to_bytes(), m.SimObjects))),
        ]

    def _on(self, into: list, message) -> None:
        with self.lock:
            into.append(message)
            self.lock.notify_all()

    def _on_objects(self, message: m.SimObjects) -> None:
        poses = {o.name: frames.homogeneous(frames.quat_wxyz_to_matrix(o.pose.quat_wxyz), o.pose.xyz)
                 for o in message.objects}
        self._on(self.objects, (message.header.stamp_ns, poses))

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


def run_placement(task: RunTask, each=None) -> dict:
    """One placement's grasp, hold, shake (and perturbation): its row."""
    from services.stack.composed import ComposedStack

    args = task.args
    base = msgspec.convert(args["base"], Scenario)
    placement, kind, perturb = args["placement"], args["object"], args.get("perturb")
    scenario = grasp_scenario(base, placement, kind)
    config = stack_config(scenario)
    keys = Keys(config.robot.robot_id)
    row = {"label": task.label, "placement": placement, "object": kind, "arm": scenario.robot.arm,
           "perturb": perturb}
    started = time.monotonic()
    view: dict = {}

    def before_robot(stack) -> None:
        session = stack.open_session()
        view.update(session=session, view=_View(session, keys))
        reply = call_task(session, keys, m.START_TASK, m.TaskRequest(
            operator="mfvs experiment grasp", reason=f"placement {placement['index']}", plan=m.TaskPlan.GRASP))
        if not reply.ok:
            raise RuntimeError(f"the controller did not start the grasp: {reply.message}")

    with ComposedStack(config, before_robot=before_robot) as stack:
        session, seen = view["session"], view["view"]
        try:
            row.update(_follow(stack, session, keys, seen, kind, perturb, started, scenario.timeout_s))
        finally:
            seen.close()
            session.close()
    row["wall_time_s"] = round(time.monotonic() - started, 2)
    return row


def _sim_s(stamp_ns: int) -> float:
    from protocol.conventions import LOCKSTEP_EPOCH_NS

    return (stamp_ns - LOCKSTEP_EPOCH_NS) * 1e-9


def _follow(stack, session, keys: Keys, seen: _View, kind: str, perturb: Optional[str], started: float,
            timeout_s: float) -> dict:
    """Watch the task to its hold, hold, perturb, shake: the figures."""
    name = {"cup": "cup", "box": "box", "slippery": "box"}.get(kind)
    phases: dict[str, float] = {}
    outcome, detail = "", ""
    seen_count = 0

    def newest_object_time() -> float:
        return _sim_s(seen.objects[-1][0]) if seen.objects else 0.0

    def wait_until(predicate, limit_s: float) -> bool:
        with seen.lock:
            while not predicate():
                if time.monotonic() - started > timeout_s or not stack.robot_alive():
                    return False
                seen.lock.wait(timeout=0.5)
                if newest_object_time() > limit_s and seen.objects:
                    return False
            return True

    # the task to its hold (or its end)
    def task_state():
        nonlocal seen_count, outcome, detail
        for status in seen.statuses[seen_count:]:
            phase = status.phase
            t = _sim_s(status.header.source_stamp_ns)
            if phase and phase not in phases:
                phases[phase] = t
            if status.detail.startswith("task failed") or status.detail.startswith("task done"):
                outcome, detail = "failed" if "failed" in status.detail else "done", status.detail
        seen_count = len(seen.statuses)
        return "hold" in phases or outcome != ""

    wait_until(task_state, SIM_TIME_LIMIT_S)
    reached_hold = "hold" in phases
    row: dict = {"phases_s": {k: round(v, 3) for k, v in phases.items()}, "failure": detail if outcome else ""}
    task = call_task(session, keys, m.GET_TASK)
    row["verdict"] = task.grasp.value if task.grasp is not None else None
    if not reached_hold or name is None:
        row.update(grasped=False, lifted_m=_lifted(seen, name), held_s=0.0, slip_mm=None, dropped=None,
                   status="timeout" if not reached_hold and not outcome else outcome or "no_object")
        return row
    hold_at = phases["hold"]
    row["grasp_s"] = round(phases["lift"] - phases["grasp"], 3)  # the fingers closing until the hand held it
    with seen.lock:
        at_hold = _in_hand(seen, name, stack)
    perturbed = False
    if perturb is not None:
        wait_until(lambda: newest_object_time() >= hold_at + PERTURB_AT_S, SIM_TIME_LIMIT_S)
        _perturb(stack, session, keys, perturb)
        perturbed = True
    held = wait_until(lambda: newest_object_time() >= hold_at + HOLD_S, SIM_TIME_LIMIT_S)
    task = call_task(session, keys, m.GET_TASK)
    row["verdict_after_hold"] = task.grasp.value if task.grasp is not None else None
    with seen.lock:
        lifted = _lifted(seen, name)
    row.update(grasped=True, lifted_m=lifted, held_s=round(newest_object_time() - hold_at, 3) if held else 0.0,
               status="held" if held else "timeout")
    if perturbed:
        row["dropped"] = lifted < DROPPED_BELOW_M
        return row
    row["shake"] = _shake(session, keys, seen, stack, started, timeout_s)
    with seen.lock:
        after = _in_hand(seen, name, stack)
        row["lifted_after_shake_m"] = _lifted(seen, name)
    row["slip_mm"] = round(float(np.linalg.norm(after[:3, 3] - at_hold[:3, 3])) * 1e3, 3)
    row["dropped"] = row["lifted_after_shake_m"] < DROPPED_BELOW_M
    return row


def _lifted(seen: _View, name: Optional[str]) -> float:
    """How far above where it first stood the object is now (m)."""
    if name is None or not seen.objects:
        return 0.0
    first, last = seen.objects[0][1][name], seen.objects[-1][1][name]
    return round(float(last[2, 3] - first[2, 3]), 4)


def _in_hand(seen: _View, name: str, stack) -> np.ndarray:
    """The object in the end effector's frame now (MuJoCo's truth of both)."""
    sim = stack.services["robot_sim"].sim
    T_ee = sim.ee_pose()
    return np.linalg.inv(T_ee) @ seen.objects[-1][1][name]


def _perturb(stack, session, keys: Keys, perturb: str) -> None:
    if perturb == "estop":
        session.put(keys.estop, m.encode(m.EStop(header=m.Header(), operator="mfvs experiment grasp",
                                                 reason="perturbation during the hold")))


def _shake(session, keys: Keys, seen: _View, stack, started: float, timeout_s: float) -> dict:
    """Stop the grasp task (the fingers keep their targets) and move the held object ±SHAKE_M sideways and back."""
    call_task(session, keys, m.STOP_TASK, m.TaskRequest(operator="mfvs experiment grasp", reason="shake"))
    moves = []
    for dy in (SHAKE_M, -2 * SHAKE_M, SHAKE_M):
        reply = call_task(session, keys, m.START_TASK, m.TaskRequest(
            operator="mfvs experiment grasp", reason="shake", plan=m.TaskPlan.MOVE, move_m=(0.0, dy, 0.0),
            move_frame=m.MoveFrame.BASE))
        if not reply.ok:
            moves.append(f"refused: {reply.message}")
            break
        while time.monotonic() - started < timeout_s and stack.robot_alive():
            status = call_task(session, keys, m.GET_TASK)
            if status.state is not m.TaskState.RUNNING:
                moves.append(status.outcome)
                break
            with seen.lock:
                seen.lock.wait(timeout=0.2)
    return {"moves": moves}


# ------------------------------------------------------------------------------------------------ the experiment
def summarize(rows: list[dict], kind: str) -> dict:
    n = len(rows)
    if kind == "none":
        empty = sum(r.get("verdict") == "empty" for r in rows)
        return {"placements": n, "said_empty": empty, "rate": round(empty / n, 3) if n else None}
    if kind == "slippery":
        caught = sum(r.get("verdict") == "slipping" or (r.get("failure") or "").find("slipping") >= 0 for r in rows)
        return {"placements": n, "caught_slipping": caught, "rate": round(caught / n, 3) if n else None}
    good = [r for r in rows if r.get("grasped") and r.get("lifted_m", 0.0) >= LIFTED_M
            and r.get("held_s", 0.0) >= HOLD_S - 0.05 and (r.get("slip_mm") or 0.0) < 10.0 and not r.get("dropped")]
    low, high = wilson_interval(len(good), n)
    slips = sorted(r["slip_mm"] for r in rows if r.get("slip_mm") is not None)
    return {"placements": n, "lifted_and_held": len(good), "rate": round(len(good) / n, 3) if n else None,
            "wilson_95": [None if low is None else round(low, 3), None if high is None else round(high, 3)],
            "dropped": sum(bool(r.get("dropped")) for r in rows),
            "slip_mm_max": slips[-1] if slips else None,
            "failures": sorted({r.get("failure") or r.get("status") for r in rows if r not in good})}


def run(arm: Optional[str], kind: str, placements: int, seed: int, perturb: Optional[str], jobs: int,
        out_dir: Optional[Path], base: Optional[Scenario] = None, progress=None) -> dict:
    """The experiment (module doc): ``placements`` seeded placements of ``kind`` on ``arm`` (None: the base
    scenario's); ``progress(row)`` as each run ends. Its output: the runs and the summary."""
    if kind not in OBJECTS:
        raise ValueError(f"grasp takes the objects {', '.join(OBJECTS)}, not {kind!r}")
    if perturb is not None and perturb not in PERTURBATIONS:
        raise ValueError(f"grasp takes the perturbations {', '.join(PERTURBATIONS)}, not {perturb!r}")
    base = base or Scenario()
    if arm is not None:
        base = msgspec.structs.replace(base, robot=msgspec.structs.replace(base.robot, arm=arm))
    base = msgspec.structs.replace(base, table=base.table or TableConfig(), timeout_s=min(base.timeout_s, 300.0))
    drawn = draw_placements(base.robot.arm, placements, seed, kind, base.grasp, base.table)
    out = Path(out_dir) if out_dir is not None else Path(".")
    tasks = [RunTask(label=f"{kind}_{p['index']}", scenario=base, out_dir=out / f"{kind}_{p['index']}",
                     runner="services.experiments.grasp:run_placement",
                     args={"base": msgspec.to_builtins(base), "placement": p, "object": kind, "perturb": perturb})
             for p in drawn]
    rows = run_tasks(tasks, jobs, on_done=None if progress is None else (lambda task, row: progress(row)))
    result = {"experiment": "grasp", "arm": base.robot.arm, "object": kind, "seed": seed, "perturb": perturb,
              "summary": summarize(rows, kind), "runs": rows}
    if out_dir is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "grasp.json").write_text(json.dumps(result, indent=1))
    return result
