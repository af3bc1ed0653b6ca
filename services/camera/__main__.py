"""``python -m services.camera [--config FILE] [--connect ENDPOINT] [--set KEY=VALUE]``"""
import sys

from services.camera.service import CameraConfig, CameraService
from services.runtime.service import service_main

if __name__ == "__main__":
    sys.exit(service_main(CameraService, CameraConfig,
                          description="a camera, video file or image folder → camera images and calibrated info"))
