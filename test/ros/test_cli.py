"""Every bad file and argument a command can be given: exit code 2, one line on stderr naming the
fault, no traceback; --debug shows the traceback instead."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from constrained_diffusion_ros.evaluation import benchmark, evaluate, latency, trial
from constrained_diffusion_ros.paths import config_dir
from constrained_diffusion_ros.policy.weights import save_policy
from constrained_diffusion_ros.recording import bags
from constrained_diffusion_ros.training import train
from constrained_diffusion_ros.training.dataset import load_demonstrations
from msg_schemas.text import LINE_LIMIT, one_line

COMMANDS: dict[str, Callable[[list[str]], int]] = {
    "evaluate": evaluate.main, "train_policy": train.main, "latency": latency.main,
    "benchmark_policy": benchmark.main, "trial": trial.main, "recover_bag": bags.main}


@pytest.fixture
def files(tmp_path: Path, make_tiny_policy, dataset_path: Path) -> dict[str, Path]:
    """The paths the cases below refer to as {name}, each broken in its own way."""
    model = save_policy(make_tiny_policy(0), tmp_path / "model")
    paths = {"tmp": tmp_path, "model": model, "dataset": dataset_path}

    def config_copy(name: str, file: str, text: str) -> None:
        paths[name] = shutil.copytree(config_dir(), tmp_path / name)
        (paths[name] / file).write_text(text)

    config_copy("yaml_syntax", "configurations.yaml", "a: [\n")
    config_copy("top_list", "configurations.yaml", "- a\n")
    config_copy("push_abc", "configurations.yaml", "r: {push: abc}\n")
    config_copy("python_tag", "configurations.yaml",
                "x: !!python/object/apply:os.system ['echo hi']\n")
    config_copy("bad_scenarios", "scenarios.yaml", "center: {zones: [[1, 2]]}\n")
    reused = tmp_path / "reused"
    reused.mkdir()
    (reused / "results.json").write_text("[{\"scenario\": ")
    paths["reused"] = reused
    for name, change in {"horizon": {"horizon": 15}, "action_steps": {"n_action_steps": 20},
                         "huge": {"down_dims": [4096, 8192, 16384]},
                         "other_shapes": {"down_dims": [512, 1024, 2048]}}.items():
        paths[name] = shutil.copytree(model, tmp_path / name)
        config = json.loads((paths[name] / "config.json").read_text())
        config["policy"].update(change)
        (paths[name] / "config.json").write_text(json.dumps(config))
    paths["truncated"] = shutil.copytree(model, tmp_path / "truncated")
    weights = paths["truncated"] / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:1000])
    resumed = shutil.copytree(model, tmp_path / "resumed")
    (resumed / "checkpoint").mkdir()
    (resumed / "checkpoint" / "state.json").write_text("{damaged")
    paths["resumed"] = resumed
    paths["not_a_bag"] = tmp_path / "not_a_bag"
    paths["not_a_bag"].mkdir()
    (paths["not_a_bag"] / "metadata.yaml").write_text("rosbag2_bagfile_information: [\n")
    paths["existing"] = tmp_path / "existing"
    paths["existing"].mkdir()
    # Issue 26, findings 7 and 8: sizes past the bounds, an alias bomb (six levels of nine: too
    # many nodes for the budget, yet cheap enough that the code before the bound printed it),
    # NaN statistics, FIFOs and /proc/self/mem where files are read.
    paths["long_horizon"] = shutil.copytree(model, tmp_path / "long_horizon")
    config = json.loads((paths["long_horizon"] / "config.json").read_text())
    config["policy"]["horizon"] = 512
    (paths["long_horizon"] / "config.json").write_text(json.dumps(config))
    bomb = ["a: &a [x, x, x, x, x, x, x, x, x]"] + [
        f"{level}: &{level} [{', '.join([f'*{below}'] * 9)}]"
        for below, level in zip("abcde", "bcdef", strict=True)]
    config_copy("alias_bomb", "scenarios.yaml", "\n".join([*bomb, "g: {zones: *f}", ""]))
    paths["nan_stats"] = shutil.copytree(model, tmp_path / "nan_stats")
    config = json.loads((paths["nan_stats"] / "config.json").read_text())
    config["policy"]["normalizer"]["obs"]["min"][3] = float("nan")
    (paths["nan_stats"] / "config.json").write_text(json.dumps(config))
    for name, file in (("fifo_config", "config.json"), ("fifo_weights", "model.safetensors")):
        paths[name] = shutil.copytree(model, tmp_path / name)
        (paths[name] / file).unlink()
        os.mkfifo(paths[name] / file)
    config_copy("fifo_yaml", "scenarios.yaml", "")
    (paths["fifo_yaml"] / "scenarios.yaml").unlink()
    os.mkfifo(paths["fifo_yaml"] / "scenarios.yaml")
    config_copy("fifo_evaluation", "evaluation.yaml", "")  # was skipped as if absent
    (paths["fifo_evaluation"] / "evaluation.yaml").unlink()
    os.mkfifo(paths["fifo_evaluation"] / "evaluation.yaml")
    paths["proc_mem"] = shutil.copytree(model, tmp_path / "proc_mem")
    (paths["proc_mem"] / "config.json").unlink()
    (paths["proc_mem"] / "config.json").symlink_to("/proc/self/mem")
    return paths


QUICK = "--episodes 1 --steps 1 --sampler ddim --denoising-steps 2"  # if it ran after all
CASES = [  # command, arguments ({name}: a path from `files`), words the one line must hold
    ("evaluate", "--config-dir {tmp}/nowhere", "no such directory"),
    ("evaluate", "--config-dir {yaml_syntax}", "line 2"),
    ("evaluate", "--config-dir {top_list}", "expected a mapping"),
    ("evaluate", "--config-dir {push_abc}", "push must be a finite number"),
    ("evaluate", "--config-dir {python_tag}", "could not determine a constructor"),
    ("evaluate", "--config-dir {bad_scenarios}", "scenario 'center'"),
    ("evaluate", "--model {model} --configs none --scenarios center_0.2 --output /proc/report",
     "/proc/report"),
    ("evaluate", "--model {model} --configs none --scenarios center_0.2 --reuse "
     "--output {reused}", "results.json"),
    ("evaluate", "--model {model} --configs none --scenarios center_0.2 --figure a b",
     "--figure a b"),
    ("evaluate", "--episodes 0", "not a positive integer"),
    ("evaluate", "--steps abc", "--steps"),
    ("evaluate", "--model {horizon} --configs none --scenarios center_0.2", "horizon"),
    ("evaluate", "--model {model} --configs none --scenarios center_0.2 --device cuda:99 "
     "--output {tmp}/gpu", "not available"),
    ("benchmark_policy", "--model {model} --device abacus", "unknown device"),
    ("benchmark_policy", "--model {model} --device mps", "not supported"),
    ("train_policy", "--dataset {dataset} --output {tmp}/gpu --device cuda:99", "not available"),
    ("benchmark_policy", "--model {action_steps}", "n_action_steps"),
    ("benchmark_policy", "--model {huge}", "down_dims"),
    ("benchmark_policy", "--model {other_shapes}", "do not match"),
    ("benchmark_policy", "--model {truncated}", "cannot read"),
    ("benchmark_policy", "--model {tmp}/none", "none"),
    ("train_policy", "--dataset {tmp}/none.zarr --output {tmp}/trained", "none.zarr"),
    ("train_policy", "--dataset {dataset} --output {model}", "holds a model already"),
    ("train_policy", "--dataset {dataset} --output {model} --resume", "no checkpoint"),
    ("train_policy", "--dataset {dataset} --output {resumed} --resume --down-dims 16 32 64 "
     "--quiet", "damaged"),
    ("train_policy", "--dataset {dataset} --batch-size 0", "--batch-size"),
    ("latency", "--delays -1", "--delays"),
    ("latency", "--configs nothing", "nothing"),
    ("trial", "--steps 0", "--steps"),
    ("trial", "--scenario nowhere --output {tmp}/t1", "nowhere"),
    ("trial", "--scenarios-file {yaml_syntax}/configurations.yaml --output {tmp}/t2", "line 2"),
    ("trial", "--output {existing}", "exists"),
    ("trial", "--configuration nothing --output {tmp}/t3", "unknown configuration 'nothing'"),
    ("trial", "--model {tmp}/none --output {tmp}/t4", "none"),
    ("recover_bag", "{tmp}/nowhere", "no metadata.yaml"),
    ("recover_bag", "{not_a_bag}", "not rosbag2 metadata"),
    # Issue 26, finding 7: sizes and YAML aliases are bounded (a MemoryError a minute later).
    ("benchmark_policy", f"--model {{long_horizon}} {QUICK}", "horizon must be a positive "
     "integer up to 256"),
    ("evaluate", "--config-dir {alias_bomb}", "aliases expand to more than"),
    # Finding 8: every bad input is exit code 2 in one line, before any process or directory.
    ("trial", "--domain-id 300 --output {tmp}/t5", "not a ROS domain id in 0..101"),
    ("trial", "--keepout-grid nan --output {tmp}/t6", "--keepout-grid"),
    ("trial", "--keepout-grid 0.01 --output {tmp}/t6b", "--keepout-grid"),
    ("trial", "--timeout -5 --output {tmp}/t7", "--timeout"),
    ("trial", "--model {truncated} --output {tmp}/t8", "cannot read weights"),
    ("benchmark_policy", f"--model {{nan_stats}} {QUICK}", "finite numbers only"),
    ("benchmark_policy", "--model {fifo_config}", "config.json is a FIFO"),
    ("benchmark_policy", "--model {fifo_weights}", "model.safetensors is a FIFO"),
    ("evaluate", "--config-dir {fifo_yaml}", "scenarios.yaml is a FIFO"),
    ("trial", "--scenarios-file {fifo_yaml}/scenarios.yaml --output {tmp}/t9", "is a FIFO"),
    ("benchmark_policy", "--model {proc_mem}", "proc_mem/config.json: Input/output error"),
    ("evaluate", "--config-dir {fifo_evaluation} --model {tmp}/none --output {tmp}/e1",
     "evaluation.yaml is a FIFO"),
]


def exit_code(command: str, argv: list[str]) -> int:
    """What the console script would exit with (argparse exits by itself)."""
    try:
        return COMMANDS[command](argv)
    except SystemExit as stop:
        return stop.code


@pytest.mark.parametrize(("command", "arguments", "words"), CASES,
                         ids=[f"{c} {a}" for c, a, _ in CASES])
def test_a_bad_file_or_argument_is_one_line_and_exit_code_2(
        files: dict[str, Path], capsys, command: str, arguments: str, words: str) -> None:
    argv = [word.format(**files) for word in arguments.split()]
    output = Path(argv[argv.index("--output") + 1]) if "--output" in argv else None
    existed = output is not None and output.exists()
    assert exit_code(command, argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(f"{command}: error: ") and words in lines[0], lines[0]
    assert "Traceback" not in captured.err + captured.out
    if output is not None and not existed:  # a refused run leaves no directory behind
        assert not output.exists(), output


def tiny_store(path: Path) -> Path:
    """A PushT zarr store of two short episodes, laid out as the real one (zarr format 2)."""
    import zarr

    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    steps = 40
    root.create_array("data/state", data=np.arange(steps * 5, dtype=np.float32).reshape(-1, 5))
    root.create_array("data/action", data=np.ones((steps, 2), np.float32))
    root.create_array("data/keypoint", data=np.ones((steps, 9, 2), np.float32))
    root.create_array("meta/episode_ends", data=np.array([20, steps]))
    return path


@pytest.mark.parametrize("link", [False, True], ids=["fifo", "symlink to a fifo"])
def test_a_fifo_inside_the_dataset_is_one_line_not_a_hang(tmp_path: Path, link: bool) -> None:
    """zarr opened data/action/.zarray and waited for a writer forever. In a process of its own
    with a timeout, so that a regression fails instead of hanging the suite."""
    store = tiny_store(tmp_path / "tiny.zarr")
    assert load_demonstrations(store).actions.shape == (40, 2)  # whole, it loads
    entry = store / "data" / "action" / ".zarray"
    entry.unlink()
    fifo = tmp_path / "fifo" if link else entry
    os.mkfifo(fifo)
    if link:
        entry.symlink_to(fifo)
    done = subprocess.run(
        [sys.executable, "-m", "constrained_diffusion_ros.training.train", "--dataset",
         str(store), "--output", str(tmp_path / "trained")],
        capture_output=True, text=True, timeout=60, cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert lines[0].startswith("train_policy: error: ") and ".zarray is a FIFO" in lines[0], \
        lines[0]
    assert not (tmp_path / "trained").exists()


def test_debug_shows_the_traceback_instead(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no such directory"):
        evaluate.main(["--config-dir", str(tmp_path / "nowhere"), "--debug"])


def test_text_from_a_message_or_file_is_one_bounded_line() -> None:
    line = one_line("frame\nid " + "x" * 1_000_000)
    assert "\n" not in line and len(line) == LINE_LIMIT and line.endswith("...")
    assert one_line("  short\ttext ") == "short text"
