"""``python -m services.torque_controller --controller NAME [--arm NAME] [--duration S] [--log FILE.npz]
[--connect ENDPOINT] [--config FILE] [--set KEY=VALUE ...]``: one run of one of the JACO thesis's controllers against
the robot's low-level torque API (jt-pid, null-space, null-space-mass, joint-pd, joint-velocity, computed-torque);
``--set options.tf_s=3`` and the like set the run's options (services.controller.torque_controllers)."""
import argparse
import sys

from services.runtime.service import service_main
from services.torque_controller.service import TorqueControllerConfig, TorqueControllerService


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--controller")
    parser.add_argument("--arm")
    parser.add_argument("--duration")
    parser.add_argument("--log")
    known, rest = parser.parse_known_args(sys.argv[1:] if argv is None else argv)
    overrides = [f"{key}={value}" for key, value in (("controller", known.controller), ("arm", known.arm),
                                                     ("duration_s", known.duration), ("log", known.log))
                 if value is not None]
    for override in overrides:
        rest += ["--set", override]
    return service_main(TorqueControllerService, TorqueControllerConfig, rest, description=__doc__)


if __name__ == "__main__":
    sys.exit(main())
