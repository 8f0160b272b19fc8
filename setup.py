"""ament_python package: `colcon build` installs it for `ros2 run`; `pip install -e .` too."""

from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "constrained_diffusion_ros"
SHARE = f"share/{PACKAGE}"


def files(pattern: str) -> list[str]:
    return sorted(str(path) for path in Path(".").glob(pattern) if path.is_file())


def model_dirs() -> list[tuple[str, list[str]]]:
    """Each shipped model directory (weights, config, loss curve) goes to share/<pkg>/models."""
    return [(f"{SHARE}/{d}", files(f"{d}/*.*")) for d in sorted(
        str(p.parent) for p in Path("models").glob("*/config.json"))]


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (SHARE, ["package.xml"]),
        (f"{SHARE}/config", files("config/*.yaml") + files("config/*.json")),
        (f"{SHARE}/launch", files("launch/*.xml")),
        *model_dirs(),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="constrained_diffusion_ros team",
    maintainer_email="team@constrained-diffusion-ros.invalid",
    description="Diffusion policy steered away from live restricted zones, for ROS 2 Jazzy.",
    license="MIT",
    entry_points={
        "console_scripts": [
            f"policy_node = {PACKAGE}.nodes.policy_node:main",
            "sim_node = sim_bridge.sim_node:main",
            f"zone_publisher = {PACKAGE}.nodes.zone_publisher:main",
            f"recorder = {PACKAGE}.nodes.recorder:main",
            f"view_node = {PACKAGE}.nodes.view_node:main",
            f"recover_bag = {PACKAGE}.recording.bags:main",
            f"trial = {PACKAGE}.evaluation.trial:main",
            f"train_policy = {PACKAGE}.training.train:main",
            f"evaluate = {PACKAGE}.evaluation.evaluate:main",
            f"latency = {PACKAGE}.evaluation.latency:main",
            f"benchmark_policy = {PACKAGE}.evaluation.benchmark:main",
        ],
        # Restricted areas a scenario can name instead of "package.module:Class"; other
        # packages add theirs to the same group (zones/plugins.py).
        f"{PACKAGE}.restricted_areas": [
            f"camera_zones = {PACKAGE}.examples.camera:CameraZones",
        ],
    },
)
