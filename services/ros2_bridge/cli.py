"""``mfvs ros2``: the running stack as a ROS 2 node (docs/ros2.md), in the foreground until Ctrl-C.

    mfvs ros2                                   # domain $ROS_DOMAIN_ID (else 0), node /mfvs, Jazzy's wire
    mfvs ros2 --namespace /jaco --distro humble

It reaches the stack as `mfvs task` and `mfvs estop` do (the running stack's router and robot id, and behind
authority the operator's zenoh config): what ROS 2 asks through it is what the operator identity may ask.
"""
from __future__ import annotations

import argparse
import os
import sys

from protocol.ros2.keys import Distro

#: the variable ROS 2 reads its domain from; the bridge joins the same domain by default
DOMAIN_ENV = "ROS_DOMAIN_ID"


def domain_id(text: str, what: str = "") -> int:
    """A ROS domain id written out (``what``: where it was, for the error); ValueError for anything that is none."""
    if not text.strip().isdigit():
        where = f"{what}=" if what else ""
        raise ValueError(f"{where}{text!r} is not a domain id (a non-negative integer)")
    return int(text)


def default_domain() -> int:
    """$ROS_DOMAIN_ID as ROS reads it (unset or empty: 0); ValueError for anything that is no domain id."""
    text = os.environ.get(DOMAIN_ENV, "").strip()
    return domain_id(text, DOMAIN_ENV) if text else 0


def add_parser(sub, add_connection_options, stack_connection) -> None:
    ros2 = sub.add_parser("ros2", help="the running stack as a ROS 2 node on rmw_zenoh's wire: camera, joint "
                                       "states, /tf, robot_description, /diagnostics; Trigger services to start "
                                       "and stop the task and engage the e-stop")
    ros2.add_argument("--domain-id", type=int, default=None, help=f"ROS domain (default ${DOMAIN_ENV}, else 0)")
    ros2.add_argument("--namespace", default="/", help="the node's namespace (default /)")
    ros2.add_argument("--node-name", default="mfvs", help="the node's name (default mfvs)")
    ros2.add_argument("--distro", choices=[d.value for d in Distro], default=Distro.JAZZY.value,
                      help="the ROS 2 graph's distribution (its rmw_zenoh's wire; default jazzy)")
    ros2.add_argument("--operator", default="ros2", help="the name the stack logs for what ROS 2 asks")
    add_connection_options(ros2)
    ros2.set_defaults(func=lambda args: run(args, stack_connection))


def run(args: argparse.Namespace, stack_connection) -> int:
    from services.ros2_bridge.service import Ros2BridgeConfig, Ros2BridgeService
    from services.runtime.logs import setup_logging
    from services.runtime.transport import ZenohConfig

    stack_connection(args)
    try:
        domain = args.domain_id if args.domain_id is not None else default_domain()
        config = Ros2BridgeConfig(robot_id=args.robot_id, domain_id=domain, namespace=args.namespace,
                                  node_name=args.node_name, distro=Distro(args.distro), operator=args.operator,
                                  action_timeout_s=args.timeout,
                                  zenoh=ZenohConfig(connect=[args.connect], config_file=args.zenoh_config))
    except ValueError as exc:
        print(f"mfvs ros2: {exc}", file=sys.stderr)
        return 2
    setup_logging("info")
    return Ros2BridgeService(config).run()
