"""Vision benchmark: AprilTag detection (vision's default detector, and aruco) and full feature extraction time per
frame, on frames rendered by robot_sim at 640×480 and 1280×720; and the corners' error against distance and motion
blur through a webcam-like camera (robot_sim's ``imaging``: read noise, JPEG, the blur of the tag's motion over the
exposure), for each detector.

``python -m bench.vision [--json] [--frames N] [--seeds N]`` or ``mfvs bench vision``.
"""
from __future__ import annotations

import argparse
import json
import time

import cv2
import mujoco
import numpy as np

from protocol import messages as m
from services.model.frames import PoseConfig
from services.model import tag as tags
from services.robot_sim.imaging import ImagingConfig, expose, motion_blur, target_corners_px
from services.robot_sim.scene import CameraConfig, SceneConfig, TargetConfig, camera_info
from services.robot_sim.sim import Simulation
from services.vision.features import RoiConfig, TagDetector, TagTracker
from services.vision.service import VisionConfig, VisionService

CAMERAS = {
    "640x480": CameraConfig(),
    "1280x720": CameraConfig(width=1280, height=720, fx=920.0, fy=920.0),
}


def _percentiles(samples_ms: list[float]) -> dict:
    s = np.sort(samples_ms)
    return {"p50": round(float(np.percentile(s, 50)), 3), "p99": round(float(np.percentile(s, 99)), 3),
            "max": round(float(s[-1]), 3), "n": len(s)}


def measure(camera: CameraConfig, frames: int) -> dict:
    cfg = SceneConfig(camera=camera, target=TargetConfig(
        pose_in_camera=PoseConfig(xyz=(0.03, -0.02, 0.5), rpy_deg=(170.0, 10.0, 20.0))))
    sim = Simulation(cfg)
    try:
        pixels = sim.render()
    finally:
        sim.close()
    gray = cv2.cvtColor(pixels, cv2.COLOR_RGB2GRAY)
    config = VisionConfig()
    detectors = {"default": TagDetector(backend=config.detector, refinement=config.refinement),
                 "aruco": TagDetector(backend="aruco")}
    timings = {}
    for name, detector in detectors.items():
        tracker = TagTracker(detector, RoiConfig(full_frame_every=frames + 1))
        assert tracker.find(gray, 0) is not None  # the first search is the full frame; then the window
        detect_ms, window_ms = [], []
        for _ in range(frames):
            t = time.perf_counter()
            assert detector.find(gray, 0) is not None
            detect_ms.append((time.perf_counter() - t) * 1e3)
            t = time.perf_counter()
            assert tracker.find(gray, 0) is not None
            window_ms.append((time.perf_counter() - t) * 1e3)
        timings[name] = {"detect_ms": _percentiles(detect_ms), "window_ms": _percentiles(window_ms)}
    service = VisionService(config)
    service._on_camera_info(camera_info(camera, m.Header()), 0)
    process_ms = []
    for _ in range(frames):
        stamp = time.time_ns()
        image = m.Image(header=m.Header(stamp_ns=stamp, source_stamp_ns=stamp), width=camera.width,
                        height=camera.height, encoding=m.ImageEncoding.RGB8, data=pixels.tobytes())
        t = time.perf_counter()
        features = service.process(image, stamp)
        process_ms.append((time.perf_counter() - t) * 1e3)
        assert features.status is m.FeatureStatus.OK
    return {**timings["default"], "process_ms": _percentiles(process_ms), "aruco": timings["aruco"]}


DISTANCES_M = (0.3, 0.6, 1.0, 1.5, 2.0)
BLURS_PX = (0.0, 3.0, 6.0, 12.0)


def corner_accuracy(seeds: int = 4, imaging: ImagingConfig | None = None) -> list[dict]:
    """Per detector, distance and blur: how often the tag is found and how far its corners are from the pinhole
    projection of MuJoCo's pose in the middle of the exposure (px: median and worst over ``seeds`` noise draws).
    The blur is the tag sliding across the image by ``blur`` px during the exposure."""
    imaging = imaging or ImagingConfig()
    rows = []
    detectors = {"aruco": TagDetector(), "apriltag": TagDetector(backend="apriltag")}
    for distance in DISTANCES_M:
        cfg = SceneConfig(floor=False, target=TargetConfig(pose_in_camera=PoseConfig(xyz=(0.0, 0.0, distance),
                                                                        rpy_deg=(200.0, 10.0, 15.0))))
        sim = Simulation(cfg)
        K = cfg.camera.matrix()
        T0 = sim.target_pose()
        try:
            for blur in BLURS_PX:
                travel = blur * distance / cfg.camera.fx  # metres across the view for a blur of that many px

                def place(s):
                    T = T0.copy()
                    T[:3, 3] += sim.camera_pose()[:3, 0] * travel * (s - 0.5)  # along the camera's x
                    sim.set_target_pose(T)
                    mujoco.mj_forward(sim.model, sim.data)

                place(0.0)
                start = target_corners_px(sim.model, sim.data, sim.camera_id, K)
                place(0.5)
                T_ct = np.linalg.inv(sim.camera_pose()) @ sim.target_pose()
                corners = (T_ct[:3, :3] @ tags.corners_in_tag(cfg.target.size_m).T).T + T_ct[:3, 3]
                truth = (K @ (corners / corners[:, 2:3]).T).T[:, :2]
                place(1.0)
                end = target_corners_px(sim.model, sim.data, sim.camera_id, K)
                gray = motion_blur(cv2.cvtColor(sim.render(), cv2.COLOR_RGB2GRAY), end, start, imaging.blur_samples)
                frames = [expose(gray, imaging, seed) for seed in range(1, seeds + 1)]
                for name, detector in detectors.items():
                    errors = []
                    for frame in frames:
                        found = detector.find(frame, 0)
                        if found is not None:
                            errors.append(float(np.linalg.norm(found.corners_px - truth, axis=1).max()))
                    rows.append({"detector": name, "distance_m": distance, "blur_px": blur,
                                 "tag_px": round(float(np.ptp(truth[:, 0])), 1), "found": len(errors) / len(frames),
                                 "median_px": round(float(np.median(errors)), 2) if errors else None,
                                 "worst_px": round(max(errors), 2) if errors else None})
        finally:
            sim.close()
    return rows


def keypoint_timing(frames: int) -> dict:
    """The keypoint front end's wall time a 640×480 frame (one thread: OpenCV's own set to one), by detector and
    object, at a frame it detects on (the taught descriptors matched anew) and at one it tracks on (LK from the
    frame before), the camera moving 2 mm a frame toward the taught view from 0.35 m; its share of the camera's
    33 ms at 30 Hz with one detection every ``detect_every`` frames."""
    from services.model import frames as fr
    from services.robot_sim.scene import TargetKind
    from services.vision.keypoints import KeypointConfig, KeypointFrontEnd, taught_goal_points
    from bench.markerless_rig import Rig, goal_target

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    out = {}
    try:
        for kind in (TargetKind.PLANE, TargetKind.CUP):
            rig = Rig(goal_target(kind))
            try:
                grays = []
                q = rig.moved(rig.home, (0.01, -0.01, -0.06), fr.rot_z(0.1))
                for _ in range(frames):
                    q = rig.moved(q, (0.0, 0.0, 0.002))
                    grays.append(rig.gray(q))
                for detector in ("sift", "orb"):
                    goal = rig.teach(region=rig.target_region(12.0), detector=detector)
                    config = KeypointConfig()
                    timed = {"detect": [], "track": []}
                    front = KeypointFrontEnd(goal, config)
                    for gray in grays:
                        t = time.perf_counter()
                        seen = front.measure(gray, rig.camera, taught_goal_points(goal))
                        if seen.view is not None:
                            timed[seen.view.search].append((time.perf_counter() - t) * 1e3)
                    detect, track = _percentiles(timed["detect"]), _percentiles(timed["track"] or [0.0])
                    mean = (detect["p50"] + (config.detect_every - 1) * track["p50"]) / config.detect_every
                    out[f"{kind.value}/{detector}"] = {"detect_ms": detect, "track_ms": track,
                                                       "mean_ms_per_frame": round(mean, 2),
                                                       "detect_every": config.detect_every,
                                                       "keypoints_taught": len(goal.points_camera)}
            finally:
                rig.close()
    finally:
        cv2.setNumThreads(threads)
    return out


def run(frames: int = 100, seeds: int = 4) -> dict:
    return {"timing": {name: measure(camera, frames) for name, camera in CAMERAS.items()},
            "corners": corner_accuracy(seeds), "keypoints_640x480": keypoint_timing(max(10, frames // 4))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench vision", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--frames", type=int, default=100, help="frames timed per resolution")
    parser.add_argument("--seeds", type=int, default=4, help="noise draws per distance and blur")
    args = parser.parse_args(argv)
    result = run(args.frames, args.seeds)
    if args.json:
        print(json.dumps(result))
    else:
        for name, r in result["timing"].items():
            d, w, p = r["detect_ms"], r["window_ms"], r["process_ms"]
            ad, aw = r["aruco"]["detect_ms"], r["aruco"]["window_ms"]
            print(f"{name}: detection (vision's default) on the full frame {d['p50']:.2f} ms p50, {d['p99']:.2f} ms "
                  f"p99; in the window around the last corners {w['p50']:.2f} ms p50, {w['p99']:.2f} ms p99 (aruco: "
                  f"{ad['p50']:.2f} and {aw['p50']:.2f} ms p50); the service's features (grayscale, window "
                  f"detection, refinement, pose, error) {p['p50']:.2f} ms p50, {p['p99']:.2f} ms p99 "
                  f"({d['n']} frames)")
        print("\nthe keypoint front end at 640x480 (one thread), a detection frame and a tracking frame, p50 / p99 ms:")
        for name, r in result["keypoints_640x480"].items():
            print(f"  {name:12s} detect {r['detect_ms']['p50']:6.1f} / {r['detect_ms']['p99']:6.1f}   track "
                  f"{r['track_ms']['p50']:5.1f} / {r['track_ms']['p99']:5.1f}   mean a frame (1 detection in "
                  f"{r['detect_every']}) {r['mean_ms_per_frame']:5.1f} ms ({r['keypoints_taught']} keypoints taught)")
        webcam = ImagingConfig()
        print(f"\ncorner error (px, worst corner) against the mid-exposure truth, through a webcam-like camera "
              f"(noise σ {webcam.noise_sigma}, JPEG {webcam.jpeg_quality}), median / worst of {args.seeds} draws; "
              "- : not found")
        for detector in ("aruco", "apriltag"):
            print(f"{detector:>9}  distance  tag px " + "".join(f"  blur {b:>4.0f} px" for b in BLURS_PX))
            for distance in DISTANCES_M:
                cells = [r for r in result["corners"] if r["detector"] == detector and r["distance_m"] == distance]
                line = "".join(f"  {c['median_px']:>5.2f}/{c['worst_px']:<5.2f}" if c["median_px"] is not None
                               else "  " + "-".center(11) for c in cells)
                found = min(c["found"] for c in cells)
                print(f"{'':>9}  {distance:>6.1f} m  {cells[0]['tag_px']:>6.0f}{line}"
                      + ("" if found == 1.0 else f"   (found in {found:.0%} at worst)"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
