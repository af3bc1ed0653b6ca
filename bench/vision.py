"""Vision benchmark: AprilTag detection and full feature extraction time per frame, on frames rendered by
robot_sim at 640×480 and 1280×720.

``python -m bench.vision [--json] [--frames N]`` or ``mfvs bench vision``.
"""
from __future__ import annotations

import argparse
import json
import time

import cv2
import numpy as np

from protocol import messages as m
from services.runtime.config import PoseConfig
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
    detector = TagDetector()
    tracker = TagTracker(detector, RoiConfig(full_frame_every=frames + 1))
    assert tracker.find(gray, 0) is not None  # the first search is the full frame; then the window
    service = VisionService(VisionConfig())
    service._on_camera_info(camera_info(camera, m.Header()), 0)
    detect_ms, window_ms, process_ms = [], [], []
    for _ in range(frames):
        t = time.perf_counter()
        assert detector.find(gray, 0) is not None
        detect_ms.append((time.perf_counter() - t) * 1e3)
        t = time.perf_counter()
        assert tracker.find(gray, 0) is not None
        window_ms.append((time.perf_counter() - t) * 1e3)
    for _ in range(frames):
        stamp = time.time_ns()
        image = m.Image(header=m.Header(stamp_ns=stamp, source_stamp_ns=stamp), width=camera.width,
                        height=camera.height, encoding=m.ImageEncoding.RGB8, data=pixels.tobytes())
        t = time.perf_counter()
        features = service.process(image, stamp)
        process_ms.append((time.perf_counter() - t) * 1e3)
        assert features.status is m.FeatureStatus.OK
    return {"detect_ms": _percentiles(detect_ms), "window_ms": _percentiles(window_ms),
            "process_ms": _percentiles(process_ms)}


def run(frames: int = 100) -> dict:
    return {name: measure(camera, frames) for name, camera in CAMERAS.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench vision", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--frames", type=int, default=100, help="frames timed per resolution")
    args = parser.parse_args(argv)
    result = run(args.frames)
    if args.json:
        print(json.dumps(result))
    else:
        for name, r in result.items():
            d, w, p = r["detect_ms"], r["window_ms"], r["process_ms"]
            print(f"{name}: detection on the full frame {d['p50']:.2f} ms p50, {d['p99']:.2f} ms p99; in the window "
                  f"around the last corners {w['p50']:.2f} ms p50, {w['p99']:.2f} ms p99; the service's features "
                  f"(grayscale, window detection, refinement, pose, error) {p['p50']:.2f} ms p50, {p['p99']:.2f} ms "
                  f"p99 ({d['n']} frames)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
