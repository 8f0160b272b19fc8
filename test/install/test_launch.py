"""The launch file (XML front-end; the launch packages are not installable here): installed under
share/, and every executable, parameter and argument it names exists."""

from __future__ import annotations

import importlib
import re
import xml.etree.ElementTree as ET

from test_package_layout import REPO, console_scripts, setup_arguments

LAUNCH = REPO / "launch" / "pusht.launch.xml"


def test_the_launch_file_is_installed_under_share() -> None:
    data_files = dict(setup_arguments()["data_files"])
    assert "launch/pusht.launch.xml" in data_files["share/constrained_diffusion_ros/launch"]


def test_every_executable_parameter_and_argument_it_names_exists() -> None:
    root = ET.parse(LAUNCH).getroot()
    scripts = console_scripts(setup_arguments())
    declared = {arg.get("name") for arg in root.iter("arg")}
    used = set(re.findall(r"\$\(var (\w+)\)", LAUNCH.read_text()))
    assert used <= declared and declared <= used  # none undeclared, none unused
    nodes = list(root.iter("node"))
    assert {node.get("exec") for node in nodes} == {"sim_node", "policy_node",
                                                    "zone_publisher", "recorder", "view_node"}
    for node in nodes:
        assert node.get("pkg") == "constrained_diffusion_ros"
        module = importlib.import_module(scripts[node.get("exec")].split(":")[0])
        known = {param.name for param in module.PARAMETERS}
        for param in node.iter("param"):
            assert param.get("name") in known, (node.get("exec"), param.get("name"))
    namespaces = [push.get("namespace") for push in root.iter("push-ros-namespace")]
    assert namespaces == ["$(var namespace)"]


def test_arguments_have_defaults_and_descriptions() -> None:
    for arg in ET.parse(LAUNCH).getroot().iter("arg"):
        assert arg.get("default") is not None and arg.get("description"), arg.get("name")
