"""The `trial` command end to end over real DDS, against the ROS-free batched evaluation."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import yaml
from ros_helpers import REPO, random_domain_id, stamp_step

from constrained_diffusion_ros.evaluation.bags import read_messages, read_trial
from constrained_diffusion_ros.evaluation.runner import evaluate_configuration
from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.planning.config import load_configurations
from constrained_diffusion_ros.policy.weights import load_policy
from msg_schemas import TOPICS


def test_trial_command_records_the_batched_evaluation(tiny_model, configurations_file, tmp_path):
    """`trial` end to end, checked against the ROS-free batched evaluation of the same episode.

    left_0.5 / fast_safe (projection, inflation, shield) / seed 100019: the tiny policy scores
    s > 0 there and, unconstrained (fast_none), commands setpoints inside the zone, so equal s
    and r = 0 are not vacuous; the shield changes setpoints there, in both alike."""
    scenario_name, seed, steps = "left_0.5", 100019, 16
    output = tmp_path / "trial"
    command = [sys.executable, "-m", "constrained_diffusion_ros.evaluation.trial",
               "--scenario", scenario_name, "--configuration", "fast_safe",
               "--configurations-file", str(configurations_file), "--seed", str(seed),
               "--steps", str(steps), "--output", str(output), "--model", str(tiny_model),
               "--timeout", "60", "--domain-id", str(random_domain_id())]
    process = subprocess.Popen(command, cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1"},
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        out, _ = process.communicate(timeout=90)
    finally:
        if process.poll() is None:  # the trial stops its own nodes on SIGINT
            process.send_signal(signal.SIGINT)
            process.communicate(timeout=20)
    assert process.returncode == 0, out
    for name in ("bag", "frames.png", "trial.gif", "trial.json"):
        assert (output / name).exists(), name
    assert (output / "frames.png").read_bytes().startswith(b"\x89PNG")
    assert len(iio.imread(output / "trial.gif", index=None)) == steps // 2 + 1

    messages = read_messages(output / "bag")
    assert set(messages) == {endpoint.resolved() for endpoint in TOPICS.values()}
    info = yaml.safe_load((output / "bag" / "metadata.yaml").read_text())
    custom = info["rosbag2_bagfile_information"]["custom_data"]
    assert json.loads(custom["message_counts"]) == {t: len(m) for t, m in messages.items()}
    setpoint_steps = [stamp_step(m.header.stamp) for m in messages[TOPICS["setpoint"].resolved()]]
    # One setpoint per executed step; the policy may also answer the final observation (step
    # `steps`), which the sim ignores at max_steps, before the trial stops it.
    assert setpoint_steps[:steps] == list(range(steps))
    assert setpoint_steps[steps:] in ([], [steps])

    trial = json.loads(custom["trial_metadata"])
    assert trial == json.loads((output / "trial.json").read_text())
    assert (trial["scenario"], trial["configuration"], trial["seed"], trial["steps"]) == \
        (scenario_name, "fast_safe", seed, steps)
    results = trial["results"]

    policy = load_policy(tiny_model)
    configurations = load_configurations(configurations_file)
    scenario = load_scenarios()[scenario_name]
    (cell,), log = evaluate_configuration(policy, configurations["fast_safe"], [scenario],
                                          seeds=[seed], n_steps=steps, progress=False)
    expected = cell.to_dict()
    assert results == {key: expected[key] for key in results}
    assert {"s", "r", "final_score", "r_body"} <= set(results)
    received = read_trial(output / "bag")
    commanded = [(received["setpoint"][t].point.x, received["setpoint"][t].point.y)
                 for t in range(steps)]
    assert np.array_equal(np.array(commanded), log.commanded[0])  # bit for bit
    assert results["s"] > 0.0 and results["r"] == 0.0
    (free,), _ = evaluate_configuration(policy, configurations["fast_none"], [scenario],
                                        seeds=[seed], n_steps=steps, progress=False)
    assert free.r > 0.0 and free.s != results["s"]
    _, unshielded = evaluate_configuration(policy, configurations["fast_inflated"], [scenario],
                                           seeds=[seed], n_steps=steps, progress=False)
    assert (unshielded.commanded != log.commanded).any()  # the shield acted, in both alike
