"""``python -m services.controller [--config FILE] [--clock realtime|lockstep] [--connect ENDPOINT]``"""
import sys

from services.runtime.service import service_main
from services.controller.service import ControllerConfig, ControllerService

if __name__ == "__main__":
    sys.exit(service_main(ControllerService, ControllerConfig, description="visual servo control laws"))
