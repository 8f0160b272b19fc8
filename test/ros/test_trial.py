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
from rosbags.typesys import Stores, get_typestore

from constrained_diffusion_ros.evaluation.runner import evaluate_configuration
from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.evaluation.trial import bag_lacks
from constrained_diffusion_ros.examples.camera import CameraZones
from constrained_diffusion_ros.planning.constraint_configs import load_configurations
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.recording import bags
from constrained_diffusion_ros.recording.bags import read_messages, read_trial
from msg_schemas import TOPICS

SEED, STEPS = 100019, 16  # the tiny policy enters the left half there when unconstrained


def run_trial_command(output, model, configurations_file, *arguments: str,
                      environment: dict[str, str] | None = None, code: int = 0) -> str:
    """`trial` with fast_safe on the tiny policy, seed SEED, STEPS steps (in `environment`
    besides the test's), expected to exit with `code`; its output."""
    command = [sys.executable, "-m", "constrained_diffusion_ros.evaluation.trial",
               "--configuration", "fast_safe", "--configurations-file", str(configurations_file),
               "--seed", str(SEED), "--steps", str(STEPS), "--output", str(output), "--model",
               str(model), "--timeout", "60", "--domain-id", str(random_domain_id()), *arguments]
    process = subprocess.Popen(command, cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1",
                                                      **(environment or {})},
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        out, _ = process.communicate(timeout=90)
    finally:
        if process.poll() is None:  # the trial stops its own nodes on SIGINT
            process.send_signal(signal.SIGINT)
            process.communicate(timeout=20)
    logs = "".join(f"\n--- {log.name}\n{log.read_text()}" for log in sorted(output.glob("*.log")))
    assert process.returncode == code, out + logs
    assert "warning" not in out, out + logs  # e.g. a bag that lacks steps
    return out


def batched(model, configurations_file, scenario, configuration: str = "fast_safe"):
    """The ROS-free evaluation of the same episode: (cell, log)."""
    (cell,), log = evaluate_configuration(
        load_policy(model), load_configurations(configurations_file)[configuration],
        [scenario], seeds=[SEED], n_steps=STEPS, progress=False)
    return cell, log


def test_trial_command_records_the_batched_evaluation(tiny_model, configurations_file, tmp_path):
    """`trial` end to end, checked against the ROS-free batched evaluation of the same episode.

    left_0.5 / fast_safe (projection, inflation, shield) / seed 100019: the tiny policy scores
    s > 0 there and, unconstrained (fast_none), commands setpoints inside the zone, so equal s
    and r = 0 are not vacuous; the shield changes setpoints there, in both alike."""
    scenario_name, seed, steps = "left_0.5", SEED, STEPS
    output = tmp_path / "trial"
    run_trial_command(output, tiny_model, configurations_file, "--scenario", scenario_name)
    for name in ("bag", "frames.png", "trial.gif", "trial.json"):
        assert (output / name).exists(), name
    assert (output / "frames.png").read_bytes().startswith(b"\x89PNG")
    assert len(iio.imread(output / "trial.gif", index=None)) == steps // 2 + 1

    messages = read_messages(output / "bag")
    unused = {TOPICS["keepout_mask"].resolved()}  # zones come as polygons here
    assert set(messages) == {endpoint.resolved() for endpoint in TOPICS.values()} - unused
    info = yaml.safe_load((output / "bag" / "metadata.yaml").read_text())
    custom = info["rosbag2_bagfile_information"]["custom_data"]
    counts = json.loads(custom["message_counts"])  # every contract topic, 0 if none came
    assert {t: n for t, n in counts.items() if n} == {t: len(m) for t, m in messages.items()}
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


def test_a_keepout_grid_and_a_plug_in_check_are_obeyed_like_the_polygons(
        tiny_model, configurations_file, tmp_path) -> None:
    """The left half as a keep-out mask (4 px cells: exactly the polygon again) and as a
    plug-in check drawn in a camera's image: each trial equals the batched evaluation of the
    polygons bit for bit, with r = 0 where the unconstrained policy enters."""
    left = load_scenarios()["left_0.5"]
    cell, log = batched(tiny_model, configurations_file, left)
    free, _ = batched(tiny_model, configurations_file, left, "fast_none")
    assert free.r > 0 and cell.r == 0

    grid = tmp_path / "grid"
    run_trial_command(grid, tiny_model, configurations_file, "--scenario", "left_0.5",
                      "--keepout-grid", "4")
    messages = read_messages(grid / "bag")
    assert messages[TOPICS["keepout_mask"].resolved()]  # the zones went as a mask
    assert not messages.get(TOPICS["zones"].resolved())

    camera = CameraZones("camera_zones.yaml")  # the shipped camera, drawing the left half
    drawn = camera.to_image(left.polygons[0]).round(3).tolist()
    config = tmp_path / "camera.yaml"
    config.write_text(yaml.safe_dump({"image_to_workspace": camera.homography.tolist(),
                                      "zones": [drawn]}))
    scenarios = tmp_path / "scenarios.yaml"
    scenarios.write_text(yaml.safe_dump({"camera_left": {"plugin": {
        "class": "constrained_diffusion_ros.examples.camera:CameraZones",
        "parameters": {"config_file": str(config)}}}}))
    plugged = tmp_path / "plugin"
    run_trial_command(plugged, tiny_model, configurations_file, "--scenario", "camera_left",
                      "--scenarios-file", str(scenarios))
    assert not read_messages(plugged / "bag").get(TOPICS["zones"].resolved())  # no zone topic

    camera_left = load_scenarios(scenarios)["camera_left"]
    plugged_cell, plugged_log = batched(tiny_model, configurations_file, camera_left)
    for output, expected, expected_log, tolerance in ((grid, cell, log, 0.5),
                                                      (plugged, plugged_cell, plugged_log, 0.0)):
        results = json.loads((output / "trial.json").read_text())["results"]
        assert results["r"] == 0.0 and results["r_body"] == expected.r_body  # as evaluated
        received = read_trial(output / "bag")
        commanded = np.array([(received["setpoint"][t].point.x, received["setpoint"][t].point.y)
                              for t in range(STEPS)])
        # The plug-in trial is the batched evaluation of its own scenario, bit for bit; the
        # mask's polygon is the left half again, its vertices in another order: the same
        # setpoints to float rounding.
        assert np.abs(commanded - expected_log.commanded[0]).max() <= tolerance
        assert abs(results["s"] - expected.s) <= 0.02


TURNS_NAN = """
import torch
from constrained_diffusion_ros.zones import RestrictedArea


class TurnsNaN(RestrictedArea):
    \"\"\"A disc whose distances turn NaN after `after` queries (the load probe makes 8).\"\"\"

    def __init__(self, centre, radius, after):
        self.centre, self.radius, self.after, self.calls = centre, radius, after, 0

    def signed_distance(self, points):
        self.calls += 1
        distance = (points - torch.tensor(self.centre, dtype=points.dtype)).norm(dim=-1)
        distance = distance - self.radius
        return distance if self.calls <= self.after else torch.full_like(distance, torch.nan)
"""


def test_a_plug_in_that_turns_nan_during_the_trial_is_named_and_fails_it(
        tiny_model, configurations_file, tmp_path) -> None:
    """Found by finding 5 of issue 41: a plug-in check that passed the load probe and turned
    NaN later held the pusher with only "planning missed its deadline" to show for it, and
    `trial` exited 0 with a score. Now the policy stops the pusher, logs the check's name and
    the fault once (at ERROR), says it on /diagnostics (ERROR, `zone_check_error`), and the
    trial fails naming it; no setpoint that goes out is NaN."""
    (tmp_path / "nan_zones.py").write_text(TURNS_NAN)
    scenarios = tmp_path / "scenarios.yaml"
    spec = "nan_zones:TurnsNaN"  # about 100 queries a plan: the first plan is made
    scenarios.write_text(yaml.safe_dump({"turns_nan": {"plugin": {"class": spec, "parameters": {
        "centre": [128, 256], "radius": 60, "after": 150}}}}))
    output = tmp_path / "trial"
    out = run_trial_command(
        output, tiny_model, configurations_file, "--scenario", "turns_nan", "--scenarios-file",
        str(scenarios), code=1, environment={
            "PYTHONPATH": os.pathsep.join(filter(None, [str(tmp_path), str(REPO),
                                                        os.environ.get("PYTHONPATH")])),
            "CONSTRAINED_DIFFUSION_ROS_PLUGIN_MODULES": "nan_zones"})
    fault = f"zone check {spec!r}: signed_distance returned NaN at ("
    failed = [line for line in out.splitlines() if line.startswith("trial: failed:")]
    assert len(failed) == 1 and fault in failed[0], out
    assert fault in json.loads((output / "trial.json").read_text())["zone_check_error"]
    said = [line for line in (output / "policy_node.log").read_text().splitlines()
            if fault in line]
    assert len(said) == 1 and "ERROR" in said[0], said  # once: the fault repeats every step

    messages = read_messages(output / "bag")
    statuses = [status for array in messages[TOPICS["diagnostics"].resolved()]
                for status in array.status]
    errors = [status for status in statuses if status.level == 2
              and fault in {kv.key: kv.value for kv in status.values}["zone_check_error"]]
    assert errors and all("zone check failed" in status.message for status in errors)
    received = read_trial(output / "bag")
    commanded = np.array([(received["setpoint"][t].point.x, received["setpoint"][t].point.y)
                          for t in range(STEPS)])
    pusher = np.array([(received["pusher"][t].point.x, received["pusher"][t].point.y)
                       for t in range(STEPS)])
    assert np.isfinite(commanded).all()
    stopped = np.all(np.abs(commanded - pusher) < 1e-3, axis=1)  # the pusher's (float32)
    assert not stopped[0] and stopped[-1]  # the first plan was made, and the check failed later


def test_a_bag_being_recorded_is_checked_for_every_step_and_topic_heard(tmp_path) -> None:
    """What `trial` waits for before it stops the nodes: the bag, still open, is read as far
    as the recorder has written it; a topic heard but not recorded, and a step the trial got
    but the bag lacks, are named."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    types = typestore.types
    writer = bags.open_bag(tmp_path / "bag", {})
    setpoint, pusher = TOPICS["setpoint"], TOPICS["pusher"]
    for endpoint, steps in ((setpoint, range(3)), (pusher, range(3))):
        connection = writer.add_connection(endpoint.resolved(), endpoint.type,
                                           typestore=typestore)
        for step in steps:
            header = types["std_msgs/msg/Header"](
                stamp=types["builtin_interfaces/msg/Time"](sec=0, nanosec=step * 100_000_000),
                frame_id="workspace")
            message = types[endpoint.type](header=header, point=types[
                "geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.0))
            writer.write(connection, step, typestore.serialize_cdr(message, endpoint.type))
    heard = {setpoint.resolved(), pusher.resolved(), TOPICS["plan"].resolved()}
    received = {"pusher": dict.fromkeys(range(4)), "block": {},
                "setpoint": dict.fromkeys(range(3))}
    assert bag_lacks(tmp_path / "bag", heard, received) == [  # nothing written yet
        *sorted(heard), "pusher of steps [0, 1, 2, 3]", "setpoint of steps [0, 1, 2]"]
    bags.flush(writer)  # what the recorder does twice a second
    assert bag_lacks(tmp_path / "bag", heard, received) == [
        TOPICS["plan"].resolved(), "pusher of steps [3]"]
    heard.discard(TOPICS["plan"].resolved())
    del received["pusher"][3]
    assert bag_lacks(tmp_path / "bag", heard, received) == []
    writer.close()
    assert bag_lacks(tmp_path / "bag", heard, received) == []
