"""Shared helpers for tests that run nodes as processes over real DDS.

Each test module picks its own random ROS domain (`random_domain_id`), so parallel runs on one
machine, and other modules of the same run, do not hear each other. Waits poll match counts,
messages or logs, never blind sleeps.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from msg_schemas import TOPICS, qos_profile

REPO = Path(__file__).resolve().parents[1]
DISCOVERY_S = 20.0  # discovery takes a few seconds here; generous for a loaded machine


def random_domain_id() -> int:
    return random.SystemRandom().randint(1, 100)


def stamp_ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def stamp_step(stamp) -> int:
    """Control step of a simulated-time stamp (0.1 s per step)."""
    return round(stamp_ns(stamp) / 100_000_000)


def param_text(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def child_env(domain_id: int, log_dir: Path) -> dict[str, str]:
    """Environment of a node process: the test's domain, one thread, unbuffered logs."""
    return {**os.environ, "ROS_DOMAIN_ID": str(domain_id), "OMP_NUM_THREADS": "1",
            "PYTHONUNBUFFERED": "1", "RCUTILS_LOGGING_BUFFERED_STREAM": "0",
            "ROS_LOG_DIR": str(log_dir / "ros_log")}


class Processes:
    """Node processes started by a test; `stop_all` interrupts them like Ctrl-C, then kills."""

    def __init__(self, log_dir: Path, domain_id: int) -> None:
        self.log_dir = log_dir
        self.started: list[subprocess.Popen] = []
        self.env = child_env(domain_id, log_dir)

    def start(self, module: str, name: str, remap: dict[str, str] | None = None,
              **params: object) -> tuple[subprocess.Popen, Path]:
        args = [sys.executable, "-m", module, "--ros-args"]
        for source, target in (remap or {}).items():
            args += ["-r", f"{source}:={target}"]
        for key, value in params.items():
            args += ["-p", f"{key}:={param_text(value)}"]
        log = self.log_dir / f"{name}.log"
        with log.open("w") as out:
            process = subprocess.Popen(args, cwd=REPO, env=self.env, stdout=out,
                                       stderr=subprocess.STDOUT)
        self.started.append(process)
        return process, log

    @staticmethod
    def stop(process: subprocess.Popen, timeout: float = 5.0) -> int:
        """SIGINT, then kill after `timeout`; returns the exit code."""
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
        return Processes._wait(process, timeout)

    @staticmethod
    def _wait(process: subprocess.Popen, timeout: float) -> int:
        try:
            return process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            return process.wait()

    def stop_all(self) -> None:
        for process in self.started:  # all at once, then wait: they stop in parallel
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        for process in self.started:
            self._wait(process, 5.0)
        self.started.clear()


class Ros:
    """The in-process test node, on its own context in the test's domain."""

    def __init__(self, domain_id: int, name: str = "test_node") -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, predicate: Callable[[], bool], timeout: float = DISCOVERY_S) -> bool:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.02)
        return True

    def spin_for(self, seconds: float) -> None:
        """Keep receiving for a while: only to check that nothing *more* arrives."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)

    def publisher(self, topic: str, msg_type, name: str | None = None):
        """A publisher with the contract's QoS for `topic` (a TOPICS key), on `name` if given
        (a remapped copy of the topic), else on the contract's name."""
        endpoint = TOPICS[topic]
        return self.node.create_publisher(msg_type, name or endpoint.name,
                                          qos_profile(endpoint, "publisher"))

    def inbox(self, topic: str, msg_type, callback: Callable | None = None) -> list:
        """Every message on a contract topic, in arrival order (after `callback`, if given)."""
        received: list = []

        def keep(msg) -> None:
            received.append(msg)
            if callback is not None:
                callback(msg)

        self.node.create_subscription(msg_type, TOPICS[topic].name, keep,
                                      qos_profile(TOPICS[topic]))
        return received

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
