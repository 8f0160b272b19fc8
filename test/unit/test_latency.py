"""The latency report: a run for one configuration keeps the other configurations' rows."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from constrained_diffusion_ros.evaluation.latency import handover_jumps, kept_rows


def test_a_run_keeps_the_rows_of_the_configurations_it_does_not_run(tmp_path) -> None:
    report = tmp_path / "latency.json"
    assert kept_rows(report, ["ddpm"]) == []
    rows = [{"configuration": "ddim", "delay": 0}, {"configuration": "ddpm", "delay": 0}]
    report.write_text(json.dumps(rows))
    assert kept_rows(report, ["ddpm"]) == [rows[0]]


def test_a_report_that_is_not_one_is_refused_with_its_name(tmp_path) -> None:
    report = tmp_path / "latency.json"
    report.write_text("{not json")
    with pytest.raises(ValueError, match=r"latency\.json is not a latency report"):
        kept_rows(report, ["ddpm"])


def test_the_jump_at_a_handover_is_told_apart_from_steps_within_a_chunk() -> None:
    commanded = np.array([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [12.0, 0.0], [13.0, 0.0]]])
    chunk = np.array([[0, 0, 0, 1, 1]])
    jump, within = handover_jumps(commanded, chunk)
    assert jump == pytest.approx(10.0) and within == pytest.approx(1.0)


def test_a_plan_every_tick_has_no_step_within_a_chunk_and_says_so_without_a_warning() -> None:
    commanded = np.array([[[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [6.0, 0.0]]])
    chunk = np.array([[0, 1, 2, 3]])  # a new chunk at every step
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's "mean of empty slice" would raise here
        jump, within = handover_jumps(commanded, chunk)
    assert jump == pytest.approx(2.0) and np.isnan(within)
