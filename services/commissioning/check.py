"""``mfvs check arm``: the commissioning check on the arm the stack drives (or, ``--simulate``, on an emulated arm
that may be told to disagree with its description), as a pass/fail table.

The robot node runs the check (:mod:`services.robot.arm_check`): it moves each joint by a few degrees at a low
speed and back, and compares the arm's own Cartesian report with the arm description's forward kinematics. The arm
moves, so the command asks for ``--yes``. The verdict stays with the robot (in every state it publishes, and in
its ``arm_check.record`` file): the controller starts tasks only on an arm that passed (or whose check is waived).
"""
from __future__ import annotations

import json
import sys
import threading
import time
from typing import Optional

from protocol import messages as m
from protocol.keys import Keys
from services.model.arm import DEFAULT_ARM, check_arm_name

#: how long a check may take (seven joints out and back at the slowest speed, with settling)
CHECK_TIMEOUT_S = 900.0


def add_parser(sub, add_connection_options, operator_session) -> None:
    """``operator_session(args)``: a session to the stack's router as the operator (the command line's own)."""
    check = sub.add_parser("check", help="commissioning checks: `mfvs check arm` compares the arm with its "
                                         "description, `mfvs check rs485` a real arm's actuator bus")
    what = check.add_subparsers(dest="what", metavar="WHAT", required=True, parser_class=type(check))
    arm = what.add_parser("arm", help="move each joint a few degrees and back; compare the arm's own Cartesian "
                                      "report with the arm description (joint directions, zeros, end-effector "
                                      "frame)")
    arm.add_argument("--yes", action="store_true", help="the arm is clear to move (without it nothing moves)")
    arm.add_argument("--simulate", action="store_true", help="on an emulated arm (robot_sim, its own router)")
    arm.add_argument("--mirror-joint", type=int, action="append", default=[], metavar="N",
                     help="--simulate: the emulated arm's joint N turns the other way from the description")
    arm.add_argument("--joints", default="", help="which joints, e.g. 1,2,3 (default: every joint of the arm)")
    arm.add_argument("--arm", default=None, metavar="NAME",
                     help="--simulate: the arm emulated (default j2s7s300); else the arm the robot must declare it "
                          "runs (default: whichever it runs)")
    arm.add_argument("--step-deg", type=float, default=5.0, help="how far each joint moves (1-10°)")
    arm.add_argument("--speed-dps", type=float, default=5.0, help="how fast (1-10°/s)")
    arm.add_argument("--operator", default="mfvs-cli", help="who is checking (logged by the robot)")
    arm.add_argument("--json", action="store_true", help="print one JSON object")
    add_connection_options(arm)
    arm.set_defaults(func=_cmd_check_arm, operator_session=operator_session)
    _add_rs485_parser(what)


def _add_rs485_parser(what) -> None:
    rs485 = what.add_parser("rs485", help="a real arm's actuator bus through Kinova's USB comm layer, the first hour "
                                          "on hardware: per-call latency, empty reads, the replies and layouts of "
                                          "0x02/0x15/0x16/0x17 against Kinova's high-level reading; a report to "
                                          "send back (nothing moves unless --torque-joint N --yes)")
    rs485.add_argument("--arm", default=DEFAULT_ARM, metavar="NAME", help="the arm connected (default j2s7s300)")
    rs485.add_argument("--sdk", default=None, metavar="DIR",
                       help="Kinova's SDK: the folder of USBCommLayerUbuntu.so (default $MFVS_KINOVA_SDK)")
    rs485.add_argument("--torque-joint", type=int, default=None, metavar="N",
                       help="also the torque handshake on joint N alone (a wrist joint; hold or support the arm)")
    rs485.add_argument("--yes", action="store_true", help="with --torque-joint: the arm is supported and may move")
    rs485.add_argument("--out", default=None, metavar="FILE.md", help="write the report there (default: print it)")
    rs485.add_argument("--json", action="store_true", help="print one JSON object")
    rs485.set_defaults(func=_cmd_check_rs485)


def _cmd_check_rs485(args) -> int:
    """Exit 0: every step agrees; 1: one differs or got no reply; 2: the bus could not be opened."""
    from services.model.arm import ArmError, load_arm
    from services.robot_gateway.kinova_sdk import ArmStartError, put_sdk_on_loader_path
    from services.robot_gateway.kinova_usb import COMMAND_LAYER, locate_comm_layer
    from services.robot_gateway.rs485_check import report_markdown, run_check

    try:
        arm = load_arm(check_arm_name(args.arm))
        if args.torque_joint is not None and not 1 <= args.torque_joint <= arm.n_joints:
            raise ValueError(f"--torque-joint: 1 to {arm.n_joints} on the {arm.name}")
        comm_layer = locate_comm_layer(args.sdk)
        command_layer = comm_layer.parent / COMMAND_LAYER
        if command_layer.is_file():
            put_sdk_on_loader_path(command_layer, "usb")  # the command layer loads the comm layer by name
        else:
            command_layer = None
        device, steps = run_check(arm, comm_layer, command_layer, args.torque_joint, args.yes)
    except (ArmStartError, ArmError, ValueError) as exc:
        print(f"mfvs check rs485: {exc}", file=sys.stderr)
        return 2
    report = report_markdown(device, steps)
    if args.out:
        with open(args.out, "w") as out:
            out.write(report)
    if args.json:
        print(json.dumps({"device": device, "steps": [vars(step) for step in steps]}))
    elif not args.out:
        print(report)
    else:
        for step in steps:
            print(f"{step.name}: {step.verdict}: {step.detail}")
        print(f"report: {args.out}")
    return 0 if all(step.verdict in ("agrees", "not run") for step in steps) else 1


def robot_declared_arm(session, keys: Keys, timeout_s: float = 2.0) -> Optional[str]:
    """The arm the robot declares in its states (None: no state within ``timeout_s``)."""
    heard: list[str] = []
    done = threading.Event()

    def on_state(sample) -> None:
        try:
            heard.append(m.decode(sample.payload.to_bytes(), m.RobotState).arm)
            done.set()
        except m.ProtocolError:
            pass

    subscriber = session.declare_subscriber(keys.robot_state, on_state)
    try:
        done.wait(timeout_s)
    finally:
        subscriber.undeclare()
    return heard[0] if heard else None


def request_check(session, keys: Keys, request: m.ArmCheckRequest, timeout_s: float = CHECK_TIMEOUT_S
                  ) -> Optional[m.ArmCheckReply]:
    """Ask the robot to run the check; its reply (None when no robot answered)."""
    for reply in session.get(keys.robot_check_arm, payload=m.encode(request), timeout=timeout_s):
        if reply.ok is not None:
            return m.decode(reply.ok.payload.to_bytes(), m.ArmCheckReply)
    return None


def simulated_check(request: m.ArmCheckRequest, mirrored: list[int], arm: str = DEFAULT_ARM) -> m.ArmCheckReply:
    """The check on robot_sim's emulated ``arm`` (lockstep, no camera), with ``mirrored`` joints turning the other
    way from the description, through a router of its own."""
    from services.robot_sim.firmware import ActuatorConfig
    from services.robot_sim.scene import CameraConfig, SceneConfig
    from services.robot_sim.service import RobotSimConfig, RobotSimService
    from services.robot.arm_check import ArmCheckConfig
    from services.runtime.transport import Router, open_session

    with Router(port=0) as router:
        config = RobotSimConfig(arm=arm, clock="lockstep", zenoh=router.client_config(),
                                scene=SceneConfig(camera=CameraConfig(enabled=False)),
                                actuators=ActuatorConfig(mirrored_joints=mirrored),
                                arm_check=ArmCheckConfig(waived=False))
        robot = RobotSimService(config)
        robot.start()
        session = open_session(router.client_config())
        try:
            deadline = time.monotonic() + 30.0
            while time.monotonic() < deadline:  # the robot's queryable, declared: the check can be asked for
                if list(session.liveliness().get(Keys().liveliness("robot_sim"), timeout=1.0)):
                    break
            reply = request_check(session, robot.keys, request)
        finally:
            session.close()
            robot.stop()
    if reply is None:
        raise RuntimeError("the simulated robot did not answer")
    return reply


def _table(reply: m.ArmCheckReply) -> list[str]:
    lines = [f"{'joint':>5}  {'moved':>7}  {'direction':<10} {'motion error':>16}  {'zero':>7}  verdict"]
    for j in reply.joints:
        lines.append(f"{j.joint:>5}  {j.moved_deg:>+6.2f}°  {j.direction:<10} {j.motion_error_mm:>7.2f} mm "
                     f"{j.motion_error_deg:>5.2f}°  {j.zero_offset_deg:>+6.2f}°  {'PASS' if j.passed else 'FAIL'}")
    axis = ", ".join(f"{v:.2f}" for v in reply.ee_frame_axis)
    lines.append(f"at the start: {reply.static_error_mm:.2f} mm, {reply.static_error_deg:.2f}° from the description "
                 f"(the end-effector frame turned {reply.ee_frame_rotation_deg:.2f}° about [{axis}])")
    lines.append(("PASSED: " if reply.passed else "FAILED: ") + reply.message)
    return lines


def _cmd_check_arm(args) -> int:
    try:
        joints = [int(j) for j in args.joints.split(",") if j.strip()]
        request = m.decode(m.encode(m.ArmCheckRequest(  # decoded as the robot will: the same limits, said here
            header=m.Header(stamp_ns=time.time_ns()), confirm=args.yes, joints=joints, step_deg=args.step_deg,
            speed_dps=args.speed_dps, operator=args.operator)), m.ArmCheckRequest)
    except (ValueError, m.ProtocolError) as exc:
        print(f"mfvs check arm: {exc}", file=sys.stderr)
        return 2
    if not args.yes:
        print(f"mfvs check arm: this moves joints {joints} by {args.step_deg}° each at {args.speed_dps}°/s and back; "
              "with the arm clear to move, run it again with --yes", file=sys.stderr)
        return 2
    if args.mirror_joint and not args.simulate:
        print("mfvs check arm: --mirror-joint configures the emulated arm: it needs --simulate", file=sys.stderr)
        return 2
    try:
        if args.arm is not None:
            check_arm_name(args.arm)
        if args.simulate:
            reply = simulated_check(request, args.mirror_joint, args.arm or DEFAULT_ARM)
        else:
            session = args.operator_session(args)
            try:
                if args.arm is not None:
                    robot_arm = robot_declared_arm(session, Keys(args.robot_id))
                    if robot_arm != args.arm:
                        raise RuntimeError(f"the robot runs the {robot_arm or 'unknown arm (no state heard)'}, not "
                                           f"the {args.arm}: nothing was checked")
                reply = request_check(session, Keys(args.robot_id), request)
            finally:
                session.close()
            if reply is None:
                raise RuntimeError(f"no robot answered on {Keys(args.robot_id).robot_check_arm} (is the stack up?)")
    except Exception as exc:
        print(f"mfvs check arm: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"passed": reply.passed, "ran": reply.ok, "state": reply.state.value,
                          "message": reply.message, "static_error_mm": reply.static_error_mm,
                          "static_error_deg": reply.static_error_deg,
                          "ee_frame_rotation_deg": reply.ee_frame_rotation_deg,
                          "ee_frame_axis": list(reply.ee_frame_axis),
                          "joints": [{"joint": j.joint, "moved_deg": j.moved_deg, "direction": j.direction,
                                      "motion_error_mm": j.motion_error_mm, "motion_error_deg": j.motion_error_deg,
                                      "zero_offset_deg": j.zero_offset_deg, "passed": j.passed, "detail": j.detail}
                                     for j in reply.joints]}, indent=2))
    else:
        print("\n".join(_table(reply)) if reply.ok else f"the check did not run to the end: {reply.message}")
    return 0 if reply.passed else 1
