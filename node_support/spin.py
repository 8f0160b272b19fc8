"""The shared `main()` body of every node of the package: init, build, spin, shut down quietly;
`spin_until`, how a tool or a test waits on the graph; and `RosLogHandler`, which puts Python
log lines on /rosout.

Part of the ROS interface layer so that the simulator node and the policy-side nodes run alike."""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import re
import sys
import threading
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

from msg_schemas.text import one_line
from node_support.parameters import Param, answered_help

BAD_ARGUMENTS = 2  # exit code of a command line rclpy cannot parse, as argparse's
FAILED = 1  # exit code of a node whose executor died while it ran
EXIT_DEADLINE_S = 1.0  # a node whose executor died is gone this soon, its clean-up finished or not
SHUTDOWN_DEADLINE_S = 5.0  # after Ctrl-C (or SIGTERM), a node whose clean-up hangs is gone by then


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
    (exit code 2, as the commands'); a bad parameter, file or plug-in at start-up is logged in
    one line (exit code 2 too: bad input). Never a traceback.

    Should the executor die (an exception out of a callback, whatever raised it), the node's
    `fail_safe(reason)`, if it has one, is called first (the policy node stops commanding the
    robot and says ERROR), the error is logged in one line, and the process exits with code 1
    within EXIT_DEADLINE_S, whether its clean-up finished or not. Ctrl-C is honoured even when
    a callback never returns (rclpy's handler only shuts the context down, and the executor
    would wait for the callback for ever): the process is gone SHUTDOWN_DEADLINE_S after it."""
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
    except (ValueError, ParameterException, *startup_errors) as error:  # UnusableArgument too
        get_logger(name).error(str(error))
        rclpy.try_shutdown()
        return BAD_ARGUMENTS
    # What start-up built (torch, the model, ROS) stays for good: frozen out of the collector,
    # whose full passes would otherwise scan it with the interpreter held: in the policy node,
    # long pauses in which its control clock cannot send.
    gc.collect()
    gc.freeze()
    code = 0
    outcome: dict[str, int] = {}  # the exit code, once the clean-up has finished
    threading.Thread(target=exit_if_stuck_after_shutdown, args=(outcome,),
                     name="shutdown_watch", daemon=True).start()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as error:  # whatever killed the executor: fail safe
        # (an RCLError after Ctrl-C is a callback cut short, publishing into a closed context)
        if not (isinstance(error, RCLError) and not rclpy.ok()):
            code = FAILED
            exit_by_deadline(code)
            reason = f"executor died: {type(error).__name__}: {one_line(error)}"
            with contextlib.suppress(Exception):
                getattr(node, "fail_safe", lambda _reason: None)(reason)
            get_logger(name).error(f"{reason}; exiting")
    finally:
        with contextlib.suppress(Exception):
            node.destroy_node()
        rclpy.try_shutdown()
        outcome["code"] = code
    return code


def exit_if_stuck_after_shutdown(outcome: dict[str, int], period_s: float = 0.1) -> None:
    """Waits for the context to shut down (Ctrl-C, SIGTERM), then gives the process
    SHUTDOWN_DEADLINE_S to end of its own: after that it ends with the code its clean-up
    settled on, or FAILED if that never finished."""
    while rclpy.ok():
        time.sleep(period_s)
    exit_by_deadline(FAILED, SHUTDOWN_DEADLINE_S, "shutdown did not finish", outcome)


def exit_by_deadline(code: int, seconds: float = EXIT_DEADLINE_S, why: str = "",
                     outcome: dict[str, int] | None = None) -> None:
    """Ends the process with `code` (or `outcome["code"]`, once set) after `seconds`, should
    it still be running: a clean-up that hangs (a node whose handles are held elsewhere) must
    not keep it alive."""
    def end() -> None:
        if outcome and "code" in outcome:
            os._exit(outcome["code"])  # the clean-up finished: only the interpreter lingers
        if why:
            print(f"{why} in {seconds:g} s: exiting", file=sys.stderr)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)

    timer = threading.Timer(seconds, end)
    timer.daemon = True
    timer.start()
