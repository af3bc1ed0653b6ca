"""``python -m services.vision [--config FILE] [--clock realtime|lockstep] [--connect ENDPOINT]``"""
import sys

from services.runtime.service import service_main
from services.vision.service import VisionConfig, VisionService

if __name__ == "__main__":
    sys.exit(service_main(VisionService, VisionConfig, description="AprilTag corners → image features"))
