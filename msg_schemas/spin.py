"""The shared `main()` body of every node of the package: init, build, spin, shut down quietly;
`spin_until`, how a tool or a test waits on the graph; and `RosLogHandler`, which puts Python
log lines on /rosout.

Part of the ROS interface layer so that the simulator node and the policy-side nodes run alike."""

from __future__ import annotations

import gc
import logging
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import rclpy
from rclpy._rclpy_pybind11 import RCLError, RCLInvalidROSArgsError, UnknownROSArgsError
from rclpy.exceptions import ParameterException
from rclpy.executors import Executor, ExternalShutdownException
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription
from rclpy.timer import Timer
from rclpy.utilities import remove_ros_args

from msg_schemas.parameters import Param, usage
from msg_schemas.text import one_line

BAD_ARGUMENTS = 2  # exit code of a command line rclpy cannot parse, as argparse's


class UnusableArgument(ValueError):
    """A parameter that is well formed but cannot be used here (a port in use, an address this
    machine does not have): exit code BAD_ARGUMENTS, as for a bad command line."""


class RosLogHandler(logging.Handler):
    """Python `logging` records into a node's logger (and so /rosout), at their level: what a
    library logs the ROS way (a planning worker's warnings) reaches the tools that watch ROS."""

    def __init__(self, logger) -> None:
        super().__init__()
        self.logger = logger

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
            if record.levelno >= logging.ERROR:
                self.logger.error(text)
            elif record.levelno >= logging.WARNING:
                self.logger.warning(text)
            elif record.levelno >= logging.INFO:
                self.logger.info(text)
            else:
                self.logger.debug(text)
        except Exception:  # a log line never takes the node down
            self.handleError(record)


def process_age_s() -> float | None:
    """Seconds since this process started (Linux's /proc), or None where that cannot be read:
    how long a node took to come up, imports included."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


class StartupPhases:
    """Where a node's start-up went, for its ready line: the interpreter's imports (from the
    process's start to building the node), then each phase `mark`ed after it ends."""

    def __init__(self) -> None:
        self.imports, self.last = process_age_s(), time.monotonic()
        self.phases: list[tuple[str, float]] = []

    def mark(self, name: str) -> None:
        now = time.monotonic()
        self.phases.append((name, now - self.last))
        self.last = now

    def text(self) -> str:
        parts = [] if self.imports is None else [("imports", self.imports)]
        return ", ".join(f"{name} {seconds:.1f} s" for name, seconds in parts + self.phases)


def answered_help(args: list[str] | None, name: str, summary: str,
                  parameters: Sequence[Param]) -> bool:
    """Prints the node's usage if `-h` or `--help` comes before `--ros-args`."""
    argv = sys.argv[1:] if args is None else list(args)
    own = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    if "-h" in own or "--help" in own:
        print(usage(name, summary, parameters))
        return True
    return False


def ros_arguments_problem(args: list[str] | None) -> str | None:
    """Why rclpy cannot parse the command line's ROS arguments (`-p mode=realtime` without its
    colon, an unknown `--flag`), in words, or None. Asked before `rclpy.init`, which raises the
    same errors after logging a line of its own; rcl's source locations are left out."""
    try:
        remove_ros_args(args)
    except UnknownROSArgsError as error:
        return f"unknown ROS arguments {error}"
    except RCLInvalidROSArgsError as error:
        return rcl_text(error)
    return None


def rcl_text(error: Exception) -> str:
    """An rcl error's message without the C source locations it appends (", at file.c:49")."""
    return re.sub(r", at \S+:\d+", "", str(error))


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


def spin_until(spinner: Executor | Node, condition: Callable[[], bool],
               timeout_s: float | None = None, *, deadline: float | None = None,
               period_s: float = 0.02, failed: Callable[[], str | None] | None = None,
               what: str | None = None) -> bool:
    """Spins `spinner` (an executor, or a node on rclpy's global executor) `period_s` at a time
    until `condition()` holds (True), or until `timeout_s` from now or the `time.monotonic()`
    `deadline` has passed (False; with `what`, RuntimeError "timed out waiting for <what>"
    instead). `failed`, asked before each spin, names a reason to stop waiting (a node process
    that exited), raised as RuntimeError: a wait on a dead node fails at once, not at its
    timeout. Polling, not sleeping, because callbacks run only while the node spins."""
    if (timeout_s is None) == (deadline is None):
        raise ValueError("spin_until takes either timeout_s or deadline")
    end = time.monotonic() + timeout_s if deadline is None else deadline
    while not condition():
        failure = failed() if failed is not None else None
        if failure:
            raise RuntimeError(failure)
        if time.monotonic() > end:
            if what is None:
                return False
            raise RuntimeError(f"timed out waiting for {what}")
        if isinstance(spinner, Node):
            rclpy.spin_once(spinner, timeout_sec=period_s)
        else:
            spinner.spin_once(timeout_sec=period_s)
    return True


def spin_node(factory: Callable[[], Node], name: str, args: list[str] | None = None,
              parameters: Sequence[Param] = (), summary: str = "",
              startup_errors: tuple[type[BaseException], ...] = ()) -> int:
    """Runs a node until Ctrl-C or shutdown. `-h`/`--help` (before `--ros-args`) prints its
    parameters and topics and exits. ROS arguments rclpy cannot parse are one line on stderr
    (exit code 2, as the commands', and for an `UnusableArgument`); a bad parameter or file at
    start-up is logged in one line (exit code 1). Never a traceback."""
    if answered_help(args, name, summary, parameters):
        return 0
    problem = ros_arguments_problem(args)
    if problem is None:
        try:
            rclpy.init(args=args)
        except RCLError as error:  # e.g. ROS_DOMAIN_ID=abc
            problem = rcl_text(error)
    if problem is not None:
        print(f"{name}: error: {one_line(problem)} (see --help)", file=sys.stderr)
        return BAD_ARGUMENTS
    try:
        node = factory()
    except UnusableArgument as error:
        get_logger(name).error(str(error))
        rclpy.try_shutdown()
        return BAD_ARGUMENTS
    except (ValueError, ParameterException, *startup_errors) as error:
        get_logger(name).error(str(error))
        rclpy.try_shutdown()
        return 1
    # What start-up built (torch, the model, ROS) stays for good: frozen out of the collector,
    # whose full passes would otherwise scan it with the interpreter held: in the policy node,
    # long pauses in which its control clock cannot send.
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
