"""``python -m services.robot_gateway [--config FILE] [--connect ENDPOINT] [--set KEY=VALUE ...]``"""
import logging
import sys

from services.runtime.service import service_main
from services.robot_gateway.kinova_sdk import check_comm_layer, locate_command_layer, put_sdk_on_loader_path
from services.robot_gateway.kinova_usb import locate_comm_layer
from services.robot_gateway.service import (KINOVA_USB, GatewayConfig, connect_sdk_arm, high_level_api, open_bus,
                                            robot_gateway_service)


def prepare(config: GatewayConfig) -> dict:
    """robot_gateway as its own process, before anything else: with Kinova's SDK, its comm layer checked, its
    folder on the loader's path (the command layer loads the comm layer by bare name: this may execute the process
    again), and the arm opened, so that what keeps the arm from starting is the one line the process prints."""
    if config.backend == "rs485" and config.bus.interface == KINOVA_USB:
        command_layer = high_level_api(config, locate_comm_layer(config.sdk_library))
        if command_layer is not None:  # it loads the comm layer by bare name at InitAPI (may execute us again)
            put_sdk_on_loader_path(command_layer, "usb")
        return {"bus": open_bus(config, log=logging.getLogger("mfvs.robot_gateway"))}
    if config.backend != "kinova_sdk":
        return {}
    command_layer = locate_command_layer(config.sdk_library, config.sdk_transport)
    check_comm_layer(command_layer, config.sdk_transport)  # what is missing, said plainly (libusb, the file)
    put_sdk_on_loader_path(command_layer, config.sdk_transport)
    return {"connection": connect_sdk_arm(config, log=logging.getLogger("mfvs.robot_gateway"))}


def gateway_process(config: GatewayConfig, **prepared):
    try:
        return robot_gateway_service(config, **prepared)
    except BaseException:
        for opened in prepared.values():
            opened.close()  # CloseAPI (CloseCommunication) on every way out
        raise


gateway_process.name = robot_gateway_service.name

if __name__ == "__main__":
    sys.exit(service_main(gateway_process, GatewayConfig, description="the robot API backed by a real arm",
                          prepare=prepare))
