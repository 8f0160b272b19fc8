"""Issue 45: every console script answers `--help` before it imports torch, rclpy or the other
heavy modules (seconds of imports on a small machine). Checked by what a `--help` imported, not
by how long it took, so that a loaded machine cannot fail it."""

from __future__ import annotations

import contextlib
import json
import math
import os
import runpy
import subprocess
import sys
from pathlib import Path
from typing import Any
from unittest import mock

import pytest

REPO = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "rclpy", "shapely", "matplotlib", "onnxruntime", "diffusers", "zarr", "ray")
# Runs an entry point as its console script would with `--help`, then says which heavy modules
# had been imported by then.
PROBE = """
import importlib, json, sys
name, target, heavy = sys.argv[1], sys.argv[2], sys.argv[3].split(",")
module, function = target.split(":")
sys.argv = [name, "--help"]
try:
    code = getattr(importlib.import_module(module), function)()
except SystemExit as stop:
    code = stop.code
sys.stdout.flush()
print("\\n@@ " + json.dumps({"code": code or 0, "heavy": sorted(set(sys.modules) & set(heavy))}))
"""


def setup_arguments() -> dict[str, Any]:
    """What setup.py passes to setuptools.setup (run with setup() stubbed)."""
    captured: dict[str, Any] = {}
    with mock.patch("setuptools.setup", lambda **kwargs: captured.update(kwargs)), \
            contextlib.chdir(REPO):
        runpy.run_path(str(REPO / "setup.py"))
    return captured


def console_scripts() -> dict[str, str]:
    """{executable name: "module:function"} from setup.py."""
    lines = setup_arguments()["entry_points"]["console_scripts"]
    return {name.strip(): target.strip() for name, _, target in
            (line.partition("=") for line in lines)}


SCRIPTS = console_scripts()


def test_every_console_script_is_checked() -> None:
    assert len(SCRIPTS) >= 11 and {"policy_node", "train_policy", "trial"} <= set(SCRIPTS)


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_help_prints_usage_without_importing_heavy_modules(name: str) -> None:
    done = subprocess.run([sys.executable, "-c", PROBE, name, SCRIPTS[name], ",".join(HEAVY)],
                          capture_output=True, text=True, timeout=120, cwd=REPO,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr
    text, _, said = done.stdout.rpartition("\n@@ ")
    result = json.loads(said)
    assert result["code"] == 0, done.stderr
    assert text.startswith("usage: ") and name in text.splitlines()[0], text[:200]
    assert result["heavy"] == [], f"{name} --help imported {result['heavy']}"


def test_the_defaults_help_shows_are_the_cores() -> None:
    """The defaults written out so that `--help` needs no torch equal those of the modules that
    own them."""
    from constrained_diffusion_ros.evaluation import distributed, latency
    from constrained_diffusion_ros.evaluation.runner import DEFAULT_SEEDS, DEFAULT_UNIT_SIZE
    from constrained_diffusion_ros.nodes import policy_parameters as written
    from constrained_diffusion_ros.nodes import view_node, zone_publisher
    from constrained_diffusion_ros.policy import device, inference
    from constrained_diffusion_ros.pusht import PUSHT_ROBOT
    from constrained_diffusion_ros.zones import grid, live, motion

    caps = grid.MaskCaps()
    defaults = {param.name: param.default for param in written.PARAMETERS}
    view_defaults = {param.name: param.default for param in view_node.PARAMETERS}
    pairs = {  # what --help shows: (written out, the owner's)
        "DEVICES": (written.DEVICES, device.DEVICES),
        "RUNTIMES": (written.RUNTIMES, inference.RUNTIMES),
        "DEFAULT_THRESHOLD": (written.DEFAULT_THRESHOLD, grid.DEFAULT_THRESHOLD),
        "MASK_PIECES": (written.MASK_PIECES, caps.pieces),
        "MASK_VERTICES": (written.MASK_VERTICES, caps.vertices),
        "MASK_CELLS": (written.MASK_CELLS, caps.cells),
        "DEFAULT_MAX_ZONES": (written.DEFAULT_MAX_ZONES, live.DEFAULT_MAX_ZONES),
        "DEFAULT_MAX_VERTICES": (written.DEFAULT_MAX_VERTICES, live.DEFAULT_MAX_VERTICES),
        "DEFAULT_SPEED_BOUND": (written.DEFAULT_SPEED_BOUND, motion.DEFAULT_SPEED_BOUND),
        "HEADROOM": (written.HEADROOM, motion.HEADROOM),
        "robot.workspace": (defaults["robot.workspace"],
                            [float(v) for v in PUSHT_ROBOT.workspace]),
        **{f"robot.{field}": (defaults[f"robot.{field}"], float(getattr(PUSHT_ROBOT, field)))
           for field in written.ROBOT_FIELDS},
        "zone_publisher.MAX_KEEPOUT_CELLS": (zone_publisher.MAX_KEEPOUT_CELLS,
                                             math.isqrt(caps.cells)),
        "view_node max_vertices": (view_defaults["max_vertices"], live.DEFAULT_MAX_VERTICES),
        "latency.DEFAULT_EPISODES": (latency.DEFAULT_EPISODES, len(DEFAULT_SEEDS)),
        "distributed.DEFAULT_UNIT_SIZE": (distributed.DEFAULT_UNIT_SIZE, DEFAULT_UNIT_SIZE),
    }
    assert {name: pair for name, pair in pairs.items() if pair[0] != pair[1]} == {}
