"""``dragd ros2``: the ROS 2 bridge beside the daemon (docs/ROS2.md)."""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

from dragd.cli.common import CliError, default_socket


def cmd_ros2(args: argparse.Namespace) -> int:
    import asyncio

    from dragd.ros2 import unavailable

    reason = unavailable()
    if reason:
        raise CliError(reason, status=1)
    if args.rate is not None and not 0 < args.rate <= 1000:
        raise CliError(f"--rate: expected a rate in (0, 1000] Hz, got {args.rate:g}")
    from dragd.ros2.bridge import Bridge

    bridge = Bridge(args.socket, ros_args=args.ros_args or [], node_name=args.node_name,
                    joint_states_rate_Hz=args.rate)
    # not asyncio.run: its cleanup waits for every task left to end on its cancel, and run() has closed what counts
    # (the stream, the lease) and bounded each step of its teardown (Bridge._bounded)
    code = asyncio.new_event_loop().run_until_complete(bridge.run())
    # the middleware's own threads (DDS, the executor's pool) are joined at interpreter exit, and one blocked in a
    # native wait would hold a SIGTERM'd bridge up: everything of ours is closed, so the process ends here
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def register(sub: Any) -> None:
    r = sub.add_parser("ros2", help="the ROS 2 bridge: joint states, services, trajectories and command streams on "
                                    "the ROS graph (needs the ros2 extra)")
    r.add_argument("--socket", default=default_socket(), help="the daemon's control socket (default: $DRAGD_SOCKET, "
                                                              "else /run/dragd/dragd.sock)")
    r.add_argument("--rate", type=float, default=None, help="/joint_states rate in Hz (default: the parameter "
                                                            "joint_states_rate_Hz, 100)")
    r.add_argument("--node-name", default="dragd", help="the node's name (default dragd: topics ~/... are /dragd/...)")
    r.add_argument("--ros-args", nargs=argparse.REMAINDER, default=[], dest="ros_args",
                   help="everything after it goes to ROS (remaps, parameters, namespace: -r __ns:=/arm1)")
    r.set_defaults(func=cmd_ros2)
