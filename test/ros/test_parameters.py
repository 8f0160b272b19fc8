"""Parameters: one table per node, with descriptors, checked with a reason, and `--help`."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from constrained_diffusion_ros.evaluation.launcher import random_domain_id
from constrained_diffusion_ros.nodes import policy_parameters, recorder, zone_publisher
from node_support.parameters import Param, declare, usage
from sim_bridge import sim_node

NODES = {"policy_node": policy_parameters, "sim_node": sim_node, "recorder": recorder,
         "zone_publisher": zone_publisher}
REPO = Path(__file__).resolve().parents[2]
LIFETIME = Param("zone_lifetime", 0.0, "s", low=0.0)


def test_a_double_takes_an_integer_and_refuses_nan_negative_and_text() -> None:
    assert LIFETIME.reason(2) is None and LIFETIME.reason(2.5) is None
    assert "finite number" in LIFETIME.reason(math.nan)
    assert "[0, inf]" in LIFETIME.reason(-1.0)
    assert "finite number" in LIFETIME.reason("2")
    assert "finite number" in LIFETIME.reason(True)


def test_choices_lists_and_integers_are_checked() -> None:
    mode = Param("mode", "lockstep", "", choices=("lockstep", "realtime"))
    assert "one of ['lockstep', 'realtime']" in mode.reason("fast")
    workspace = Param("robot.workspace", [0.0, 0.0, 512.0, 512.0], "")
    assert "4 numbers" in workspace.reason([0.0, 1.0])
    threads = Param("torch_threads", 1, "", low=1, high=256)
    assert threads.reason(0) and threads.reason(1.5) and threads.reason(4) is None


def test_descriptors_carry_description_range_and_read_only() -> None:
    rate = Param("rate_hz", 10.0, "setpoints per second", read_only=True, low=0.1)
    descriptor = rate.descriptor()
    assert descriptor.description == "setpoints per second" and descriptor.read_only
    assert descriptor.floating_point_range[0].from_value == pytest.approx(0.1)
    assert descriptor.dynamic_typing  # so that `-p rate_hz:=20` (an integer) is taken


@pytest.mark.parametrize("name", sorted(NODES))
def test_every_parameter_has_a_description_and_a_valid_default(name: str) -> None:
    for param in NODES[name].PARAMETERS:
        assert param.description and param.reason(param.default) is None, param.name


def test_usage_lists_parameters_and_the_nodes_own_topics() -> None:
    text = usage("policy_node", "The policy.", policy_parameters.PARAMETERS)
    assert "zone_lifetime (default 0.0, range [0, inf])" in text
    assert "subscribes zones (geometry_msgs/msg/PolygonInstanceStamped)" in text
    assert "publishes setpoint" in text and "serves clear_zones" in text
    assert "publishes pusher" not in text  # the simulator's


@pytest.mark.parametrize("module", ["sim_bridge.sim_node", "constrained_diffusion_ros.nodes."
                                    "recorder", "constrained_diffusion_ros.nodes.policy_node"])
def test_help_prints_usage_and_exits_without_starting_the_node(module: str, tmp_path) -> None:
    done = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True,
                          text=True, timeout=120, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: ") and "parameters:" in done.stdout
    assert list(tmp_path.iterdir()) == []  # the recorder wrote no bag


@pytest.mark.parametrize(("parameter", "words"), [("device:=cuda:99", "not available"),
                                                  ("device:=abacus", "unknown device")])
def test_a_device_that_is_not_here_stops_the_node_in_one_line(parameter: str, words: str,
                                                                tmp_path) -> None:
    done = subprocess.run([sys.executable, "-m", "constrained_diffusion_ros.nodes.policy_node",
                           "--ros-args", "-p", parameter], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(REPO),
                               "ROS_DOMAIN_ID": str(random_domain_id())})
    assert done.returncode == 2  # bad input, as a bad command line
    output = (done.stdout + done.stderr).strip().splitlines()
    assert len(output) == 1 and words in output[0], output
    assert "Traceback" not in done.stderr


def test_an_integer_given_for_a_double_is_held_as_a_double() -> None:
    """README: `zone_lifetime:=2` is taken as 2.0, at start and when set at run time; a read-only
    double stays read-only and its range stays in its descriptor."""
    context = Context()
    rclpy.init(context=context, domain_id=random_domain_id())
    node = Node("doubles", context=context, parameter_overrides=[
        Parameter("zone_lifetime", value=2), Parameter("rate_hz", value=20)])
    try:
        rate = Param("rate_hz", 10.0, "setpoints per second", read_only=True, low=0.1)
        assert declare(node, [LIFETIME, rate]) == {"zone_lifetime": 2.0, "rate_hz": 20.0}
        for name, value in (("zone_lifetime", 2.0), ("rate_hz", 20.0)):
            held = node.get_parameter(name)
            assert held.type_ == Parameter.Type.DOUBLE and held.value == value, name
        assert node.describe_parameter("rate_hz").read_only
        assert node.describe_parameter("zone_lifetime").floating_point_range[0].from_value == 0
        assert node.set_parameters([Parameter("zone_lifetime", value=3)])[0].successful
        held = node.get_parameter("zone_lifetime")
        assert held.type_ == Parameter.Type.DOUBLE and held.value == 3.0
        assert not node.set_parameters([Parameter("zone_lifetime", value=-1)])[0].successful
        assert not node.set_parameters([Parameter("rate_hz", value=5.0)])[0].successful
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)


@pytest.mark.parametrize(("arguments", "words"), [
    (["-p", "mode=realtime"], "Couldn't parse parameter override rule: '-p mode=realtime'"),
    (["--bogus"], "unknown ROS arguments ['--bogus']")])
def test_ros_arguments_rclpy_cannot_parse_are_one_line_and_exit_code_2(
        arguments: list[str], words: str, tmp_path) -> None:
    """Issue 26, finding 8: rclpy's traceback before."""
    done = subprocess.run([sys.executable, "-m", "constrained_diffusion_ros.nodes.policy_node",
                           "--ros-args", *arguments], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(REPO),
                               "ROS_DOMAIN_ID": str(random_domain_id())})
    assert done.returncode == 2
    output = (done.stdout + done.stderr).strip().splitlines()
    assert len(output) == 1 and output[0].startswith("policy_node: error: "), output
    assert words in output[0] and "Traceback" not in done.stderr
