"""The shared `main()` body of every node of the package: init, build, spin, shut down quietly.

Part of the ROS interface layer so that the simulator node and the policy-side nodes run alike."""

from __future__ import annotations

import gc
import sys
from collections.abc import Callable, Sequence

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription
from rclpy.timer import Timer

from msg_schemas.parameters import Param, usage


def answered_help(args: list[str] | None, name: str, summary: str,
                  parameters: Sequence[Param]) -> bool:
    """Prints the node's usage if `-h` or `--help` comes before `--ros-args`."""
    argv = sys.argv[1:] if args is None else list(args)
    own = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    if "-h" in own or "--help" in own:
        print(usage(name, summary, parameters))
        return True
    return False


def log_matches(node: Node, endpoints: Sequence[Publisher | Subscription],
                period_s: float = 0.2) -> Timer:
    """Logs "<topic>: N subscriber(s) matched" (a publisher) or "... publisher(s) matched" (a
    subscription) whenever N changes, counted on this endpoint's own side of discovery. The graph
    can list a subscriber before a publisher has matched it, and a best-effort message sent in
    between never reaches it: a tool that must not lose the first messages (a recorded trial)
    waits on these lines."""
    counts = [0] * len(endpoints)

    def check() -> None:
        for index, endpoint in enumerate(endpoints):
            if isinstance(endpoint, Publisher):
                count, side = endpoint.get_subscription_count(), "subscriber"
            else:
                count, side = endpoint.get_publisher_count(), "publisher"
            if count != counts[index]:
                counts[index] = count
                node.get_logger().info(f"{endpoint.topic_name}: {count} {side}(s) matched")

    check()
    return node.create_timer(period_s, check)


def spin_node(factory: Callable[[], Node], name: str, args: list[str] | None = None,
              parameters: Sequence[Param] = (), summary: str = "",
              startup_errors: tuple[type[BaseException], ...] = ()) -> int:
    """Runs a node until Ctrl-C or shutdown. `-h`/`--help` (before `--ros-args`) prints its
    parameters and topics and exits. A bad parameter or file at start-up is logged in one line
    (exit code 1), never a traceback."""
    if answered_help(args, name, summary, parameters):
        return 0
    rclpy.init(args=args)
    try:
        node = factory()
    except (ValueError, ParameterException, *startup_errors) as error:
        get_logger(name).error(str(error))
        rclpy.try_shutdown()
        return 1
    # What start-up built (torch, the model, ROS) stays for good: frozen out of the collector,
    # whose full passes would otherwise scan it with the interpreter held (200 ms measured in
    # the policy node, time its control clock cannot send in).
    gc.collect()
    gc.freeze()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:  # a callback cut short by Ctrl-C publishes into a context that is gone
        if rclpy.ok():
            raise
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
