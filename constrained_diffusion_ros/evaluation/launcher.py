"""Node processes for a trial, a benchmark or a test: one launcher, as a launch file would do it,
and one harness that drives them (`Stack`).

Each caller picks the ROS domain its nodes run in (so runs side by side do not hear each
other) and every process gets its compute threads set on purpose: torch takes one thread per
core by default, and several processes doing so on a small machine slow each other down many
times over. Processes stop like Ctrl-C (SIGINT), and are killed if they do not.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

NODES = {  # executable name -> python module (the console scripts of setup.py)
    "policy_node": "constrained_diffusion_ros.nodes.policy_node",
    "zone_publisher": "constrained_diffusion_ros.nodes.zone_publisher",
    "recorder": "constrained_diffusion_ros.nodes.recorder",
    "view_node": "constrained_diffusion_ros.nodes.view_node",
    "sim_node": "sim_bridge.sim_node",
}
ROOT = Path(__file__).resolve().parents[2]


def random_domain_id() -> int:
    """A ROS domain id in [1, 100], so a run is unlikely to share its domain with another."""
    return random.SystemRandom().randint(1, 100)


def parameter_text(value: object) -> str:
    """A value as `--ros-args -p name:=value` wants it (YAML): text quoted, so that a name
    like "100" or "{a: 1}" stays a string."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str | os.PathLike):
        return json.dumps(str(value))
    return str(value)


class NodeProcesses:
    """Started node processes, by name; logs go to `log_dir/<name>.log`."""

    def __init__(self, log_dir: Path, domain_id: int, threads: int = 1) -> None:
        self.log_dir, self.domain_id, self.threads = Path(log_dir), domain_id, threads
        self.processes: dict[str, subprocess.Popen] = {}

    def environment(self, threads: int | None = None) -> dict[str, str]:
        threads = str(threads or self.threads)
        return {**os.environ, "ROS_DOMAIN_ID": str(self.domain_id), "OMP_NUM_THREADS": threads,
                "MKL_NUM_THREADS": threads, "PYTHONUNBUFFERED": "1",
                "RCUTILS_LOGGING_BUFFERED_STREAM": "0",
                "ROS_LOG_DIR": str(self.log_dir / "ros_log"),
                "ROS_HOME": str(self.log_dir / "ros_home")}  # what nodes remember: per run

    def start(self, name: str, node: str | None = None, remap: dict[str, str] | None = None,
              threads: int | None = None, **parameters: object
              ) -> tuple[subprocess.Popen, Path]:
        """Starts executable `node` (default: `name`) with parameters and remappings; returns
        the process and its log file."""
        args = [sys.executable, "-m", NODES[node or name], "--ros-args"]
        for source, target in (remap or {}).items():
            args += ["-r", f"{source}:={target}"]
        for key, value in parameters.items():
            args += ["-p", f"{key}:={parameter_text(value)}"]
        log = self.log_dir / f"{name}.log"
        with log.open("w") as out:
            self.processes[name] = subprocess.Popen(
                args, cwd=ROOT, env=self.environment(threads), stdout=out,
                stderr=subprocess.STDOUT)
        return self.processes[name], log

    def failed(self) -> str | None:
        """Which process has exited, if any (while all should run)."""
        for name, process in self.processes.items():
            if process.poll() is not None:
                return f"{name} exited with code {process.returncode} (see " \
                       f"{self.log_dir / (name + '.log')})"
        return None

    def logs(self) -> str:
        """Every node log in the log directory, for a failure message."""
        return "\n".join(f"--- {path.name}\n{path.read_text(errors='replace')}"
                         for path in sorted(self.log_dir.glob("*.log")))

    def stop(self, name: str, timeout: float = 10.0) -> int | None:
        """SIGINT, then kill after `timeout`; returns the exit code (None: not running)."""
        process = self.processes.pop(name, None)
        if process is None:
            return None
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
        return _wait(process, timeout)

    def stop_all(self, timeout: float = 10.0) -> None:
        """All at once, then wait: they stop in parallel."""
        for process in self.processes.values():
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        for process in self.processes.values():
            _wait(process, timeout)
        self.processes.clear()

    def __enter__(self) -> NodeProcesses:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop_all()


class Stack:
    """A stack of node processes and a client node of the caller's own that drives them, in
    one ROS domain: what `trial` and the live benchmarks start, watch and stop.

    `wait_for` spins the client until a condition holds, and fails at once, naming it, when a
    node process has exited (a wait on a dead node does not sit out its timeout);
    `transition` takes the policy node through a lifecycle transition, as nav2's lifecycle
    manager asks; `close` stops the processes and the client. The client node is `node`
    (namespace /pusht) on `executor`, in `context`."""

    def __init__(self, name: str, log_dir: Path, domain_id: int | None = None) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        from msg_schemas import NAMESPACE

        self.domain_id = random_domain_id() if domain_id is None else domain_id
        self.processes = NodeProcesses(log_dir, self.domain_id)
        self.context = Context()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.node = rclpy.create_node(name, namespace=NAMESPACE, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.logs: dict[str, Path] = {}  # node name -> its log file
        self._lifecycle = None  # the policy node's change_state client, once asked

    def start(self, name: str, **parameters: object) -> Path:
        """Start node `name` (`NodeProcesses.start`'s arguments); its log file."""
        _, self.logs[name] = self.processes.start(name, **parameters)
        return self.logs[name]

    def failed(self) -> str | None:
        return self.processes.failed()

    def wait_for(self, condition: Callable[[], bool], what: str, timeout_s: float | None = None,
                 *, deadline: float | None = None, period_s: float = 0.02) -> None:
        """Spin the client until `condition()` holds; RuntimeError "timed out waiting for
        <what>" past `timeout_s` from now or the time.monotonic() `deadline`, or naming the
        node process that exited."""
        from node_support.spin import spin_until

        spin_until(self.executor, condition, timeout_s, deadline=deadline, period_s=period_s,
                   failed=self.failed, what=what)

    def call(self, client, request, what: str, timeout_s: float = 30.0,
             deadline: float | None = None):
        """A service's answer, once the service is there (`wait_for`'s failures)."""
        if deadline is None:
            deadline = time.monotonic() + timeout_s
        self.wait_for(client.service_is_ready, f"the {what} service", deadline=deadline)
        answer = client.call_async(request)
        self.wait_for(answer.done, what, deadline=deadline)
        return answer.result()

    def transition(self, label: str, deadline: float | None = None) -> None:
        """The policy node (the managed one) through lifecycle transition `label`
        (configure, activate, ...); ValueError naming its log if it refuses."""
        from lifecycle_msgs.srv import ChangeState

        from msg_schemas import SERVICES

        if self._lifecycle is None:
            self._lifecycle = self.node.create_client(ChangeState,
                                                      SERVICES["change_state"].name)
        request = ChangeState.Request()
        request.transition.label = label
        answer = self.call(self._lifecycle, request, f"the policy node to {label}",
                           deadline=deadline)
        if not answer.success:
            raise ValueError(f"the policy node could not {label} (see "
                             f"{self.logs.get('policy_node', 'its log')})")

    def close(self) -> None:
        """Stop every node process (at once, SIGINT then kill), then the client."""
        import rclpy

        try:
            self.processes.stop_all()
        finally:
            self.executor.shutdown()
            self.node.destroy_node()
            rclpy.try_shutdown(context=self.context)

    def __enter__(self) -> Stack:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def _wait(process: subprocess.Popen, timeout: float) -> int:
    try:
        return process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.wait()
