"""``mfvs calibrate intrinsics`` and ``mfvs calibrate hand-eye``: write the files the camera service reads, print
the residuals; ``--simulate`` makes the recording in the simulator and says how far the result is from its truth.
"""
from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from services.camera.calibration import CalibrationError, read_intrinsics, write_camera_in_ee, write_intrinsics
from services.model.board import BoardConfig


def add_parser(sub) -> None:
    calibrate = sub.add_parser("calibrate", help="calibrate the camera (intrinsics from a ChArUco board) and its "
                                                 "mounting on the end effector (hand-eye)")
    what = calibrate.add_subparsers(dest="what", metavar="WHAT", required=True, parser_class=type(calibrate))
    intrinsics = what.add_parser("intrinsics", help="intrinsics and distortion from images of a ChArUco board")
    source = intrinsics.add_mutually_exclusive_group(required=True)
    source.add_argument("--images", help="folder of images of the board, seen from different angles")
    source.add_argument("--simulate", action="store_true",
                        help="photograph the board with the simulator's camera and compare with its intrinsics")
    intrinsics.add_argument("--out", help="calibration file to write (OpenCV YAML; the camera service's "
                                          "`calibration`)")
    intrinsics.add_argument("--views", type=int, default=16, help="--simulate: how many images (default 16)")
    _add_common(intrinsics)
    intrinsics.set_defaults(func=_cmd_intrinsics)

    hand_eye = what.add_parser("hand-eye", help="the camera's mounting on the end effector from arm poses looking "
                                                "at a fixed board")
    source = hand_eye.add_mutually_exclusive_group(required=True)
    source.add_argument("--recording", help="folder of images and arm_poses.yaml (joint angles at each image)")
    source.add_argument("--simulate", action="store_true",
                        help="move the simulated arm through wrist poses and compare with its true mounting")
    hand_eye.add_argument("--calibration", help="the camera's calibration file (--simulate: default the "
                                                "simulator's exact intrinsics)")
    hand_eye.add_argument("--out", help="hand-eye file to write (the camera service's `hand_eye`)")
    hand_eye.add_argument("--poses", type=int, default=15, help="--simulate: how many arm poses (default 15)")
    _add_common(hand_eye)
    hand_eye.set_defaults(func=_cmd_hand_eye)


def _add_common(parser) -> None:
    from services.model.arm import arm_names

    parser.add_argument("--arm", default=None, metavar="NAME",
                        help=f"the arm ({', '.join(arm_names())}): --simulate's emulated arm (default j2s7s300); a "
                             "recording's arm must be this one")
    defaults = BoardConfig()
    parser.add_argument("--squares", default=f"{defaults.squares_x}x{defaults.squares_y}",
                        help="the board's squares across x down (default %(default)s)")
    parser.add_argument("--square-m", type=float, default=defaults.square_m, help="square edge (m)")
    parser.add_argument("--marker-m", type=float, default=defaults.marker_m, help="marker edge (m)")
    parser.add_argument("--dictionary", default=defaults.dictionary, help="ArUco dictionary (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="--simulate: the poses' random seed")
    parser.add_argument("--keep", help="--simulate: keep the recording in this folder")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def _board(args) -> BoardConfig:
    try:
        across, _, down = args.squares.partition("x")
        return BoardConfig(squares_x=int(across), squares_y=int(down), square_m=args.square_m,
                           marker_m=args.marker_m, dictionary=args.dictionary)
    except ValueError as exc:
        raise CalibrationError("--squares/--square-m/--marker-m/--dictionary", str(exc)) from None


def _recording_dir(args, stack) -> Path:
    if args.keep:
        Path(args.keep).mkdir(parents=True, exist_ok=True)
        return Path(args.keep)
    return Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="mfvs-calibration-")))


def _finish(args, report: dict, lines: list[str]) -> int:
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print("\n".join(lines))
    return 0 if report.get("passed", True) else 1


def _fail(command: str, exc: Exception) -> int:
    print(f"mfvs calibrate {command}: {exc}", file=sys.stderr)
    return 2


def _cmd_intrinsics(args) -> int:
    from contextlib import ExitStack

    from services.calibration.intrinsics import CalibrationFailed, calibrate_intrinsics, read_images
    from services.calibration.simulate import record_intrinsics
    from services.model.arm import DEFAULT_ARM, load_arm

    if not args.simulate and not args.out:
        return _fail("intrinsics", ValueError("say where to write the calibration: --out FILE"))
    try:
        board = _board(args)
        with ExitStack() as stack:
            truth = None
            directory = Path(args.images) if args.images else _recording_dir(args, stack)
            if args.simulate:
                truth = record_intrinsics(directory, board, views=args.views, seed=args.seed,
                                          arm=load_arm(args.arm or DEFAULT_ARM))
            if not directory.is_dir():
                raise CalibrationFailed(f"no folder {directory}")
            result = calibrate_intrinsics(read_images(directory), board)
    except (CalibrationFailed, CalibrationError, ValueError) as exc:
        return _fail("intrinsics", exc)
    report = result.summary()
    K = result.intrinsics
    lines = [f"{report['views']} views ({len(result.skipped)} left out), RMS reprojection error "
             f"{result.rms_px:.3f} px (worst view {report['worst_view_px']:.3f} px), views {result.view_spread_deg:.0f}°"
             " apart at most",
             f"fx {K.fx:.2f}  fy {K.fy:.2f}  cx {K.cx:.2f}  cy {K.cy:.2f}  (px, {K.width}x{K.height})",
             "distortion k1 k2 p1 p2 k3: " + " ".join(f"{v:+.5f}" for v in K.distortion)]
    for name, why in result.skipped.items():
        lines.append(f"  left out {name}: {why}")
    if truth is not None:
        cam = truth.camera
        cx, cy = cam.principal_point
        errors = {"fx_error_pct": 100 * abs(K.fx - cam.fx) / cam.fx, "fy_error_pct": 100 * abs(K.fy - cam.fy) / cam.fy,
                  "cx_error_px": abs(K.cx - cx), "cy_error_px": abs(K.cy - cy)}
        report.update(errors, truth={"fx": cam.fx, "fy": cam.fy, "cx": cx, "cy": cy},
                      passed=bool(errors["fx_error_pct"] < 0.5 and errors["fy_error_pct"] < 0.5))
        lines.append(f"against the simulator's camera (fx {cam.fx}, fy {cam.fy}, cx {cx}, cy {cy}): fx off by "
                     f"{errors['fx_error_pct']:.3f} %, fy by {errors['fy_error_pct']:.3f} %, principal point by "
                     f"{errors['cx_error_px']:.2f}, {errors['cy_error_px']:.2f} px: "
                     + ("PASS (focal within 0.5 %)" if report["passed"] else "FAIL (focal beyond 0.5 %)"))
    if args.out:
        write_intrinsics(args.out, K, comment=f"mfvs calibrate intrinsics: {report['views']} views, RMS "
                                              f"{result.rms_px:.3f} px")
        report["written"] = args.out
        lines.append(f"wrote {args.out}")
    return _finish(args, report, lines)


def _cmd_hand_eye(args) -> int:
    from contextlib import ExitStack

    from services.calibration.hand_eye import HandEyeFailed, calibrate_hand_eye, read_recording
    from services.calibration.simulate import CAMERA, mounting_error, record_hand_eye
    from services.model.arm import DEFAULT_ARM, load_arm

    if not args.simulate and not args.calibration:
        return _fail("hand-eye", ValueError("the camera's intrinsics are needed: --calibration FILE"))
    if not args.simulate and not args.out:
        return _fail("hand-eye", ValueError("say where to write the mounting: --out FILE"))
    try:
        board = _board(args)
        with ExitStack() as stack:
            truth = None
            directory = Path(args.recording) if args.recording else _recording_dir(args, stack)
            if args.simulate:
                truth = record_hand_eye(directory, board, poses=args.poses, seed=args.seed,
                                        arm=load_arm(args.arm or DEFAULT_ARM))
            elif args.arm is not None:
                recorded = read_recording(directory).arm
                if recorded != args.arm:
                    raise CalibrationError(f"{directory} was recorded on the {recorded}, not the {args.arm}")
            if args.calibration:
                intrinsics = read_intrinsics(args.calibration)
                K, distortion = intrinsics.camera_matrix, intrinsics.distortion
            else:
                K, distortion = CAMERA.matrix(), np.zeros(5)
            result = calibrate_hand_eye(directory, board, K, distortion)
    except (HandEyeFailed, CalibrationError, RuntimeError, ValueError) as exc:
        return _fail("hand-eye", exc)
    report = result.summary()
    xyz, rpy = report["camera_in_ee"]["xyz"], report["camera_in_ee"]["rpy_deg"]
    lines = [f"{result.poses_used} arm poses ({len(result.skipped)} left out), solver {result.solver}",
             "camera_in_ee: xyz [" + ", ".join(f"{v:.4f}" for v in xyz) + "] m, rpy_deg ["
             + ", ".join(f"{v:.2f}" for v in rpy) + "]",
             f"the board's corners reproject through it to {result.reprojection_rms_px:.3f} px RMS; its pose "
             f"through each arm pose strays {result.board_spread_mm:.2f} mm and {result.board_spread_deg:.3f}° RMS "
             "from their mean (a good calibration: under a pixel, about a millimetre)"]
    for name, why in result.skipped.items():
        lines.append(f"  left out {name}: {why}")
    if truth is not None:
        mm, deg = mounting_error(result.T_ee_camera, truth.T_ee_camera)
        report.update(translation_error_mm=mm, rotation_error_deg=deg, passed=bool(mm < 2.0 and deg < 0.5),
                      truth={"xyz": list(truth.camera.camera_in_ee.xyz),
                             "rpy_deg": list(truth.camera.camera_in_ee.rpy_deg)})
        lines.append(f"against the simulator's mounting: {mm:.2f} mm, {deg:.3f}°: "
                     + ("PASS (within 2 mm and 0.5°)" if report["passed"] else "FAIL (beyond 2 mm or 0.5°)"))
    if args.out:
        write_camera_in_ee(args.out, result.T_ee_camera,
                           {"board_spread_mm": result.board_spread_mm, "board_spread_deg": result.board_spread_deg,
                            "poses": result.poses_used},
                           comment="mfvs calibrate hand-eye: the camera frame in the end-effector frame")
        report["written"] = args.out
        lines.append(f"wrote {args.out}")
    return _finish(args, report, lines)
