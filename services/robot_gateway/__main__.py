"""``python -m services.robot_gateway [--config FILE] [--connect ENDPOINT] [--set KEY=VALUE ...]``"""
import sys

from services.runtime.service import service_main
from services.robot_gateway.kinova_sdk import check_comm_layer, locate_command_layer, put_sdk_on_loader_path
from services.robot_gateway.service import GatewayConfig, robot_gateway_service


def gateway_process(config: GatewayConfig):
    """robot_gateway as its own process: with Kinova's SDK, its directory first goes on the loader's path (the
    command layer loads its comm layer by bare name), which may execute the process again."""
    if config.backend == "kinova_sdk":
        command_layer = locate_command_layer(config.sdk_library, config.sdk_transport)
        check_comm_layer(command_layer, config.sdk_transport)  # what is missing, said plainly (libusb, the file)
        put_sdk_on_loader_path(command_layer, config.sdk_transport)
    return robot_gateway_service(config)


gateway_process.name = robot_gateway_service.name

if __name__ == "__main__":
    sys.exit(service_main(gateway_process, GatewayConfig, description="the robot API backed by a real arm"))
