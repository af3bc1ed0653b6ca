"""A stand-in for safety's resend loop, as its own process at realtime priority (as safety runs deployed):
publishes one mixed-frame Cartesian velocity command every ``--period`` for ``--seconds``.

    python -m bench.command_source --connect ENDPOINT --linear 0.04 -0.03 0.03 --rotational 0 0 0.2
"""
import argparse
import sys
import time

from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from protocol.keys import Keys
from services.runtime.transport import ZenohConfig, open_session
from services.runtime.pacing import request_realtime


def main(argv=None) -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--connect", required=True)
    parser.add_argument("--linear", type=float, nargs=3, required=True)
    parser.add_argument("--rotational", type=float, nargs=3, required=True)
    parser.add_argument("--seconds", type=float, default=1.5)
    parser.add_argument("--period", type=float, default=0.005)
    parser.add_argument("--realtime-priority", type=int, default=30)
    args = parser.parse_args(argv)
    request_realtime(args.realtime_priority, "command source")  # before zenoh starts its threads
    session = open_session(ZenohConfig(connect=[args.connect]))
    try:
        publisher = session.declare_publisher(Keys().robot_command)
        start = time.monotonic()
        for k in range(int(args.seconds / args.period)):
            time.sleep(max(0.0, start + k * args.period - time.monotonic()))
            header = m.Header(seq=k, stamp_ns=time.time_ns())
            twist = m.Twist(header=header, frame=Frame.MIXED, angular=AngularConvention.SEED000,
                            linear=tuple(args.linear), rotational=tuple(args.rotational))
            publisher.put(m.encode(m.RobotCommand(header=header, mode=m.CommandMode.CARTESIAN_VELOCITY, twist=twist)))
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
