"""What each ``mfvs`` command does, given its parsed arguments (:mod:`services.cli` parses them): thin, each calls
the module that does the work and prints its outcome."""
from __future__ import annotations

import argparse
import difflib
import json
import signal
import sys
import threading
from importlib.metadata import PackageNotFoundError, version

from services.cli.options import arm_or_exit, jobs_or_exit


def mfvs_version() -> str:
    try:
        return version("mfvs")
    except PackageNotFoundError:
        return "unknown (not installed)"


def cmd_router(args: argparse.Namespace) -> int:
    from services.runtime.transport import Router

    from services.runtime.pacing import request_realtime
    from services.runtime import iteration_profile
    from services.runtime.threads import wait_until_set

    iteration_profile.install("router")  # mfvs bench lockstep: the router's CPU; nothing unless it asks
    # the router carries the command path (safety to the robot): it must not wait behind the rest of the host
    request_realtime(args.realtime_priority, "router")
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    from services.runtime.config import ConfigError

    port = args.port if args.port is not None or args.config else 7447  # a config's own endpoint wins
    import zenoh

    try:
        router = Router(port=port, host=args.host, config_file=args.config).start()
    except ConfigError as exc:
        print(f"mfvs router: {exc}", file=sys.stderr)
        return 2
    except zenoh.ZError as exc:
        reason = "the port is in use (another router?): pick another with --port" if "in use" in str(exc) else exc
        print(f"mfvs router: cannot listen on {args.host}:{port}: {reason}", file=sys.stderr)
        return 1
    with router:
        print(json.dumps({"router": router.endpoint, "zid": router.zid}), flush=True)
        wait_until_set(stop)
    return 0


def cmd_bus_hub(args: argparse.Namespace) -> int:
    from services.tools.can_hub import CanHub
    from services.runtime.logs import setup_logging

    from services.runtime.pacing import request_realtime

    setup_logging("info")
    hub = CanHub(port=args.port, host=args.host)
    # the hub carries the robot's bus: it relays every 2 ms cycle between the gateway and the actuators, whose
    # loops run at realtime priority; a hub that waits behind the rest of the host would stall both
    request_realtime(args.realtime_priority, "CAN hub")
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: hub.stop())
    try:
        hub.bind()
    except OSError as exc:
        print(f"mfvs bus-hub: cannot listen on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 1
    print(json.dumps({"bus_hub": hub.channel, "interface": "mfvs_hub"}), flush=True)
    hub.serve_forever()
    print(json.dumps({"bus_hub": hub.channel, **hub.counters.snapshot()}), flush=True)
    return 0


def cmd_model(args: argparse.Namespace) -> int:
    import numpy as np

    from services.model import frames

    arm = arm_or_exit("model", args.arm)
    if arm is None:
        return 2
    if args.what == "urdf":
        sys.stdout.write(arm.urdf() + "\n")
        return 0
    if args.what == "fk":
        if args.joints_deg is None:
            print("mfvs model fk: give the joints: --joints-deg A,B,... (physical degrees, one per joint)",
                  file=sys.stderr)
            return 2
        try:
            joints = [float(v) for v in args.joints_deg.split(",")]
        except ValueError:
            print(f"mfvs model fk: --joints-deg {args.joints_deg!r} is not comma-separated numbers", file=sys.stderr)
            return 2
        if len(joints) != arm.n_joints or not all(np.isfinite(joints)):
            print(f"mfvs model fk: the {arm.name} has {arm.n_joints} joints: give {arm.n_joints} finite angles, not "
                  f"{len(joints)}", file=sys.stderr)
            return 2
        T = arm.dh_forward_kinematics(arm.physical_deg_to_model(joints))
        pose = {k: round(v, 6) for k, v in frames.kinova_pose(T[:3, :3], T[:3, 3]).items()}
        if args.json:
            print(json.dumps({"arm": arm.name, "joints_deg": joints, **pose}))
        else:
            print(f"{arm.name} at {joints} deg: X {pose['X']:.4f} Y {pose['Y']:.4f} Z {pose['Z']:.4f} m, "
                  f"ThetaX {pose['ThetaX']:.4f} ThetaY {pose['ThetaY']:.4f} ThetaZ {pose['ThetaZ']:.4f} rad")
        return 0
    T = arm.dh_forward_kinematics(arm.home)
    info = {
        "arm": arm.name,
        "title": arm.title,
        "seed": arm.seed,
        "description": str(arm.path),
        "joints": [
            {
                "name": j.name,
                "continuous": j.continuous,
                "limits_physical_deg": None if j.continuous else [j.lower_deg, j.upper_deg],
                "max_speed_dps": j.max_speed_dps,
                "peak_torque_nm": j.peak_torque_nm,
                "nominal_torque_nm": j.nominal_torque_nm,
                "actuator": j.actuator,
                "no_load_speed_dps": round(j.spec.no_load_speed_rpm * 6.0, 2),
                "gear_ratio": j.spec.gear_ratio,
                "torque_sensor_precision_nm": j.spec.torque_sensor_precision_nm,
                "bus_address": f"0x{arm.bus_addresses[i]:02X}",
                "link_mass_kg": round(j.link_mass_kg, 6),
            }
            for i, j in enumerate(arm.joints)
        ],
        "home_physical_deg": arm.home_deg.tolist(),
        "home_ee_xyz_m": np.round(T[:3, 3], 4).tolist(),
        "home_ee_euler_xyz_deg": np.round(np.degrees(frames.matrix_to_euler_xyz(T[:3, :3])), 2).tolist(),
        "reach_m": round(arm.reach, 4),
        "max_linear_speed_mps": arm.max_linear_speed_mps,
        "max_angular_speed_rps": arm.max_angular_speed_rps,
        # where the emulated arm departs from this description (robot_sim): the description file says why
        "emulation": {"link_mass_scale": arm.true_link_mass_scale.tolist(),
                      "torque_mode_friction_nm": np.round(arm.true_friction_nm, 4).tolist()},
    }
    print(json.dumps(info, indent=None if args.json else 2))
    return 0


def stack_connection(args: argparse.Namespace) -> None:
    """Fill in what the command line left open from the running stack (its run directory), as `status` does:
    the router's endpoint and the robot id; a stack on another port is then reached without saying so."""
    from services.stack.launcher import read_stack

    stack = read_stack() or {}
    args.connect = args.connect or stack.get("endpoint") or "tcp/127.0.0.1:7447"
    args.robot_id = args.robot_id or stack.get("robot_id") or "jaco"
    args.zenoh_config = args.zenoh_config or stack.get("zenoh_config")


def operator_session(args: argparse.Namespace):
    from services.runtime.transport import ZenohConfig, open_session

    stack_connection(args)
    return open_session(ZenohConfig(connect=[args.connect], config_file=args.zenoh_config))


def cmd_estop(args: argparse.Namespace) -> int:
    """Engage (or reset) the latched e-stop and report what the safety service says."""
    import time

    from protocol.keys import Keys
    from services.runtime.pacing import request_realtime
    from services.safety.estop_client import EStopClient
    from services.safety.estop_sender import ESTOP_REALTIME_PRIORITY

    # before the session, whose threads inherit it: nothing at normal priority between the e-stop's stamp and the
    # router (services/safety/estop_sender.py says why); refused, it goes out at normal priority
    request_realtime(ESTOP_REALTIME_PRIORITY, "mfvs estop")
    try:
        session = operator_session(args)
    except Exception as exc:  # the command a person reaches for in an emergency: say what failed, plainly
        print(f"e-stop NOT sent: cannot reach the router at {args.connect} ({exc}); is the stack up? "
              f"(--connect ENDPOINT, --zenoh-config FILE)", file=sys.stderr)
        return 2
    with EStopClient(session, Keys(args.robot_id)) as client:
        time.sleep(0.2)  # let the declarations reach the router
        status = client.send(args.reset, args.operator, args.reason, args.timeout)
    session.close()
    word = "reset" if args.reset else "engaged"
    if status is not None:
        print(f"e-stop {word}: safety reports state {status.state.value}")
        return 0
    print(f"e-stop {'reset' if args.reset else 'request'} sent, but no safety service confirmed it within "
          f"{args.timeout:g} s", file=sys.stderr)
    return 1


def cmd_task(args: argparse.Namespace) -> int:
    """Start, stop or show the controller's task: the stack moves the arm only while a task runs."""
    import msgspec

    from protocol import messages as m
    from protocol.keys import Keys
    from services.controller.task_client import TaskUnavailable, call_task
    from services.controller.task_client import describe_task

    try:
        session = operator_session(args)
    except Exception as exc:
        print(f"task {args.action}: cannot reach the router at {args.connect} ({exc}); is the stack up? "
              f"(--connect ENDPOINT, --zenoh-config FILE)", file=sys.stderr)
        return 2
    function = {"start": m.START_TASK, "release": m.START_TASK, "stop": m.STOP_TASK, "status": m.GET_TASK,
                "resume": m.RESUME_TASK}[args.action]
    if args.grasp and args.action != "start":
        print("task: --grasp is for task start", file=sys.stderr)
        session.close()
        return 2
    plan = m.TaskPlan.RELEASE if args.action == "release" else m.TaskPlan.GRASP if args.grasp else m.TaskPlan.SERVO
    request = None if function == m.GET_TASK else m.TaskRequest(operator=args.operator, reason=args.reason, plan=plan)
    if args.goal is not None:
        if args.action != "start":
            print("task: --goal is for task start", file=sys.stderr)
            session.close()
            return 2
        if not _give_goal(session, Keys(args.robot_id), args.goal, args.timeout):
            session.close()
            return 2
    try:
        status = call_task(session, Keys(args.robot_id), function, request, args.timeout)
    except TaskUnavailable as exc:
        print(f"task {args.action}: {exc} (is the controller up? may this identity ask it?)", file=sys.stderr)
        return 2
    finally:
        session.close()
    if args.json:
        print(json.dumps(msgspec.to_builtins(status)))
    else:
        print(describe_task(status))
    return 0 if status.ok else 1


def cmd_jog(args: argparse.Namespace) -> int:
    """Drive the arm with a stick: a scripted one (--script FILE) or a Linux gamepad (--device PATH), streamed to
    safety as jog requests (it moves the arm only while the dead-man is held; the person's stick pauses a running
    task)."""
    import threading

    from protocol.keys import Keys
    from services.jog.client import run_stick
    from services.jog.config import JogConfig
    from services.jog.evdev_input import DeviceError
    from services.jog.script import load_script
    from services.jog.sender import script_reader
    from services.runtime.config import load_config

    if (args.script is None) == (args.device is None):
        print("jog: give one of --script FILE or --device PATH", file=sys.stderr)
        return 2
    try:
        config = load_config(args.config, JogConfig)
        if args.source is not None:
            config = JogConfig(**{**{f: getattr(config, f) for f in config.__struct_fields__}, "source": args.source})
        reader = None
        if args.script is not None:
            script = load_script(args.script)
            read, rate_hz, what = script_reader(script), script.rate_hz, f"script {args.script} " \
                                                                             f"({script.duration_s:.1f} s)"
        else:
            reader, read = _device_reader(args.device, config)
            rate_hz, what = config.rate_hz, f"device {args.device}"
    except (ValueError, DeviceError) as exc:  # a bad file or source, a device that cannot be read: nothing sent
        print(f"jog: {exc}", file=sys.stderr)
        return 2
    try:
        session = operator_session(args)
    except Exception as exc:
        if reader is not None:
            reader.stop()
        print(f"jog: cannot reach the router at {args.connect} ({exc}); is the stack up? (--connect ENDPOINT, "
              "--zenoh-config FILE: the jog identity's)", file=sys.stderr)
        return 2
    stop = threading.Event()
    if not args.json:
        print(f"jog: {what} as {config.source} at {rate_hz:g} Hz (Ctrl-C stops)", file=sys.stderr)
    try:
        report, replies = run_stick(session, Keys(args.robot_id), config, read, rate_hz, stop=stop)
    except KeyboardInterrupt:
        stop.set()
        report, replies = None, []
    finally:
        session.close()
        if reader is not None:
            reader.stop()
    if report is None:
        return 130
    gone = getattr(read, "gone", "")
    summary = {"sent": report.sent, "missed_slots": report.missed, "resumes": report.resumes,
               "resume_replies": replies, "last_seq": report.last.header.seq if report.last else 0,
               "device_gone": gone}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"jog: sent {report.sent} requests, {report.missed} slots missed (a late host), {report.resumes} "
              f"resume presses{': ' + '; '.join(replies) if replies else ''}{'; ' + gone if gone else ''}")
    return 1 if gone else 0


def _device_reader(path: str, config):
    """(the device's reader thread, the stick read at each slot) for an evdev device; DeviceError when it cannot
    be read."""
    from services.jog.evdev_input import DeviceReader, open_device, stick_of
    from services.jog.sender import Reading

    device = open_device(path)
    reader = DeviceReader(device, stick_of(device, config.gamepad, config.speed_level)).start()
    heard_budget_s = 0.1  # the reader waits at most 20 ms at a time: 100 ms unheard is a thread that hangs

    def read(_t_s: float):
        with reader.lock:
            if reader.gone:
                read.gone = reader.gone
                return None  # run_stick says released once, and the stream ends
            stick = reader.stick.input()
            resume = reader.stick.take_resume()
        return Reading(stick, heard=reader.heard_within(heard_budget_s), resume=resume)

    read.gone = ""
    return reader, read


def _give_goal(session, keys, path: str, timeout_s: float) -> bool:
    """A taught goal's file to vision before the task starts; whether vision took it (it says why not, in a line)."""
    from services.vision.taught import read_goal
    from services.vision.teach_client import TeachFailed, set_taught_goal

    try:
        goal, payload = read_goal(path)
        reply = set_taught_goal(session, keys, payload, timeout_s)
    except (ValueError, TeachFailed) as exc:
        print(f"task start: {exc}", file=sys.stderr)
        return False
    if not reply.ok:
        print(f"task start: vision refused the goal: {reply.message}", file=sys.stderr)
        return False
    print(f"goal {reply.goal} ({reply.goal_digest}): {len(goal.points_camera)} keypoints, the keypoint front end")
    return True


def cmd_teach(args: argparse.Namespace) -> int:
    """Teach the current view (services/vision/teach_client.py) and keep the goal in a file."""
    from pathlib import Path

    from protocol.keys import Keys
    from services.vision.teach_client import TeachFailed, teach

    region = ()
    if args.region is not None:
        try:
            x0, y0, x1, y1 = (float(v) for v in args.region.split(","))
        except ValueError:
            print("teach: --region takes X0,Y0,X1,Y1 (px)", file=sys.stderr)
            return 2
        region = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    if not 0.5 <= args.probe_cm <= 10.0:
        print("teach: --probe-cm must be within 0.5..10", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path(f"{args.name}.mfvsgoal")

    def confirm(question: str) -> bool:
        if args.yes:
            return True
        if not sys.stdin.isatty():
            print(f"teach: {question} (answer on a terminal, or give --yes)", file=sys.stderr)
            return False
        return input(f"{question} [y/N] ").strip().lower() in ("y", "yes")

    try:
        session = operator_session(args)
    except Exception as exc:
        print(f"teach: cannot reach the router at {args.connect} ({exc}); is the stack up?", file=sys.stderr)
        return 2
    try:
        result = teach(session, Keys(args.robot_id), args.name, args.operator, region_px=region,
                       probe_m=(args.probe_cm / 100.0, 0.0, 0.0), detector=args.detector, confirm=confirm,
                       say=lambda line: print(f"  {line}", flush=True))
    except TeachFailed as exc:
        print(f"teach: {exc}", file=sys.stderr)
        return 1
    finally:
        session.close()
    from services.vision.taught import decode_goal, write_goal

    write_goal(decode_goal(result.file).file, out)
    print(f"taught {result.goal} ({result.digest}): {result.keypoints} keypoints, "
          f"{'planar' if result.planar else 'not planar'}, kept in {out}; vision servos to it at `mfvs task start` "
          f"(again later: mfvs task start --goal {out})")
    return 0


def cmd_authority(args: argparse.Namespace) -> int:
    from services.runtime.authority import DEFAULT_SERVICES, write_deployment

    services = args.services.split(",") if args.services else list(DEFAULT_SERVICES)
    deployment = write_deployment(args.out, tls=args.tls, host=args.host, port=args.port, services=services,
                                  ros2_domains=args.ros2_domain or ())
    print(json.dumps({"router_config": str(deployment.router_config), "endpoint": deployment.endpoint,
                      "clients": {k: str(v) for k, v in deployment.client_configs.items()}, "tls": deployment.tls},
                     indent=2))
    return 0


def cmd_servo(args: argparse.Namespace) -> int:
    from pathlib import Path

    from services.runtime.config import ConfigError
    from services.servo.run import run
    from services.servo.scenario import load_scenario, on_arm

    try:
        scenario = on_arm(load_scenario(args.scenario), args.arm, args.scenario)
    except (ConfigError, ValueError) as exc:
        print(f"mfvs servo: {exc}", file=sys.stderr)
        return 2
    if args.profile not in ("sim", "gateway"):
        print(f"mfvs servo: unknown profile {args.profile!r}: sim or gateway", file=sys.stderr)
        return 2
    if args.bus != "hub" and args.profile != "gateway":
        print(f"mfvs servo: --bus {args.bus} is the gateway profile's (--profile gateway)", file=sys.stderr)
        return 2

    def progress(record) -> None:
        if not args.json:
            print(f"iteration {record.iteration:4d}  {record.status:12s}  ‖e‖ = {record.error_norm:.3e}", flush=True)

    result = run(scenario, Path(args.out) if args.out else None, progress, profile=args.profile,
                 record=Path(args.record) if args.record else None, processes=args.processes, bus=args.bus)
    if args.json:
        print(json.dumps(result.to_json()), flush=True)
    else:
        final = "none (no tag)" if result.final_error_norm is None else f"{result.final_error_norm:.3e}"
        print(f"{result.status}: {result.iterations} iterations, final ‖e‖ = {final}, "
              f"max speed {result.max_linear_speed_mps:.3f} m/s, min manipulability {result.min_manipulability:.4f}")
        if result.detail:
            print(result.detail)
        if result.trajectory_log:
            print(f"log: {result.trajectory_log}; plots: {', '.join(result.plots)}")
        if args.record:
            print(f"recording: {args.record} (mfvs replay {args.record}; open it in Foxglove)")
    return 0 if result.converged else 1


def _experiment_progress(name: str, quiet: bool):
    """After each run a line (on stderr with --json); during the runs, on a terminal, one progress line, the run
    it shows the last to report (runs side by side take turns on it). Its ``on_iteration`` is None when no line
    would show: the runs then send their iterations nowhere (with ``--jobs`` each went from its worker to this
    process, an iteration at a time)."""
    from services.runtime.progress import ProgressLine, shows
    from services.servo.result import error_rms

    bars: dict = {}
    ended: set = set()
    shown: list = []

    def on_iteration(label: str, scenario, record) -> None:
        if label in ended:  # a record still on its way from a run that has ended
            return
        if label not in bars:
            bars[label] = ProgressLine(f"{name} {label}", scenario.convergence.rms,
                                       scenario.convergence.max_iterations, enabled=not quiet)
        bars[label].update(record.iteration, error_rms(record))
        shown[:] = [bars[label]]

    def progress(label: str, result) -> None:
        ended.add(label)
        bars.pop(label, None)
        if shown:
            shown.pop().done()
        final = "–" if result.final_error_norm is None else f"{result.final_error_norm:.2e}"
        print(f"  {name} {label:22s} {result.status:14s} {result.iterations:5d} iterations  final ‖e‖ {final}  "
              f"({result.wall_time_s:.0f} s)", file=sys.stderr if quiet else sys.stdout, flush=True)
    progress.on_iteration = on_iteration if shows(not quiet) else None
    return progress


def _print_experiment(output: dict) -> None:
    print(f"{output['title']} ({output['experiment']}; paper: {output['paper']})")
    for row in output["runs"]:
        final = "–" if row["final_error_norm"] is None else f"{row['final_error_norm']:.2e}"
        extra = f"  failure: {row['failure']}" if row["failure"] else ""
        print(f"  {row['label']:22s} {row['status']:14s} {row['iterations']:5d} iterations  final ‖e‖ {final}{extra}")
    print("summary: " + json.dumps(output["summary"]))
    if not output["repeatable"]:
        print("not repeatable: the arm went on without the pipeline's answer at some ticks (a loaded host); "
              "a rerun may differ")
    if output["report"]:
        print(f"report: {output['report']}")


def _uses_warm_server(jobs: int, processes: bool, profile: str = "sim") -> bool:
    """Whether a command's lockstep runs fork from the warm server (:mod:`services.stack.warm_start`): runs side by side
    are its forks (:mod:`services.experiments.pool`), and so are the services of a stack of processes; a composed run
    alone needs none."""
    return jobs > 1 or processes or profile != "sim"


def cmd_experiment(args: argparse.Namespace) -> int:
    if _uses_warm_server(args.jobs, args.processes, args.profile):  # started now, its imports beside ours
        from services.stack.warm_start import start_server

        start_server()
    from services.experiments.registry import RUNNERS, experiment_names, options_taken

    if args.name not in experiment_names():
        close = difflib.get_close_matches(args.name, experiment_names(), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        print(f"mfvs experiment: unknown experiment {args.name!r}{hint}; known: {', '.join(experiment_names())}",
              file=sys.stderr)
        return 2
    if args.profile not in ("sim", "gateway"):
        print(f"mfvs experiment: unknown profile {args.profile!r}: sim or gateway", file=sys.stderr)
        return 2
    runner = RUNNERS[args.name]
    for option in EXPERIMENT_OPTIONS:
        if option not in runner.options and getattr(args, option) != args.option_defaults[option]:
            flag = "--" + option.replace("_", "-")
            takers = options_taken(option)
            print(f"mfvs experiment: {args.name} takes no {flag} ({flag} is for {', '.join(takers) or 'none'})",
                  file=sys.stderr)
            return 2
    return runner.function()(args)


#: the options of ``mfvs experiment`` that some experiments take and others not (each runner declares its own:
#: services.experiments.registry.RUNNERS)
EXPERIMENT_OPTIONS = ("scenario", "random_starts", "seed", "quick", "runs", "jobs", "processes", "object", "texture",
                      "perturb", "placements")


def servo_experiment(args: argparse.Namespace) -> int:
    """``mfvs experiment NAME`` for a servo comparison: its runs from its start (or ``--scenario``'s), or from
    random starts."""
    from services.experiments.registry import run_experiment
    from services.runtime.config import ConfigError

    if not jobs_or_exit("experiment", args.jobs):
        return 2
    if args.random_starts is not None:
        return _random_starts_experiment(args)
    try:
        progress = _experiment_progress(args.name, args.json)
        output = run_experiment(args.name, args.scenario, args.out, progress, profile=args.profile,
                                on_iteration=progress.on_iteration, arm=args.arm, jobs=args.jobs,
                                processes=args.processes)
    except ConfigError as exc:
        print(f"mfvs experiment: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(output), flush=True)
    else:
        _print_experiment(output)
    return 0


def markerless_experiment(args: argparse.Namespace) -> int:
    """``mfvs experiment markerless``: teach by showing at the goal, then servo from random starts
    (services.experiments.markerless)."""
    from pathlib import Path

    from services.experiments.markerless import run_markerless
    from services.runtime.config import ConfigError

    if not jobs_or_exit("experiment", args.jobs):
        return 2
    if args.arm is not None and arm_or_exit("experiment", args.arm) is None:
        return 2
    perturb = tuple(p for group in (args.perturb or []) for p in group.split(",") if p)
    count = args.random_starts if args.random_starts is not None else 20
    stream = sys.stderr if args.json else sys.stdout

    def progress(label: str, row: dict) -> None:
        mm, deg = row.get("final_position_error_mm"), row.get("final_rotation_error_deg")
        extra = f"  {mm} mm {deg}°" if mm is not None else f"  {row.get('failure') or ''}"
        swap = f"  held {row['held']}, {row['travel_after_swap_mm']} mm after the swap" if "held" in row else ""
        print(f"  {label:8s} {row['status']:14s} {row['iterations']:5d} iterations (tag "
              f"{row.get('tag', {}).get('iterations', '–')}){extra}{swap}", file=stream, flush=True)

    try:
        output = run_markerless(args.object or "plane", args.texture, count, args.seed, args.arm, perturb, args.out,
                                args.jobs, progress, Path(args.scenario) if args.scenario else None)
    except (ConfigError, ValueError) as exc:
        print(f"mfvs experiment: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(output), flush=True)
        return 0
    s = output["summary"]
    print(f"{output['title']}: succeeded on {s['succeeded']}/{s['starts']} (Wilson 95 % {s['wilson_95']}); final "
          f"error median {s['final_position_error_mm']['median']} mm, {s['final_rotation_error_deg']['median']}°; "
          f"iterations over the tag's, median {s['iterations_over_tag']['median']}")
    if output["report"]:
        print(f"report: {output['report']}")
    return 0


def grasp_experiment(args: argparse.Namespace) -> int:
    """``mfvs experiment grasp``: reach, grasp and lift an object from seeded placements on the table
    (services.experiments.grasp)."""
    from services.experiments import grasp
    from services.runtime.config import ConfigError
    from services.servo.scenario import load_scenario

    if not jobs_or_exit("experiment", args.jobs):
        return 2
    if args.arm is not None and arm_or_exit("experiment", args.arm) is None:
        return 2
    kind = args.object or "cup"
    perturb = [p for group in (args.perturb or []) for p in group.split(",") if p]
    problems = []
    if kind not in grasp.OBJECTS:
        problems.append(f"grasp takes --object {', '.join(grasp.OBJECTS)}, not {kind}")
    if len(perturb) > 1 or any(p not in grasp.PERTURBATIONS for p in perturb):
        problems.append(f"grasp takes one --perturb of {', '.join(grasp.PERTURBATIONS)}")
    count = args.placements if args.placements is not None else 10
    if count < 1:
        problems.append("--placements must be at least 1")
    if problems:
        print(f"mfvs experiment: {'; '.join(problems)}", file=sys.stderr)
        return 2
    stream = sys.stderr if args.json else sys.stdout

    def progress(row: dict) -> None:
        print(f"  {row['label']:12s} {row.get('status', ''):8s} verdict {row.get('verdict')}  lifted "
              f"{row.get('lifted_m')} m  slip {row.get('slip_mm')} mm  dropped {row.get('dropped')}"
              f"{'  ' + row['failure'] if row.get('failure') else ''}", file=stream, flush=True)

    try:
        base = load_scenario(args.scenario) if args.scenario else None
        output = grasp.run(args.arm, kind, count, args.seed, perturb[0] if perturb else None, args.jobs, args.out,
                           base, progress)
    except (ConfigError, ValueError) as exc:
        print(f"mfvs experiment: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(output), flush=True)
        return 0
    print(f"grasp ({output['arm']}, {kind}{', ' + output['perturb'] if output['perturb'] else ''}): "
          f"{json.dumps(output['summary'])}")
    return 0


def torque_experiment(args: argparse.Namespace) -> int:
    """``mfvs experiment torque-control``: the JACO thesis's chapter 5 in realtime
    (services.experiments.torque_control), every run from the arm's home."""
    from services.experiments.torque_control import run_torque_control

    if args.arm is not None and arm_or_exit("experiment", args.arm) is None:
        return 2
    labels = None
    if args.runs is not None:
        from services.model.arm import load_arm
        from services.experiments.torque_control import THESIS_ARM, runs_for

        known = [spec.label for spec in runs_for(load_arm(args.arm or THESIS_ARM), args.quick)]
        labels = [label.strip() for label in args.runs.split(",") if label.strip()]
        unknown = [label for label in labels if label not in known]
        if unknown or not labels:
            print(f"mfvs experiment: torque-control{' --quick' if args.quick else ''} has no run "
                  f"{', '.join(map(repr, unknown)) or 'named'}; its runs: {', '.join(known)}", file=sys.stderr)
            return 2
    stream = sys.stderr if args.json else sys.stdout

    def progress(row: dict) -> None:
        if row["status"] == "failed":
            print(f"  {row['label']:26s} failed: {row['failure']}", file=stream, flush=True)
            return
        p, o = row["position_mm"], row["orientation_deg"]
        print(f"  {row['label']:26s} {row['status']:9s} position RMS/max/final {p['rms']:.2f}/{p['max']:.2f}/"
              f"{p['final']:.2f} mm  orientation {o['rms']:.2f}/{o['max']:.2f}/{o['final']:.2f}°  saturated "
              f"{row['saturation_s']:.2f} s  missed {row['missed_cycles']}/{row['timing']['answered']}  safety stops "
              f"{row['safety_stops'] if row['safety_stops'] is not None else '?'}"
              + ("" if row["host_kept_time"] else "  (this host did not keep the loop's time)"),
              file=stream, flush=True)

    print(f"torque-control on the {args.arm or 'j2n6s300'} ({args.profile} profile, realtime; about "
          f"{'30 s' if args.quick else '4 min'})", file=stream, flush=True)
    output = run_torque_control(args.arm, args.out, args.profile, quick=args.quick, progress=progress,
                                labels=labels)
    if args.json:
        print(json.dumps(output), flush=True)
        return 0
    for obs in output["summary"]["observations"]:
        print(f"  [{obs['verdict']}] {obs['thesis']}: {obs['measured']}")
    target = output["summary"]["target"]
    if not target["reachable"]:
        print(f"  Xf is not reachable: the nearest pose is {target['nearest']['position_mm']} mm and "
              f"{target['nearest']['orientation_deg']}° away")
    if output["report"]:
        print(f"report: {output['report']}")
    return 0


def _random_starts_experiment(args: argparse.Namespace) -> int:
    from pathlib import Path

    from services.experiments.random_starts import run_random_starts
    from services.runtime.config import ConfigError

    if args.random_starts < 1:
        print("mfvs experiment: --random-starts needs at least 1 start", file=sys.stderr)
        return 2
    # the starts are written where they can be run again: beside the results, or in the working directory
    starts_dir = (Path(args.out) / "starts" if args.out
                  else Path("mfvs-random-starts") / f"{args.name}-{args.arm or 'scenario'}-seed{args.seed}")
    progress = _experiment_progress(args.name, args.json)
    try:
        output = run_random_starts(args.name, args.random_starts, args.seed, args.scenario, args.out, starts_dir,
                                   progress, profile=args.profile, on_iteration=progress.on_iteration, arm=args.arm,
                                   jobs=args.jobs, processes=args.processes)
    except (ConfigError, ValueError) as exc:
        print(f"mfvs experiment: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(output), flush=True)
        return 0
    summary = output["summary"]
    print(f"{output['title']} (starts in {output['random_starts']['scenarios']})")
    for law, figures in summary["laws"].items():
        it = figures["iterations"]
        quart = "–" if it["median"] is None else f"{it['q1']:.0f} / {it['median']:.0f} / {it['q3']:.0f}"
        print(f"  {law:22s} converged {figures['converged']}/{summary['starts']}  iterations q1/median/q3 {quart}"
              f"  (paper {figures['paper_iterations']})" + (f"  failures {figures['failures']}"
                                                            if figures["failures"] else ""))
    print(f"in the paper's order on {summary['fraction_in_paper_order']:.0%} of the starts; the mixed law "
          f"≥ {summary['clearly_faster_pct']:g} % faster than adaptive-pd-joint on "
          f"{summary['fraction_clearly_faster']:.0%}, median improvement {summary['median_improvement_pct']} % "
          f"(paper {summary['paper_improvement_pct']} %), mixed failures {summary['proposed_failures']}")
    for entry in summary["not_clearly_faster"]:
        print(f"  start {entry['index']}: improvement {entry['improvement_pct']} %; shaped by {entry['shaped_by']}")
    if output["report"]:
        print(f"report: {output['report']}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from pathlib import Path

    from services.stack.warm_start import start_server

    if not jobs_or_exit("demo", args.jobs):
        return 2
    if _uses_warm_server(args.jobs, args.processes):
        start_server()  # started now, its imports beside ours
    from services.experiments.registry import run_experiments

    out = Path(args.out).resolve()
    print(f"mfvs demo: Sensors 2022's Part A and Table 3 on the emulated JACO-2 (MuJoCo, the real services, lockstep, "
          f"{args.jobs} run{'s' if args.jobs > 1 else ''} at a time); figures and reports go to {out}", flush=True)
    progress = _experiment_progress("demo", False)
    # Table 3's runs first, the longest first: the pool then ends together
    outputs = dict(zip(("table3", "part-a"), run_experiments(["table3", "part-a"], out, progress,
                                                             on_iteration=progress.on_iteration, jobs=args.jobs,
                                                             processes=args.processes)))
    reports = []
    for name in ("part-a", "table3"):
        print(f"{name}:", flush=True)
        _print_experiment(outputs[name])
        reports.append(outputs[name]["report"])
    print(f"\ndone. Open {reports[0]} and {reports[1]} (figures beside them: errors.png, features.png and each "
          f"run's own folder).")
    return 0


def cmd_up(args: argparse.Namespace) -> int:
    from services.runtime.config import ConfigError
    from services.stack.launcher import load_profile, up, with_arm, with_bus_period, with_ros2

    try:
        profile = load_profile(args.profile, args.port, args.bus_port)
    except ConfigError as exc:
        print(f"mfvs up: {exc}", file=sys.stderr)
        return 2
    if args.arm is not None:
        if arm_or_exit("up", args.arm) is None:
            return 2
        profile = with_arm(profile, args.arm)
    if args.bus_period is not None:
        try:
            profile = with_bus_period(profile, args.bus_period)
        except ValueError as exc:
            print(f"mfvs up: {exc}", file=sys.stderr)
            return 2
    if args.ros2:
        from services.ros2_bridge.cli import default_domain

        try:
            profile = with_ros2(profile, default_domain())
        except ValueError as exc:
            print(f"mfvs up: {exc}", file=sys.stderr)
            return 2
    code, message = up(profile, args.clock, args.wait, args.host)
    print(message, file=sys.stderr if code else sys.stdout)
    return code


def cmd_down(args: argparse.Namespace) -> int:
    from services.stack.launcher import down

    code, message = down()
    print(message)
    return code


def _restarts(entry: dict) -> str:
    if not entry.get("restarts"):
        return ""
    return f"  restarted {entry['restarts']}× (last {entry['restarted_ago_s']:.0f} s ago)"


def cmd_restart(args: argparse.Namespace) -> int:
    from services.stack.launcher import restart

    code, message = restart(args.name)
    print(message, file=sys.stderr if code else sys.stdout)
    return code


def cmd_status(args: argparse.Namespace) -> int:
    from protocol.keys import ROBOT_SERVICES

    from services.stack.launcher import read_stack, status_json

    stack = read_stack()
    endpoint = args.connect or (stack["endpoint"] if stack else "tcp/127.0.0.1:7447")
    robot_id = args.robot_id or (stack["robot_id"] if stack else "jaco")
    report = status_json(endpoint, robot_id, args.zenoh_config or (stack or {}).get("zenoh_config"))
    if args.json:
        print(json.dumps(report))
    else:
        router = report["router"]
        print(f"router {router['endpoint']}: {'reachable' if router['reachable'] else 'NOT reachable'}"
              f"{_restarts(router)}")
        for s in report["services"]:
            rates = ", ".join(f"{k} {v:.1f} Hz" for k, v in sorted(s["rates_hz"].items()))
            errors = ", ".join(f"{k} {v}" for k, v in sorted(s["errors"].items())) or "no errors"
            condition = s["condition"].upper() if s["condition"] != "healthy" else "healthy"
            why = f" ({'; '.join(s['degraded'])})" if s["degraded"] else ""
            print(f"  {s['name']:12s} pid {s['pid']}  {condition}{why}{_restarts(s)}  {rates}; {errors}")
            if s["name"] in ("safety", "controller") or s["condition"] in ("dead", "not responding"):
                print(f"  {'':12s} {s['detail']}")  # the e-stop, the task's state, or how it ended
            elif s["name"] in ROBOT_SERVICES and s["detail"].startswith("arm "):
                print(f"  {'':12s} {s['detail'].split(';')[0]}")  # the arm, and what drives its joints
    return 0 if report["router"]["reachable"] else 1


BENCHMARKS = {"loops": "bench.loops", "vision": "bench.vision", "laws": "bench.laws", "latency": "bench.latency",
              "rs485": "bench.rs485", "swap": "bench.swap", "cpu": "bench.cpu", "gateway": "bench.gateway",
              "load": "bench.load", "soak": "bench.soak", "console": "bench.console", "lowlevel": "bench.lowlevel",
              "lockstep": "bench.lockstep"}


def cmd_bench(args: argparse.Namespace) -> int:
    import importlib

    module = importlib.import_module(BENCHMARKS[args.name])
    return module.main((["--json"] if args.json else []) + args.options)


#: every service's module: each declares its ports on its service classes (services.runtime.ports)
SERVICE_MODULES = ("services.vision.service", "services.controller.service", "services.safety.service",
                   "services.camera.service", "services.console.service", "services.torque_controller.service",
                   "services.robot_sim.service", "services.robot_gateway.service", "services.ros2_bridge.service")


def service_classes() -> list:
    """Every service class of the stack (a robot service's, robot_sim's or robot_gateway's, may be several)."""
    import importlib

    from services.runtime.service import Service

    for module in SERVICE_MODULES:
        importlib.import_module(module)
    found, todo = [], list(Service.__subclasses__())
    while todo:
        cls = todo.pop()
        todo.extend(cls.__subclasses__())
        if cls.__module__ in SERVICE_MODULES:
            found.append(cls)
    return sorted(found, key=lambda c: (c.__module__, c.__name__))


def service_graph() -> list[str]:
    """``mfvs keys --graph``: a line per topic, ``publishers --key (Type)--> subscribers``, as the services declare
    them (a topic no service publishes: who does, from protocol/topics.py)."""
    from protocol.keys import Keys
    from protocol.topics import topics
    from services.runtime.ports import graph

    keys = Keys()
    declared: dict = {}
    for cls in service_classes():
        declared[cls.name] = declared[cls.name] | cls.PORTS if cls.name in declared else cls.PORTS
    outside = {t.key: t.publisher for t in topics(keys)}
    lines = []
    for key, type_name, publishers, subscribers in graph(declared, keys):
        who = ", ".join(publishers) or f"({outside.get(key, 'nobody')})"
        lines.append(f"{who} --{key.removeprefix(keys.prefix + '/')} ({type_name})--> {', '.join(subscribers) or '-'}")
    lines.append("every service --health/<name> (ServiceHealth)--> mfvs status, the console; in lockstep each "
                 "follows sim/clock")
    return lines

