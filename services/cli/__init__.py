"""The ``mfvs`` command line: its parser and entry point (docs/contracts.md lists the commands that are stable; the
rest change with their issues). What each command does is :mod:`services.cli.commands`; the options the commands
share with the benchmarks are :mod:`services.cli.options`."""
from __future__ import annotations

import argparse
import difflib
import os
import re
import sys

from services.cli.commands import (
    BENCHMARKS,
    cmd_authority,
    cmd_bench,
    cmd_bus_hub,
    cmd_demo,
    cmd_down,
    cmd_estop,
    cmd_experiment,
    cmd_jog,
    cmd_model,
    cmd_restart,
    cmd_router,
    cmd_servo,
    cmd_status,
    cmd_task,
    cmd_teach,
    cmd_up,
    mfvs_version,
    operator_session,
    service_graph,
    stack_connection,
)
from services.cli.options import add_arm_option, add_connection_options, add_jobs_option, add_processes_option


class _Parser(argparse.ArgumentParser):
    """argparse, with the closest command or choice offered when one is mistyped."""

    def error(self, message: str):
        wrong = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if wrong:
            choices = re.findall(r"'([^']*)'", wrong.group(2))
            close = difflib.get_close_matches(wrong.group(1), choices, n=1)
            if close:
                message += f"; did you mean '{close[0]}'?"
        super().error(message)


#: the commands that run the stack's own infrastructure: parsed without the rest of the CLI, whose options import
#: NumPy, OpenCV and the arm descriptions (20 MB and 0.15 s of CPU in a router every stack starts)
INFRASTRUCTURE_COMMANDS = ("router", "bus-hub")


def build_parser(infrastructure_only: bool = False) -> argparse.ArgumentParser:
    parser = _Parser(
        prog="mfvs",
        description="Mixed-frame visual servoing for assistive robot arms (Kinova JACO-2) over Eclipse Zenoh.",
    )
    parser.add_argument("--version", action="version", version=f"mfvs {mfvs_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    # each group in the order `mfvs --help` lists the commands
    _add_infrastructure_commands(sub)
    if infrastructure_only:
        return parser
    _add_model_command(sub)
    _add_stack_commands(sub)
    _add_servo_commands(sub)
    _add_package_commands(sub)
    _add_operator_commands(sub)
    _add_bench_command(sub)
    return parser


def _domain_id(text: str) -> int:
    """A ROS domain id on the command line (services.ros2_bridge.cli.domain_id), as argparse reports a bad one."""
    from services.ros2_bridge.cli import domain_id

    try:
        return domain_id(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _add_infrastructure_commands(sub) -> None:
    """``mfvs router`` and ``mfvs bus-hub``: the stack's own infrastructure, parsed with nothing else
    imported (:data:`INFRASTRUCTURE_COMMANDS`)."""
    router = sub.add_parser("router", help="run a zenoh router in the foreground until SIGTERM/SIGINT")
    router.add_argument("--port", type=int, default=None,
                        help="TCP port to listen on (0: a free one; default: the --config file's listen endpoint, "
                             "else 7447); a port that conflicts with the file's is an error")
    router.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    router.add_argument("--config", default=None, help="zenoh JSON5 config file (access control, TLS)")
    router.add_argument("--realtime-priority", type=int, default=30, metavar="N",
                        help="SCHED_FIFO priority where the OS grants it: the router carries safety's commands to "
                             "the robot (0: normal scheduling)")
    router.set_defaults(func=cmd_router)

    hub = sub.add_parser("bus-hub", help="run the loopback CAN hub that carries RS-485 frames between robot_sim's "
                         "emulated actuators and robot_gateway (python-can interface mfvs_hub)")
    hub.add_argument("--port", type=int, default=7448, help="TCP port to listen on (default 7448)")
    hub.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    hub.add_argument("--realtime-priority", type=int, default=40, metavar="N",
                     help="SCHED_FIFO priority where the OS grants it, as the robot's loops (0: normal scheduling)")
    hub.set_defaults(func=cmd_bus_hub)


def _add_model_command(sub) -> None:
    """``mfvs model``: an arm's description."""
    model = sub.add_parser("model", help="an arm's description (j2s7s300: Sensors 2022's 7-DoF; j2n6s300: the JACO "
                                         "thesis's 6-DoF): its joints, limits, home, URDF and forward kinematics")
    model.add_argument("what", choices=["urdf", "info", "fk"],
                       help="urdf: print the URDF; info: joints, limits, home pose; fk: the end effector's pose")
    add_arm_option(model)
    model.add_argument("--joints-deg", default=None, metavar="A,B,...",
                       help="fk: physical joint angles (deg, as GetAngularPosition), one per joint")
    model.add_argument("--json", action="store_true", help="one JSON object (info, fk)")
    model.set_defaults(func=cmd_model)


def _add_stack_commands(sub) -> None:
    """``mfvs up``, ``down``, ``restart``, ``status``: a stack's processes."""
    up_cmd = sub.add_parser("up", help="start a stack (router and services) as background processes")
    up_cmd.add_argument("--profile", default="sim", help="sim, gateway, or a profile YAML file")
    up_cmd.add_argument("--clock", choices=["realtime", "lockstep"], default=None, help="override the clock mode")
    up_cmd.add_argument("--port", type=int, default=7447, help="router port (sim and gateway profiles)")
    up_cmd.add_argument("--bus-port", type=int, default=7448, help="CAN hub port (gateway profile)")
    up_cmd.add_argument("--bus-period", type=float, default=None, metavar="MS",
                        help="the actuator bus's period (ms): 2 (default), 2.5, 3.33 or 5, where USB does not "
                             "sustain 2 ms (profiles with robot_gateway; `mfvs bench rs485 --period` measures it)")
    up_cmd.add_argument("--wait", type=float, default=60.0, help="seconds to wait for every service")
    add_arm_option(up_cmd, default=None, what="the profile's (j2s7s300 unless it sets one)")
    up_cmd.add_argument("--ros2", action="store_true",
                        help="also run the ROS 2 bridge (`mfvs ros2` as a service of the stack: domain "
                             "$ROS_DOMAIN_ID, else 0; a profile may list ros2_bridge with its own settings)")
    up_cmd.add_argument("--host", default=None,
                        help="in a profile across computers (deploy/profiles/multi-host.yaml), which one this is: "
                             "start only its part")
    up_cmd.set_defaults(func=cmd_up)
    down_cmd = sub.add_parser("down", help="stop the stack `mfvs up` started")
    down_cmd.set_defaults(func=cmd_down)
    restart_cmd = sub.add_parser("restart", help="restart one process of the stack `mfvs up` started (a service, "
                                 "the router) with its command line, as its systemd unit would")
    restart_cmd.add_argument("name", help="the process's name in `mfvs status` (vision, safety, router, ...)")
    restart_cmd.set_defaults(func=cmd_restart)
    status_cmd = sub.add_parser("status", help="health, rates and error counters of the running services")
    status_cmd.add_argument("--json", action="store_true", help="print one JSON object")
    status_cmd.add_argument("--connect", default=None, help="router endpoint (default: the stack's)")
    status_cmd.add_argument("--robot-id", default=None, help="robot id (default: the stack's)")
    status_cmd.add_argument("--zenoh-config", default=None, help="zenoh client config (credentials, certificates)")
    status_cmd.set_defaults(func=cmd_status)


def _add_servo_commands(sub) -> None:
    """``mfvs servo``, ``experiment``, ``demo``: one servo task, the papers' experiments made of them, and a new
    user's first look."""
    servo = sub.add_parser("servo", help="run one servo task described by a scenario file")
    servo.add_argument("--scenario", required=True, help="scenario YAML (see examples/scenarios)")
    servo.add_argument("--profile", default="sim",
                       help="sim (the simulator's DSP; default) or gateway (robot_gateway over the RS-485 bus, as "
                            "processes; in lockstep the same run to the bit)")
    servo.add_argument("--bus", default="hub", choices=("hub", "kinova_usb"),
                       help="gateway profile: how robot_gateway reaches the emulated actuators: hub (the CAN hub; "
                            "default) or kinova_usb (robot_sim's emulated base through Kinova's own USB comm layer, "
                            "as a real arm's bus: Kinova's SDK from $MFVS_KINOVA_SDK, a C compiler for the stand-in "
                            "libusb)")
    servo.add_argument("--json", action="store_true", help="print one JSON object with the result")
    servo.add_argument("--out", help="directory for the trajectory log, plots and result.json")
    add_arm_option(servo, default=None, what="the scenario's robot.arm")
    servo.add_argument("--record", metavar="FILE.mcap", help="record every topic of the run into this MCAP file "
                       "(as `mfvs record` does)")
    add_processes_option(servo)
    servo.set_defaults(func=cmd_servo)

    experiment = sub.add_parser("experiment", help="reproduce one of the seed papers' experiments (Sensors 2022: "
                                                   "table3, part-a, part-b, part-c, part-d; Muñoz 2018: constraints; "
                                                   "JACO thesis: torque-control; Nelson 1995: tracking-region) and "
                                                   "report it beside the paper")
    experiment.add_argument("name", help="table3, part-a, part-b, part-c, part-d, constraints, torque-control, "
                                         "tracking-region, markerless or grasp")
    experiment.add_argument("--scenario", default=None,
                            help="the same comparison from this scenario's start and goal (Sensors 2022: its law and "
                                 "gains are replaced by the experiment's; constraints: its constraints are the "
                                 "case; tracking-region: its target motion and weights are the case)")
    experiment.add_argument("--out", default=None, help="directory for the runs' logs, the figures and report.md")
    experiment.add_argument("--json", action="store_true", help="print one JSON object with the runs and summary")
    experiment.add_argument("--profile", default="sim", help="sim (default) or gateway (robot_gateway over the "
                                                             "RS-485 bus; lockstep gives the same numbers)")
    experiment.add_argument("--random-starts", type=int, default=None, metavar="N",
                            help="table3 from N random Table-2-like starts (the tag placed at random around "
                                 "--scenario's, or table2.yaml's), each written as a scenario file to run again")
    experiment.add_argument("--seed", type=int, default=1, help="the random starts' draws (default 1)")
    experiment.add_argument("--quick", action="store_true",
                            help="torque-control: the five controllers on a 3 s reference (3/16 of the motion, the "
                                 "same speeds), without the runs that check the thesis's observations")
    experiment.add_argument("--runs", default=None, metavar="LABEL,...",
                            help="torque-control: only these runs (their labels, e.g. jt-pid,joint-velocity)")
    experiment.add_argument("--object", default=None, choices=("plane", "cup", "box", "slippery", "none"),
                            help="markerless: the object taught and servoed to (plane: a textured box face, the "
                                 "default; cup); grasp: the object grasped (cup, the default; box; slippery: the "
                                 "box wet; none: the tag card alone, nothing to hold)")
    experiment.add_argument("--placements", type=int, default=None, metavar="N",
                            help="grasp: N seeded placements of the object on the table (default 10)")
    experiment.add_argument("--texture", default=None, metavar="FILE",
                            help="markerless: an image printed on the object (default: the procedural print)")
    experiment.add_argument("--perturb", action="append", default=None,
                            metavar="lighting|occlusion|swap|clutter|webcam|estop",
                            help="markerless: the servo lit otherwise than the teach, an occluder crossing the "
                                 "object, the object swapped for another, objects of a like print beside it, or a "
                                 "webcam's noise, blur and JPEG (may be given more than once); grasp: an "
                                 "emergency stop 1 s into the hold")
    add_jobs_option(experiment)
    add_processes_option(experiment)
    add_arm_option(experiment, default=None, what="the scenario's; torque-control: j2n6s300")
    # which options were given (each experiment's runner takes its own: services.experiments.registry.RUNNERS)
    experiment.set_defaults(func=cmd_experiment, option_defaults={
        action.dest: action.default for action in experiment._actions if action.dest != "help"})

    demo = sub.add_parser("demo", help="for a new user: run part-a and table3 with a line per run, write the "
                                       "figures and reports, say where to look")
    demo.add_argument("--out", default="mfvs-demo", help="directory for the figures and reports (default: "
                                                         "./mfvs-demo)")
    add_jobs_option(demo)
    add_processes_option(demo)
    demo.set_defaults(func=cmd_demo)


def _add_package_commands(sub) -> None:
    """The commands their packages add themselves: ``calibrate``, ``check``, ``doctor``, the observers'
    (services.observe.cli), the console's and ``ros2``, each given the command line's own connection helpers."""
    from services.calibration.cli import add_parser as add_calibrate
    from services.commissioning.check import add_parser as add_check
    from services.commissioning.doctor import add_parser as add_doctor

    from services.console.cli import add_parser as add_console
    from services.observe.cli import add_parsers as add_observe
    from services.ros2_bridge.cli import add_parser as add_ros2

    add_calibrate(sub)
    add_check(sub, add_connection_options, operator_session)
    add_doctor(sub)
    add_observe(sub, add_connection_options, operator_session, stack_connection, service_graph)
    add_console(sub, add_connection_options, stack_connection)
    add_ros2(sub, add_connection_options, stack_connection)


def _add_operator_commands(sub) -> None:
    """``mfvs estop``, ``task``, ``authority``: what an operator tells a running stack, and who may command the
    robot."""
    estop = sub.add_parser("estop", help="engage the latched emergency stop (or --reset it)")
    estop.add_argument("--reset", action="store_true", help="release the e-stop (only an explicit reset does)")
    estop.add_argument("--operator", default="mfvs-cli", help="who is asking (logged by safety)")
    estop.add_argument("--reason", default="", help="why (logged by safety)")
    add_connection_options(estop)
    estop.set_defaults(func=cmd_estop)

    task = sub.add_parser("task", help="start, stop or show the servo task (the stack comes up idle: the arm "
                                       "moves only while a task runs)")
    task.add_argument("action", choices=["start", "stop", "status", "release", "resume"],
                      help="release: open the hand (a grasp task's hold ends in it; with no task, the hand opens "
                           "where it is); resume: go on with a task the person's stick paused, from where the arm is")
    task.add_argument("--grasp", action="store_true",
                      help="start: reach, grasp and lift (servo to the pre-grasp view, approach along the tool's "
                           "axis, close the fingers until the hand holds it, lift, hold until released)")
    task.add_argument("--operator", default="mfvs-cli", help="who is asking (logged, and kept in the task status)")
    task.add_argument("--reason", default="", help="why (logged)")
    task.add_argument("--json", action="store_true", help="print the task status as one JSON object")
    task.add_argument("--goal", default=None, metavar="FILE",
                      help="start: servo to this taught goal (mfvs teach's file; refused when its camera, "
                           "resolution or arm differ from the stack's)")
    add_connection_options(task)
    task.set_defaults(func=cmd_task)

    jog = sub.add_parser("jog", help="drive the arm with a stick in the mixed frame, as Kinova's joystick: a "
                                     "Linux gamepad (--device) or a scripted one (--script); it moves only while "
                                     "its dead-man is held, and pauses a running task")
    jog.add_argument("--script", default=None, metavar="FILE",
                     help="replay a scripted stick (YAML: rate_hz, steps of for_s, mode, axes, deadman; "
                          "services/jog/script.py)")
    jog.add_argument("--device", default=None, metavar="PATH", help="a gamepad's /dev/input/eventN (python-evdev)")
    jog.add_argument("--config", default=None, metavar="FILE",
                     help="speeds, dead band, spasm filter, the gamepad's map (default services/jog/jog.yaml's)")
    jog.add_argument("--source", default=None, metavar="jog/NAME", help="the source its requests name "
                                                                         "(default jog/stick)")
    jog.add_argument("--json", action="store_true", help="print what was sent as one JSON object")
    add_connection_options(jog)
    jog.set_defaults(func=cmd_jog)

    teach = sub.add_parser("teach", help="teach the current view as a goal (no marker): the arm moves the camera a "
                                         "few centimetres sideways and back to measure the object's depth, once "
                                         "you confirm; the goal is kept in a file")
    teach.add_argument("--name", default="taught", help="the goal's name (default taught)")
    teach.add_argument("--out", default=None, metavar="FILE",
                       help="where to keep the goal (default ./NAME.mfvsgoal)")
    teach.add_argument("--region", default=None, metavar="X0,Y0,X1,Y1",
                       help="the object's region in the image (px; default: the frame less a border)")
    teach.add_argument("--detector", default="", choices=("", "sift", "orb"),
                       help="sift (accurate; vision's default) or orb (fast)")
    teach.add_argument("--probe-cm", type=float, default=3.0,
                       help="how far the camera moves sideways to measure depth (cm, default 3)")
    teach.add_argument("--yes", action="store_true", help="do not ask before the arm moves (the way is clear)")
    teach.add_argument("--operator", default="mfvs-cli", help="who is teaching (logged)")
    add_connection_options(teach)
    teach.set_defaults(func=cmd_teach)

    authority = sub.add_parser("authority", help="write zenoh configs where only safety may command the robot")
    authority.add_argument("action", choices=["init"])
    authority.add_argument("--out", required=True, help="directory for the router/client configs and secrets")
    authority.add_argument("--tls", action="store_true", help="mutual TLS with certificates (else user/password)")
    authority.add_argument("--host", default="127.0.0.1", help="router address")
    authority.add_argument("--port", type=int, default=7447, help="router port")
    authority.add_argument("--services", help="comma-separated service identities (default: all of mfvs)")
    authority.add_argument("--ros2-domain", type=_domain_id, action="append", metavar="N",
                           help="also an identity for the lab's ROS 2 nodes (rmw_zenoh), which with the ROS 2 "
                                "bridge may use this ROS domain's keys and nothing of mfvs's (repeatable)")
    authority.set_defaults(func=cmd_authority)


def _add_bench_command(sub) -> None:
    """``mfvs bench``: a benchmark of bench/ with its own options."""
    bench = sub.add_parser("bench", help="run a benchmark and print its figures")
    bench.add_argument("name", choices=sorted(BENCHMARKS),
                       help="loops: robot_sim loop rate, jitter, lockstep speed; vision: detection time per frame; "
                       "laws: µs per control-law iteration; latency: capture → applied, per hop; "
                       "rs485: actuator bus cycle and request→reply latency; swap: iterations to converge through "
                       "robot_sim and through robot_gateway; cpu: CPU and memory per service; gateway: tracking "
                       "under load; load: the robot state's period while a flood hits an unrelated key; "
                       "soak: servo tasks back to back through random faults, and the unsafe events; console: "
                       "frames per second and capture → page delay of the console in headless Chromium; lowlevel: "
                       "the 500 Hz low-level torque loop as a client sees it (state rate, jitter, missed cycles, "
                       "watchdog, command → state); lockstep: where a lockstep iteration's wall time goes "
                       "(--identity: runs bit-identical to main's); every benchmark on an arm takes --arm NAME")
    bench.add_argument("--json", action="store_true", help="print one JSON object")
    bench.add_argument("options", nargs=argparse.REMAINDER, help="options of the benchmark itself (see --help)")
    bench.set_defaults(func=cmd_bench)


def main(argv: list[str] | None = None) -> int:
    import faulthandler

    faulthandler.enable()  # a crash in a native library (EGL, MuJoCo, zenoh) says where, on stderr
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(infrastructure_only=bool(argv) and argv[0] in INFRASTRUCTURE_COMMANDS)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return args.func(args)
    except BrokenPipeError:  # `mfvs status | head -2`: the reader left; nothing more to say, and no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except Exception as exc:
        if type(exc).__name__ != "ZError":  # zenoh's: no router where the command looked for the stack
            raise
        where = getattr(args, "connect", None) or "the stack's endpoint"
        print(f"mfvs {args.command}: cannot reach the stack's router at {where} (is the stack up? `mfvs up`, or "
              f"--connect): {str(exc).split('  at ')[0]}", file=sys.stderr)
        return 2

