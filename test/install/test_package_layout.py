"""The ament_python layout: package.xml agrees with setup.py, and colcon (from PyPI) builds the
package into an install space where `ros2 run` would find every executable and the share files."""

from __future__ import annotations

import ast
import contextlib
import os
import runpy
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from unittest import mock

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGE = "constrained_diffusion_ros"
VENV_BIN = Path(sys.executable).parent
# What the package ships when git cannot say (no checkout): sources, data and build files.
SHIPPED = ("package.xml", "setup.py", "setup.cfg", "resource", PACKAGE, "sim_bridge",
           "msg_schemas", "node_support", "config", "launch", "models")
REQUIRED_EXEC_DEPENDS = {"rclpy", "geometry_msgs", "nav_msgs", "visualization_msgs", "std_srvs"}


def setup_arguments() -> dict[str, Any]:
    """What setup.py passes to setuptools.setup, read by running it with setup() stubbed."""
    captured: dict[str, Any] = {}
    with mock.patch("setuptools.setup", lambda **kwargs: captured.update(kwargs)), \
            contextlib.chdir(REPO):
        runpy.run_path(str(REPO / "setup.py"))
    assert captured, "setup.py did not call setuptools.setup"
    return captured


def console_scripts(arguments: dict[str, Any]) -> dict[str, str]:
    """{executable name: "module:function"} from setup()'s entry_points."""
    scripts = {}
    for line in arguments.get("entry_points", {}).get("console_scripts", []):
        name, _, target = line.partition("=")
        scripts[name.strip()] = target.strip()
    return scripts


def package_files() -> list[str]:
    """Paths (relative to the checkout) of the files a clone would hold: tracked ones and new ones
    git does not ignore, so work in progress is built too; without git, the SHIPPED trees."""
    if shutil.which("git") and (REPO / ".git").exists():
        listing = subprocess.run(
            ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
            cwd=REPO, capture_output=True, check=True).stdout.decode()
        return [name for name in listing.split("\0") if name and (REPO / name).is_file()]
    names = []
    for entry in SHIPPED:
        path = REPO / entry
        found = [path] if path.is_file() else sorted(path.rglob("*")) if path.is_dir() else []
        names += [str(p.relative_to(REPO)) for p in found if p.is_file()
                  and "__pycache__" not in p.parts and "checkpoint" not in p.parts]
    return names


# -- Fast: the manifest ------------------------------------------------------------------------

def test_package_xml_is_format_3_and_matches_setup_py() -> None:
    root = ET.parse(REPO / "package.xml").getroot()
    arguments = setup_arguments()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == arguments["name"] == PACKAGE
    assert root.findtext("version") == arguments["version"]
    assert root.findtext("export/build_type") == "ament_python"
    exec_depends = {element.text for element in root.findall("exec_depend")}
    missing = REQUIRED_EXEC_DEPENDS - exec_depends
    assert not missing, f"package.xml lacks exec_depend on {sorted(missing)}"
    # The ament index marker that setup.py installs, and the script directory ros2 run searches.
    assert (REPO / "resource" / PACKAGE).is_file()
    assert f"$base/lib/{PACKAGE}" in (REPO / "setup.cfg").read_text()


def test_every_console_script_points_at_a_function_in_the_package() -> None:
    """Checked in the source, without importing it (nodes import rclpy)."""
    scripts = console_scripts(setup_arguments())
    assert "train_policy" in scripts
    for name, target in scripts.items():
        module, _, function = target.partition(":")
        assert module and function, f"{name}: malformed entry point {target!r}"
        path = REPO / (module.replace(".", "/") + ".py")
        assert path.is_file(), f"{name}: {module} has no source file {path}"
        tree = ast.parse(path.read_text())
        defined = {node.name for node in tree.body if isinstance(node, ast.FunctionDef)}
        assert function in defined, f"{name}: {module} defines no function {function}()"


def test_the_launcher_starts_the_executables_ros2_run_would() -> None:
    """The node processes of trials, benchmarks and tests run the console scripts' modules."""
    from constrained_diffusion_ros.evaluation.launcher import NODES

    scripts = console_scripts(setup_arguments())
    assert NODES and {name: f"{module}:main" for name, module in NODES.items()} == {
        name: scripts[name] for name in NODES}


# -- Slow: a real colcon build -------------------------------------------------------------------

@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Builds a copy of the package in a fresh workspace; yields the workspace."""
    colcon = VENV_BIN / "colcon"
    if not colcon.is_file():
        pytest.fail(f"{colcon} not found: run `make setup` (requirements-test.txt pins "
                    "colcon-core and colcon-ros)")
    workspace = tmp_path_factory.mktemp("ws")
    source = workspace / "src" / PACKAGE
    for name in package_files():
        target = source / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / name, target)
    env = {key: value for key, value in os.environ.items()
           if key not in {"PYTHONPATH", "AMENT_PREFIX_PATH", "COLCON_PREFIX_PATH"}}
    env.update(PATH=f"{VENV_BIN}{os.pathsep}{env.get('PATH', '')}",
               COLCON_HOME=str(workspace / "colcon_home"))  # no user defaults
    result = subprocess.run(
        [str(colcon), "build", "--base-paths", "src", "--build-base", "build",
         "--install-base", "install"],
        cwd=workspace, env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, (
        f"colcon build failed ({result.returncode}):\n{result.stdout[-4000:]}\n"
        f"{result.stderr[-4000:]}")
    yield workspace


def test_colcon_identifies_an_ament_python_package(colcon_install: Path) -> None:
    log = (colcon_install / "log" / "latest_build" / "logger_all.log").read_text()
    assert f"with type 'ros.ament_python' and name '{PACKAGE}'" in log


def test_colcon_installs_every_console_script_where_ros2_run_looks(
        colcon_install: Path) -> None:
    scripts = console_scripts(setup_arguments())
    directory = colcon_install / "install" / PACKAGE / "lib" / PACKAGE
    for name in scripts:
        script = directory / name
        assert script.is_file(), f"{name} not installed in {directory}"
        assert os.access(script, os.X_OK), f"{script} is not executable"
        assert script.read_text().startswith("#!"), f"{script} has no interpreter line"
    assert sorted(p.name for p in directory.iterdir()) == sorted(scripts)


def test_colcon_installs_the_share_files_and_the_ament_index_marker(
        colcon_install: Path) -> None:
    prefix = colcon_install / "install" / PACKAGE
    marker = prefix / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE
    assert marker.is_file()
    share = prefix / "share" / PACKAGE
    assert (share / "package.xml").read_text() == (REPO / "package.xml").read_text()
    configs = sorted(p.name for p in (REPO / "config").glob("*.yaml"))
    assert configs and sorted(p.name for p in (share / "config").glob("*.yaml")) == configs
    source = colcon_install / "src" / PACKAGE
    for model in sorted((source / "models").glob("*/config.json")):
        installed = share / "models" / model.parent.name
        assert (installed / "config.json").is_file(), installed
        for weights in model.parent.glob("*.safetensors"):
            assert (installed / weights.name).is_file(), installed / weights.name


def test_the_install_space_is_self_contained(colcon_install: Path) -> None:
    """Every top-level Python package is installed, and from the install space (not the
    checkout) the package finds its config through the ament index."""
    prefix = colcon_install / "install" / PACKAGE
    site = prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / \
        "site-packages"
    source = colcon_install / "src" / PACKAGE
    packages = sorted(p.parent.name for p in source.glob("*/__init__.py")
                      if p.parent.name != "test")
    assert PACKAGE in packages and "sim_bridge" in packages
    for name in packages:
        assert (site / name / "__init__.py").is_file(), f"{name} not installed"
    probe = ("import constrained_diffusion_ros.paths as p; "
             "print(p.__file__); print(p.config_dir())")
    env = dict(os.environ, PYTHONPATH=str(site), AMENT_PREFIX_PATH=str(prefix))
    result = subprocess.run([sys.executable, "-c", probe], cwd=colcon_install, env=env,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    module_file, config = result.stdout.split()
    assert Path(module_file).is_relative_to(site)
    assert Path(config) == prefix / "share" / PACKAGE / "config"
