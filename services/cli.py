"""The ``mfvs`` command line (docs/contracts.md lists the commands that are stable; the rest change with their
issues)."""
from __future__ import annotations

import argparse
import difflib
import json
import os
import re
import signal
import sys
import threading
from importlib.metadata import PackageNotFoundError, version
from typing import Optional


def _version() -> str:
    try:
        return version("mfvs")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _cmd_router(args: argparse.Namespace) -> int:
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


def _cmd_bus_hub(args: argparse.Namespace) -> int:
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


def arm_or_exit(command: str, name: str):
    """The arm description ``name``, or (None, after one line on stderr: ``mfvs <command>: ...``) when there is none
    of that name: every command's ``--arm``, the benchmarks' too, checked before anything starts."""
    from services.model.arm import ArmError, load_arm

    try:
        return load_arm(name)
    except ArmError as exc:
        print(f"mfvs {command}: {exc}", file=sys.stderr)
        return None


def add_arm_option(parser, default: Optional[str] = "default", what: str = "") -> None:
    """``--arm NAME``: the arm description a command runs with (one setting for a whole stack); ``default``: the
    default arm unless given (None: what the command's input says, ``what``)."""
    from services.model.arm import DEFAULT_ARM, arm_names

    default = DEFAULT_ARM if default == "default" else default
    parser.add_argument("--arm", default=default, metavar="NAME",
                        help=f"the arm: {', '.join(arm_names())} (default {default or what})")


def _cmd_model(args: argparse.Namespace) -> int:
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


def _stack_connection(args: argparse.Namespace) -> None:
    """Fill in what the command line left open from the running stack (its run directory), as `status` does:
    the router's endpoint and the robot id; a stack on another port is then reached without saying so."""
    from services.launcher import read_stack

    stack = read_stack() or {}
    args.connect = args.connect or stack.get("endpoint") or "tcp/127.0.0.1:7447"
    args.robot_id = args.robot_id or stack.get("robot_id") or "jaco"
    args.zenoh_config = args.zenoh_config or stack.get("zenoh_config")


def _operator_session(args: argparse.Namespace):
    from services.runtime.transport import ZenohConfig, open_session

    _stack_connection(args)
    return open_session(ZenohConfig(connect=[args.connect], config_file=args.zenoh_config))


def _cmd_estop(args: argparse.Namespace) -> int:
    """Engage (or reset) the latched e-stop and report what the safety service says."""
    import time

    from protocol.keys import Keys
    from services.safety.estop_client import EStopClient

    try:
        session = _operator_session(args)
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


def _cmd_task(args: argparse.Namespace) -> int:
    """Start, stop or show the controller's task: the stack moves the arm only while a task runs."""
    import msgspec

    from protocol import messages as m
    from protocol.keys import Keys
    from services.controller.task_client import TaskUnavailable, call_task
    from services.controller.task_client import describe_task

    try:
        session = _operator_session(args)
    except Exception as exc:
        print(f"task {args.action}: cannot reach the router at {args.connect} ({exc}); is the stack up? "
              f"(--connect ENDPOINT, --zenoh-config FILE)", file=sys.stderr)
        return 2
    function = {"start": m.START_TASK, "stop": m.STOP_TASK, "status": m.GET_TASK}[args.action]
    request = None if function == m.GET_TASK else m.TaskRequest(operator=args.operator, reason=args.reason)
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


def _cmd_authority(args: argparse.Namespace) -> int:
    from services.runtime.authority import DEFAULT_SERVICES, write_deployment

    services = args.services.split(",") if args.services else list(DEFAULT_SERVICES)
    deployment = write_deployment(args.out, tls=args.tls, host=args.host, port=args.port, services=services)
    print(json.dumps({"router_config": str(deployment.router_config), "endpoint": deployment.endpoint,
                      "clients": {k: str(v) for k, v in deployment.client_configs.items()}, "tls": deployment.tls},
                     indent=2))
    return 0


def _cmd_servo(args: argparse.Namespace) -> int:
    from pathlib import Path

    from services.runtime.config import ConfigError
    from services.servo import load_scenario, on_arm, run

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


def add_processes_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--processes", action="store_true",
                        help="in lockstep with the sim profile, every service a process of its own with a router, as "
                             "deployed (the same numbers, slower); by default they run composed in the runner's "
                             "process, on one zenoh session")


def add_jobs_option(parser: argparse.ArgumentParser) -> None:
    from services.run_pool import default_jobs

    parser.add_argument("--jobs", type=int, default=default_jobs(), metavar="N",
                        help=f"lockstep runs side by side, each on a stack and a core of its own (default: the "
                             f"cores, {default_jobs()} here); every run gives the same numbers however many run "
                             "beside it (torque-control runs in realtime, one controller at a time, and takes none)")


def _jobs_or_exit(command: str, jobs: int) -> bool:
    from services.run_pool import check_jobs

    try:
        check_jobs(jobs)
    except ValueError as exc:
        print(f"mfvs {command}: {exc}", file=sys.stderr)
        return False
    return True


def _experiment_progress(name: str, quiet: bool):
    """After each run a line (on stderr with --json); during the runs, on a terminal, one progress line, the run
    it shows the last to report (runs side by side take turns on it). Its ``on_iteration`` is None when no line
    would show: the runs then send their iterations nowhere (with ``--jobs`` each went from its worker to this
    process, an iteration at a time)."""
    from services.runtime.progress import ProgressLine, shows

    bars: dict = {}
    ended: set = set()
    shown: list = []

    def on_iteration(label: str, scenario, record) -> None:
        if label in ended:  # a record still on its way from a run that has ended
            return
        if label not in bars:
            bars[label] = ProgressLine(f"{name} {label}", scenario.convergence.error_norm,
                                       scenario.convergence.max_iterations, enabled=not quiet)
        bars[label].update(record.iteration, record.error_norm)
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
    """Whether a command's lockstep runs fork from the warm server (:mod:`services.warm_start`): runs side by side
    are its forks (:mod:`services.run_pool`), and so are the services of a stack of processes; a composed run alone
    needs none."""
    return jobs > 1 or processes or profile != "sim"


def _cmd_experiment(args: argparse.Namespace) -> int:
    if _uses_warm_server(args.jobs, args.processes, args.profile):  # started now, its imports beside ours
        from services.warm_start import start_server

        start_server()
    from services.experiments import EXPERIMENTS, experiment_names, run_experiment
    from services.runtime.config import ConfigError

    if args.name not in experiment_names():
        close = difflib.get_close_matches(args.name, experiment_names(), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        print(f"mfvs experiment: unknown experiment {args.name!r}{hint}; known: {', '.join(experiment_names())}",
              file=sys.stderr)
        return 2
    if args.profile not in ("sim", "gateway"):
        print(f"mfvs experiment: unknown profile {args.profile!r}: sim or gateway", file=sys.stderr)
        return 2
    if args.name not in EXPERIMENTS:
        return _torque_experiment(args)
    if args.quick:
        print(f"mfvs experiment: --quick is torque-control's, not {args.name}'s", file=sys.stderr)
        return 2
    if not _jobs_or_exit("experiment", args.jobs):
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


def _torque_experiment(args: argparse.Namespace) -> int:
    """``mfvs experiment torque-control``: the JACO thesis's chapter 5 in realtime (services.torque_experiment)."""
    from services.torque_experiment import run_torque_control

    for flag, given in (("--scenario", args.scenario is not None), ("--random-starts", args.random_starts is not None)):
        if given:
            print(f"mfvs experiment: torque-control takes no {flag} (it starts every run from the arm's home)",
                  file=sys.stderr)
            return 2
    if args.arm is not None and arm_or_exit("experiment", args.arm) is None:
        return 2
    labels = None
    if args.runs is not None:
        from services.model.arm import load_arm
        from services.torque_experiment import THESIS_ARM, runs_for

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

    from services.experiments import RANDOM_START_EXPERIMENTS, run_random_starts
    from services.runtime.config import ConfigError

    if args.name not in RANDOM_START_EXPERIMENTS:
        print(f"mfvs experiment: --random-starts runs {', '.join(RANDOM_START_EXPERIMENTS)}, not {args.name}",
              file=sys.stderr)
        return 2
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


def _cmd_demo(args: argparse.Namespace) -> int:
    from pathlib import Path

    from services.warm_start import start_server

    if not _jobs_or_exit("demo", args.jobs):
        return 2
    if _uses_warm_server(args.jobs, args.processes):
        start_server()  # started now, its imports beside ours
    from services.experiments import run_experiments

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


def _cmd_up(args: argparse.Namespace) -> int:
    from services.runtime.config import ConfigError
    from services.launcher import load_profile, up, with_arm, with_bus_period

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
    code, message = up(profile, args.clock, args.wait, args.host)
    print(message, file=sys.stderr if code else sys.stdout)
    return code


def _cmd_down(args: argparse.Namespace) -> int:
    from services.launcher import down

    code, message = down()
    print(message)
    return code


def _restarts(entry: dict) -> str:
    if not entry.get("restarts"):
        return ""
    return f"  restarted {entry['restarts']}× (last {entry['restarted_ago_s']:.0f} s ago)"


def _cmd_restart(args: argparse.Namespace) -> int:
    from services.launcher import restart

    code, message = restart(args.name)
    print(message, file=sys.stderr if code else sys.stdout)
    return code


def _cmd_status(args: argparse.Namespace) -> int:
    from protocol.keys import ROBOT_SERVICES

    from services.launcher import read_stack, status_json

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


def _cmd_bench(args: argparse.Namespace) -> int:
    import importlib

    module = importlib.import_module(BENCHMARKS[args.name])
    return module.main((["--json"] if args.json else []) + args.options)


def _add_connection_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--connect", default=None, help="zenoh router endpoint (default: the running stack's)")
    parser.add_argument("--zenoh-config", default=None, help="zenoh client config (credentials, certificates)")
    parser.add_argument("--robot-id", default=None, help="robot id (keys under mfvs/<robot_id>/; default: the "
                        "running stack's)")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for confirmation")


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
    parser.add_argument("--version", action="version", version=f"mfvs {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    router = sub.add_parser("router", help="run a zenoh router in the foreground until SIGTERM/SIGINT")
    router.add_argument("--port", type=int, default=None,
                        help="TCP port to listen on (0: a free one; default: the --config file's listen endpoint, "
                             "else 7447); a port that conflicts with the file's is an error")
    router.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    router.add_argument("--config", default=None, help="zenoh JSON5 config file (access control, TLS)")
    router.add_argument("--realtime-priority", type=int, default=30, metavar="N",
                        help="SCHED_FIFO priority where the OS grants it: the router carries safety's commands to "
                             "the robot (0: normal scheduling)")
    router.set_defaults(func=_cmd_router)

    hub = sub.add_parser("bus-hub", help="run the loopback CAN hub that carries RS-485 frames between robot_sim's "
                         "emulated actuators and robot_gateway (python-can interface mfvs_hub)")
    hub.add_argument("--port", type=int, default=7448, help="TCP port to listen on (default 7448)")
    hub.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    hub.add_argument("--realtime-priority", type=int, default=40, metavar="N",
                     help="SCHED_FIFO priority where the OS grants it, as the robot's loops (0: normal scheduling)")
    hub.set_defaults(func=_cmd_bus_hub)
    if infrastructure_only:
        return parser

    model = sub.add_parser("model", help="an arm's description (j2s7s300: Sensors 2022's 7-DoF; j2n6s300: the JACO "
                                         "thesis's 6-DoF): its joints, limits, home, URDF and forward kinematics")
    model.add_argument("what", choices=["urdf", "info", "fk"],
                       help="urdf: print the URDF; info: joints, limits, home pose; fk: the end effector's pose")
    add_arm_option(model)
    model.add_argument("--joints-deg", default=None, metavar="A,B,...",
                       help="fk: physical joint angles (deg, as GetAngularPosition), one per joint")
    model.add_argument("--json", action="store_true", help="one JSON object (info, fk)")
    model.set_defaults(func=_cmd_model)

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
    up_cmd.add_argument("--host", default=None,
                        help="in a profile across computers (deploy/profiles/multi-host.yaml), which one this is: "
                             "start only its part")
    up_cmd.set_defaults(func=_cmd_up)
    down_cmd = sub.add_parser("down", help="stop the stack `mfvs up` started")
    down_cmd.set_defaults(func=_cmd_down)
    restart_cmd = sub.add_parser("restart", help="restart one process of the stack `mfvs up` started (a service, "
                                 "the router) with its command line, as its systemd unit would")
    restart_cmd.add_argument("name", help="the process's name in `mfvs status` (vision, safety, router, ...)")
    restart_cmd.set_defaults(func=_cmd_restart)
    status_cmd = sub.add_parser("status", help="health, rates and error counters of the running services")
    status_cmd.add_argument("--json", action="store_true", help="print one JSON object")
    status_cmd.add_argument("--connect", default=None, help="router endpoint (default: the stack's)")
    status_cmd.add_argument("--robot-id", default=None, help="robot id (default: the stack's)")
    status_cmd.add_argument("--zenoh-config", default=None, help="zenoh client config (credentials, certificates)")
    status_cmd.set_defaults(func=_cmd_status)

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
    servo.set_defaults(func=_cmd_servo)

    experiment = sub.add_parser("experiment", help="reproduce one of the seed papers' experiments (Sensors 2022: "
                                                   "table3, part-a, part-b, part-c, part-d; Muñoz 2018: constraints; "
                                                   "JACO thesis: torque-control; Nelson 1995: tracking-region) and "
                                                   "report it beside the paper")
    experiment.add_argument("name", help="table3, part-a, part-b, part-c, part-d, constraints, torque-control or "
                                         "tracking-region")
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
    add_jobs_option(experiment)
    add_processes_option(experiment)
    add_arm_option(experiment, default=None, what="the scenario's; torque-control: j2n6s300")
    experiment.set_defaults(func=_cmd_experiment)

    demo = sub.add_parser("demo", help="for a new user: run part-a and table3 with a line per run, write the "
                                       "figures and reports, say where to look")
    demo.add_argument("--out", default="mfvs-demo", help="directory for the figures and reports (default: "
                                                         "./mfvs-demo)")
    add_jobs_option(demo)
    add_processes_option(demo)
    demo.set_defaults(func=_cmd_demo)

    from services.calibration.cli import add_parser as add_calibrate
    from services.check import add_parser as add_check
    from services.doctor import add_parser as add_doctor

    from services.console.cli import add_parser as add_console
    from services.observe.cli import add_parsers as add_observe

    add_calibrate(sub)
    add_check(sub, _add_connection_options, _operator_session)
    add_doctor(sub)
    add_observe(sub, _add_connection_options, _operator_session, _stack_connection)
    add_console(sub, _add_connection_options, _stack_connection)

    estop = sub.add_parser("estop", help="engage the latched emergency stop (or --reset it)")
    estop.add_argument("--reset", action="store_true", help="release the e-stop (only an explicit reset does)")
    estop.add_argument("--operator", default="mfvs-cli", help="who is asking (logged by safety)")
    estop.add_argument("--reason", default="", help="why (logged by safety)")
    _add_connection_options(estop)
    estop.set_defaults(func=_cmd_estop)

    task = sub.add_parser("task", help="start, stop or show the servo task (the stack comes up idle: the arm "
                                       "moves only while a task runs)")
    task.add_argument("action", choices=["start", "stop", "status"])
    task.add_argument("--operator", default="mfvs-cli", help="who is asking (logged, and kept in the task status)")
    task.add_argument("--reason", default="", help="why (logged)")
    task.add_argument("--json", action="store_true", help="print the task status as one JSON object")
    _add_connection_options(task)
    task.set_defaults(func=_cmd_task)

    authority = sub.add_parser("authority", help="write zenoh configs where only safety may command the robot")
    authority.add_argument("action", choices=["init"])
    authority.add_argument("--out", required=True, help="directory for the router/client configs and secrets")
    authority.add_argument("--tls", action="store_true", help="mutual TLS with certificates (else user/password)")
    authority.add_argument("--host", default="127.0.0.1", help="router address")
    authority.add_argument("--port", type=int, default=7447, help="router port")
    authority.add_argument("--services", help="comma-separated service identities (default: all of mfvs)")
    authority.set_defaults(func=_cmd_authority)

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
    bench.set_defaults(func=_cmd_bench)
    return parser


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


if __name__ == "__main__":
    sys.exit(main())
