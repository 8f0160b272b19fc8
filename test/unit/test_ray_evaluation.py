"""Issue 44: the evaluation on Ray. Units of fixed composition give the same episodes however
they run: here, on a local Ray cluster of one worker or of two, and after a worker is killed
mid-run; an unreachable cluster is one line and exit 2; Ctrl-C keeps the finished cells."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from constrained_diffusion_ros.evaluation import evaluate
from constrained_diffusion_ros.evaluation.runner import (
    evaluate_configurations,
    run_unit,
    study_units,
)
from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.weights import save_policy

ray = pytest.importorskip("ray")

REPO = Path(__file__).resolve().parents[2]
TIMING = {"ms_per_chunk", "ms_per_call", "batch_wall_s"}  # wall clock: differs run to run
# Two sampler groups (DDPM and DDIM), 2 scenarios, 5 seeds in units of 2: 6 units.
STUDY = ["--scenarios", "left_0.5", "center_0.2", "--configs", "none", "ddim10_r_g10_p_safe",
         "--episodes", "5", "--steps", "24", "--unit", "2", "--threads", "1",
         "--ray-threads", "1"]
TASK_TITLE = b"ray::run_unit_task"  # a Ray worker's process title while it runs a unit


def figures(output: Path) -> list[dict]:
    """results.json without its wall-clock fields."""
    cells = json.loads((output / "results.json").read_text())
    return [{k: v for k, v in cell.items() if k not in TIMING} for cell in cells]


def command(*args: str) -> list[str]:
    return [sys.executable, "-m", "constrained_diffusion_ros.evaluation.evaluate", *args]


def environment() -> dict[str, str]:
    """This process's environment for a command, with the module's Ray settings (`ray_temp`)."""
    return {**os.environ, "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def ray_temp() -> Iterator[None]:
    """Ray sessions of this module in a temporary directory removed afterwards (short: Ray's
    socket paths must fit in 107 characters), without the token Ray would otherwise write to
    ~/.ray for a new local cluster."""
    directory = tempfile.mkdtemp(prefix="rayt", dir="/tmp")
    wanted = {"RAY_TMPDIR": directory, "RAY_AUTH_MODE": "disabled"}
    before = {name: os.environ.get(name) for name in wanted}
    os.environ.update(wanted)
    yield
    for name, value in before.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
    shutil.rmtree(directory, ignore_errors=True)


@pytest.fixture(scope="module")
def cluster(ray_temp: None) -> Iterator[str]:
    """A local cluster of two worker CPUs for this module; its GCS address."""
    context = ray.init(address="local", num_cpus=2, include_dashboard=False,
                       logging_level="ERROR")
    yield context.address_info["gcs_address"]
    ray.shutdown()


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import torch

    from constrained_diffusion_ros.policy.policy_config import PolicyConfig

    torch.manual_seed(0)
    stats = {"obs": {"min": [0.0] * 20, "max": [512.0] * 20},
             "action": {"min": [0.0, 0.0], "max": [512.0, 512.0]}}
    policy = DiffusionPolicy(PolicyConfig(down_dims=(16, 32, 64), normalizer=stats)).eval()
    return save_policy(policy, tmp_path_factory.mktemp("model"))


@pytest.fixture(scope="module")
def local_figures(model: Path, tmp_path_factory: pytest.TempPathFactory) -> list[dict]:
    """The study run here, unit after unit: what every Ray run must equal."""
    output = tmp_path_factory.mktemp("local")
    assert evaluate.main(["--model", str(model), *STUDY, "--output", str(output)]) == 0
    cells = figures(output)
    assert len(cells) == 4 and all(c["episodes"] == 5 for c in cells)
    assert sum(c["r"] for c in cells if c["configuration"] == "none") > 0  # not all zeros
    return cells


def test_a_unit_run_alone_gives_the_rows_it_gives_in_a_study(
        tiny_policy: DiffusionPolicy) -> None:
    scenarios = load_scenarios()
    chosen = [scenarios["left_0.5"], scenarios["hand_homing@100"]]
    configs = [ConstraintConfig("blind", sampler="ddim", denoising_steps=2),
               ConstraintConfig("projected", sampler="ddim", denoising_steps=2, project=True)]
    seeds = list(range(100000, 100005))
    units = study_units(2, seeds, 2, noise_seed=7)
    assert [(u.group, u.seeds, u.noise_seed) for u in units[:3]] == [
        (0, (100000, 100001), 7), (0, (100002, 100003), 9), (0, (100004,), 11)]
    assert [u.group for u in units] == [0, 0, 0, 1, 1, 1]
    cells, log, first_rows = evaluate_configurations(
        tiny_policy, configs, [chosen, chosen], seeds, n_steps=6, progress=False, unit_size=2)
    # The merged log is laid out as one batch of all the seeds: block by block, seeds in order.
    assert log.seeds == seeds * 4  # blind: one block (the homing zone has its own), projected: 2
    assert first_rows[("left_0.5", "projected")] == 10
    middle = run_unit(tiny_policy, configs, [chosen, chosen], (100002, 100003), 6,
                      noise_seed=2).log
    for block in range(4):
        np.testing.assert_array_equal(log.commanded[5 * block + 2: 5 * block + 4],
                                      middle.commanded[2 * block: 2 * block + 2])
    assert {c.batch for c in cells} == {8}  # 4 blocks x 2 seeds: the largest unit's batch
    again, _, _ = evaluate_configurations(
        tiny_policy, configs, [chosen, chosen], seeds, n_steps=6, progress=False, unit_size=2)
    assert [c.s for c in again] == [c.s for c in cells]


def test_local_and_ray_with_one_and_two_workers_give_the_same_figures(
        cluster: str, model: Path, local_figures: list[dict], ray_temp: None,
        tmp_path: Path) -> None:
    two = tmp_path / "two"  # the module's cluster of two workers, from this process
    assert evaluate.main(["--model", str(model), *STUDY, "--output", str(two), "--ray"]) == 0
    assert "as Ray tasks" in (two / "table.md").read_text()
    one = tmp_path / "one"  # a cluster of one worker that the command starts and stops
    done = subprocess.run(command("--model", str(model), *STUDY, "--output", str(one),
                                  "--ray", "--ray-workers", "1"),
                          capture_output=True, text=True, timeout=300, env=environment(), cwd=REPO)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "as Ray tasks" in (one / "table.md").read_text()
    assert figures(two) == local_figures
    assert figures(one) == local_figures


def test_a_worker_killed_mid_run_costs_no_episode(
        cluster: str, model: Path, local_figures: list[dict], ray_temp: None,
        tmp_path: Path) -> None:
    """The driver runs in its own process against the module's cluster; a worker running a
    unit is killed; its unit is run again and counted once."""
    output = tmp_path / "killed"
    driver = subprocess.Popen(command("--model", str(model), *STUDY, "--output", str(output),
                                      "--ray", cluster),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env=environment(), cwd=REPO)
    killed = None
    deadline = time.monotonic() + 240
    while killed is None and driver.poll() is None and time.monotonic() < deadline:
        running = running_units()
        if running:
            killed = running[0]
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.02)
    _, err = driver.communicate(timeout=300)
    assert killed is not None, f"no worker was seen running a unit: {err[-2000:]}"
    assert driver.returncode == 0, err[-2000:]
    assert figures(output) == local_figures  # each episode once: the same means and counts


def running_units() -> list[int]:
    """Process ids of this machine's Ray workers running a unit now."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if (entry / "cmdline").read_bytes().startswith(TASK_TITLE):
                    pids.append(int(entry.name))
            except OSError:
                continue
    return pids


@pytest.mark.parametrize("address", ["127.0.0.1:1", "ray://127.0.0.1:1"])
def test_an_unreachable_cluster_is_one_line_and_exit_2(
        model: Path, tmp_path: Path, address: str, capsys: pytest.CaptureFixture[str]) -> None:
    code = evaluate.main(["--model", str(model), *STUDY, "--output", str(tmp_path / "o"),
                          "--ray", address])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"evaluate: error: cannot reach the Ray cluster at {address}")
    assert len(err.splitlines()) == 1, err
    assert not (tmp_path / "o" / "results.json").exists()


@pytest.mark.parametrize("on_ray", [False, True], ids=["here", "ray"])
def test_ctrl_c_keeps_the_finished_cells_and_exits_130(
        model: Path, tmp_path: Path, on_ray: bool, request: pytest.FixtureRequest) -> None:
    """Interrupted once the first sampler group is done, the run writes that group's cells."""
    output = tmp_path / "stopped"
    ray_args = ["--ray", request.getfixturevalue("cluster")] if on_ray else []
    driver = subprocess.Popen(
        command("--model", str(model), "--scenarios", "left_0.5", "center_0.2", "--configs",
                "ddim10_r_g10_p_safe", "none", "--episodes", "6", "--steps", "40", "--unit",
                "1", "--threads", "1", "--output", str(output), *ray_args),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
        env=environment())
    for line in driver.stdout:
        if line.startswith("ddim10_r_g10_p_safe: 2 cells"):
            driver.send_signal(signal.SIGINT)
            break
    _, err = driver.communicate(timeout=300)
    assert driver.returncode == 130, err[-2000:]
    assert "interrupted; 2 finished cells written to" in err
    cells = json.loads((output / "results.json").read_text())
    assert sorted((c["scenario"], c["configuration"]) for c in cells) == [
        ("center_0.2", "ddim10_r_g10_p_safe"), ("left_0.5", "ddim10_r_g10_p_safe")]
    assert all(c["episodes"] == 6 for c in cells)


def test_a_run_without_ray_does_not_import_it(model: Path, tmp_path: Path) -> None:
    probe = ("import sys\nfrom constrained_diffusion_ros.evaluation import evaluate\n"
             f"code = evaluate.main(['--model', {str(model)!r}, '--scenarios', 'left_0.5', "
             f"'--configs', 'none', '--episodes', '1', '--steps', '2', '--threads', '1', "
             f"'--output', {str(tmp_path / 'o')!r}])\n"
             "print('ray imported:', 'ray' in sys.modules, 'code:', code)\n")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          timeout=300, env=environment(), cwd=REPO)
    assert "ray imported: False code: 0" in done.stdout, done.stderr[-2000:]


def test_latency_on_ray_gives_the_rows_it_gives_here(cluster: str, model: Path,
                                                      tmp_path: Path) -> None:
    from constrained_diffusion_ros.evaluation import latency

    study = ["--model", str(model), "--configs", "ddim10_r_g10_p_safe", "--scenarios",
             "center_0.2", "--delays", "0", "2", "--every-tick", "--episodes", "3", "--steps",
             "20", "--unit", "2", "--threads", "1"]
    assert latency.main([*study, "--output", str(tmp_path / "here")]) == 0
    assert latency.main([*study, "--output", str(tmp_path / "ray"), "--ray"]) == 0
    here = json.loads((tmp_path / "here" / "latency.json").read_text())
    assert [(r["delay"], r["handover"]) for r in here] == [
        (0, "none"), (2, "sync"), (2, "async"), (2, "async_prefix")]
    assert json.loads((tmp_path / "ray" / "latency.json").read_text()) == here
