"""Constraint configurations from YAML, and the evaluation's labels for them."""

from __future__ import annotations

import itertools
import math
import time
from pathlib import Path

import pytest
import yaml

from constrained_diffusion_ros.evaluation.evaluated_configurations import load_evaluated
from constrained_diffusion_ros.paths import config_dir
from constrained_diffusion_ros.planning.constraint_configs import (
    ConstraintConfig,
    load_configurations,
    safe_yaml,
)
from constrained_diffusion_ros.policy.normalizer import MinMaxNormalizer
from constrained_diffusion_ros.policy.policy_config import PolicyConfig

# -- Configurations ------------------------------------------------------------------------------

def test_load_configurations_reads_every_entry_of_the_shipped_file() -> None:
    path = config_dir() / "configurations.yaml"
    configs = load_configurations(path)
    assert list(configs) == list(yaml.safe_load(path.read_text()))
    assert all(name == config.name for name, config in configs.items())
    assert not configs["none"].constrains
    r_g10 = configs["r_g10"]
    assert r_g10.resample and r_g10.push == 10 and not r_g10.project
    assert configs["ddim10_scratch_8"].from_scratch == 8
    assert configs["ddim10_scratch_8"].sampler == "ddim"


def test_an_unknown_configuration_key_is_refused_by_name(tmp_path: Path) -> None:
    path = tmp_path / "configurations.yaml"
    path.write_text("ok: {resample: true}\nbad: {resample: true, lambda: 3}\n")
    with pytest.raises(ValueError, match="lambda"):
        load_configurations(path)


@pytest.mark.parametrize("entry", [{"push": -1.0}, {"from_scratch": 4, "resample": True},
                                   {"sampler": "euler"}, {"guide_until": 1.5},
                                   {"repair_from": -0.1}, {"margin_shrink": -1.0},
                                   {"denoising_steps": 1001}, {"candidates": 1025},
                                   {"from_scratch": 1025}])
def test_inconsistent_configurations_are_refused(entry: dict) -> None:
    with pytest.raises(ValueError, match="'bad'"):
        ConstraintConfig("bad", **entry)


def test_the_evaluation_labels_every_configuration_and_marks_the_papers_six() -> None:
    evaluated = load_evaluated(config_dir())
    assert list(evaluated) == list(load_configurations(config_dir() / "configurations.yaml"))
    assert evaluated["r_g10"].label == "R + G10" and evaluated["r_g10"].paper
    assert evaluated["resampling"].scenarios == "paper"
    paper = {name for name, entry in evaluated.items() if entry.paper}
    assert len(paper) == 6
    paper_table = yaml.safe_load((config_dir() / "paper_table1.yaml").read_text())
    for row in paper_table.values():
        assert set(row) == paper


@pytest.mark.parametrize("text, fault", [("ghost: {label: G}", "ghost"),
                                         ("none: {label: N, scenarios: some}", "scenarios"),
                                         ("none: {colour: red}", "colour")])
def test_bad_evaluation_labels_are_refused_by_name(tmp_path: Path, text: str, fault: str) -> None:
    (tmp_path / "configurations.yaml").write_text("none: {}\n")
    (tmp_path / "evaluation.yaml").write_text(text + "\n")
    with pytest.raises(ValueError, match=fault):
        load_evaluated(tmp_path)


@pytest.mark.parametrize(("text", "reason"), [
    ("a: [\n", "not valid YAML at line 2"),
    ("- a\n", "expected a mapping"),
    ("r: {push: abc}\n", "push must be a finite number"),
    ("x: !!python/object/apply:os.system ['echo hi']\n", "could not determine a constructor"),
    ("x: {denoising_steps: 0}\n", "denoising_steps must be at least 1"),
    ("x: {resample: 3}\n", "resample must be true or false"),
    ("x: string\n", "must be a mapping of fields"),
])
def test_a_bad_configurations_file_is_one_line_naming_the_fault(tmp_path, text: str,
                                                                reason: str) -> None:
    path = tmp_path / "configurations.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=reason) as caught:
        load_configurations(path)
    assert "\n" not in str(caught.value)


# -- Hostile files (issue 26, finding 7) --------------------------------------------------------

def billion_laughs() -> str:
    """The bomb of the issue: nine levels of nine aliases, 387 million nodes in 300 bytes."""
    lines = ["a: &a [x, x, x, x, x, x, x, x, x]"] + [
        f"{name}: &{name} [{', '.join([f'*{below}'] * 9)}]"
        for below, name in itertools.pairwise("abcdefghi")]
    return "\n".join([*lines, "r: {push: *i}", ""])


def test_an_alias_bomb_is_refused_before_it_expands(tmp_path: Path) -> None:
    path = tmp_path / "configurations.yaml"
    path.write_text(billion_laughs())
    started = time.perf_counter()
    with pytest.raises(ValueError, match=r"at line 5, column \d+: aliases expand to more than"):
        load_configurations(path)
    assert time.perf_counter() - started < 0.5  # before: 3.4 GB after 9 s


def test_a_recursive_alias_is_refused_and_the_shipped_aliases_are_taken() -> None:
    with pytest.raises(ValueError, match=r"parameter p: not valid YAML at line 1.*refers to"):
        safe_yaml("a: &a [1, *a]\n", "parameter p")
    assert safe_yaml("d: &d {x: 1}\ne: {<<: *d, y: 2}\n", "text") == {
        "d": {"x": 1}, "e": {"x": 1, "y": 2}}


@pytest.mark.parametrize(("field", "value"), [("horizon", 512), ("num_train_timesteps", 10**9),
                                              ("obs_dim", 10**7), ("kernel_size", 101),
                                              ("n_action_steps", 10**6)])
def test_policy_sizes_past_their_bounds_are_refused_by_name(field: str, value: int) -> None:
    with pytest.raises(ValueError, match=f"{field} must be a positive integer up to"):
        PolicyConfig(**{field: value})


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_normaliser_statistics_must_be_finite(bad: float) -> None:
    stats = {"obs": {"min": [0.0] * 20, "max": [512.0] * 20},
             "action": {"min": [0.0, bad], "max": [512.0, 512.0]}}
    with pytest.raises(ValueError, match="normalizer action min and max must hold finite"):
        PolicyConfig(normalizer=stats)
    with pytest.raises(ValueError, match="NaN or inf"):
        MinMaxNormalizer.from_dict(stats["action"])
