"""``python -m services.safety [--config FILE] [--clock realtime|lockstep] [--connect ENDPOINT]``"""
import sys

from services.runtime.service import service_main
from services.safety.service import SafetyConfig, SafetyService

if __name__ == "__main__":
    sys.exit(service_main(SafetyService, SafetyConfig, description="the only path to the robot"))
