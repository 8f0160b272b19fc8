"""Fixtures of the ROS/DDS tests: a test node in a ROS domain of the module's own, node
processes from the package's launcher, the simulator node with the test's side of its topics,
and a tiny random policy with fast configurations (so a whole trial takes seconds)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml
from geometry_msgs.msg import PointStamped, PolygonStamped, PoseStamped
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from ros_helpers import SEED, NodeProcesses, Ros, random_domain_id, stamp_ns
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from constrained_diffusion_ros.policy.weights import save_policy
from msg_schemas import FRAME_ID, SERVICES
from sim_bridge.scene import seeded_state

CONFIGURATIONS = {
    "fast_project": {"sampler": "ddim", "denoising_steps": 5, "project": True},
    "fast_none": {"sampler": "ddim", "denoising_steps": 5},
    "fast_inflated": {"sampler": "ddim", "denoising_steps": 5, "project": True, "inflate": True},
    "fast_safe": {"sampler": "ddim", "denoising_steps": 5, "project": True, "inflate": True,
                  "shield": True},
}


@pytest.fixture(scope="module")
def domain_id() -> int:
    return random_domain_id()


@pytest.fixture(scope="module")
def ros(domain_id, request):
    handle = Ros(domain_id, f"test_{request.module.__name__}")
    yield handle
    handle.close()


@pytest.fixture(scope="module")
def log_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("nodes")


@pytest.fixture
def processes(log_dir, domain_id):
    with NodeProcesses(log_dir, domain_id) as started:
        yield started


@pytest.fixture
def tiny_model(make_tiny_policy, tmp_path) -> Path:
    return save_policy(make_tiny_policy(0), tmp_path / "tiny_policy")


@pytest.fixture
def configurations_file(tmp_path) -> Path:
    path = tmp_path / "configurations.yaml"
    path.write_text(yaml.safe_dump(CONFIGURATIONS))
    return path


class SimLink:
    """The sim_node process and the test node's side of its topics."""

    def __init__(self, ros: Ros, process: subprocess.Popen, log: Path) -> None:
        self.ros, self.process, self.log = ros, process, log
        self.pushers = ros.inbox("pusher", PointStamped)
        self.keypoints = ros.inbox("keypoints", PolygonStamped)
        self.poses = ros.inbox("block_pose", PoseStamped)
        self.scores = ros.inbox("score", Float64)
        self.setpoint_pub = ros.publisher("setpoint", PointStamped)
        self.sent = 0  # setpoints published, all kept in the publisher's history
        self.reset_client = ros.node.create_client(Trigger, SERVICES["reset"].name)
        self.params = AsyncParameterClient(ros.node, "sim_node")

    def stamps(self) -> list[int]:
        """Distinct observation stamps in arrival order (the sim re-sends while idle)."""
        return list(dict.fromkeys(stamp_ns(m.header.stamp) for m in self.pushers))

    def latest(self) -> PointStamped:
        return self.pushers[-1]

    def send(self, x: float, y: float, stamp=None) -> None:
        msg = PointStamped()
        msg.header.stamp = stamp if stamp is not None else self.latest().header.stamp
        msg.header.frame_id = FRAME_ID
        msg.point.x, msg.point.y = float(x), float(y)
        self.setpoint_pub.publish(msg)
        self.sent += 1

    def wait_new_stamps(self, before: list[int], n: int, timeout: float = 10.0) -> list[int]:
        assert self.ros.spin_until(lambda: len(self.stamps()) >= len(before) + n, timeout), \
            f"expected {n} new observations, got {len(self.stamps()) - len(before)}"
        return self.stamps()[len(before):]

    def reset(self, seed: int) -> Trigger.Response:
        """Set the seed parameter, call the reset service, wait for the new scene's first
        observation and forget the observations before it (stamps start again at 0)."""
        future = self.params.set_parameters([Parameter("seed", value=seed)])
        assert self.ros.spin_until(future.done, 10.0), "setting the seed parameter timed out"
        assert future.result().results[0].successful
        mark = len(self.pushers)
        future = self.reset_client.call_async(Trigger.Request())
        assert self.ros.spin_until(future.done, 10.0), "reset service timed out"
        if future.result().success:
            start = tuple(seeded_state(seed)[:2])

            def first_of_scene() -> int | None:
                return next((i for i in range(mark, len(self.pushers))
                             if stamp_ns(self.pushers[i].header.stamp) == 0
                             and (self.pushers[i].point.x, self.pushers[i].point.y) == start),
                            None)

            assert self.ros.spin_until(lambda: first_of_scene() is not None, 10.0)
            del self.pushers[:first_of_scene()]
        return future.result()


@pytest.fixture(scope="module")
def sim(ros, log_dir, domain_id):
    started = NodeProcesses(log_dir, domain_id)
    process, log = started.start("sim_node", seed=SEED, mode="lockstep")
    link = SimLink(ros, process, log)
    subscriptions = [s for s in ros.node.subscriptions]
    discovered = ros.spin_until(
        lambda: link.setpoint_pub.get_subscription_count() >= 1
        and all(s.get_publisher_count() >= 1 for s in subscriptions)
        and link.reset_client.service_is_ready() and link.params.services_are_ready()
        and all((link.pushers, link.keypoints, link.poses, link.scores)))
    if not discovered:
        started.stop_all()
        pytest.fail(f"sim_node not discovered; its log:\n{log.read_text()}")
    yield link
    started.stop_all()


# --------------------------------------------------------------------------- sim_node

