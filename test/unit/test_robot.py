"""The robot model the planning core gets: built from the PushT constants, it predicts the
simulated pusher exactly, and bad robot parameters are refused."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from constrained_diffusion_ros.planning.robot import REACH_SLACK, RobotModel
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from sim_bridge import PushTSim
from sim_bridge.scene import AGENT_START, observation

# Up a square's left side, then right along its top: a path with a sharp turn.
AROUND_THE_CORNER = ([(183.0, max(183.0, 420.0 - 40 * t)) for t in range(1, 8)]
                     + [(183.0 + 40 * t, 183.0) for t in range(1, 8)])
START = [183.0, 420.0, 80.0, 60.0, 0.0]  # the T far away in a corner


def test_the_pd_model_predicts_the_simulated_pusher_exactly() -> None:
    sim = PushTSim()
    sim.set_state(START)
    one_step = PUSHT_ROBOT.transition(PUSHT_ROBOT.substeps)[-1]
    position, velocity = sim.state[:2], sim.agent_velocity
    for setpoint in AROUND_THE_CORNER:
        predicted = one_step @ np.stack([position, velocity, np.array(setpoint)])
        sim.step(setpoint)
        position, velocity = sim.state[:2], sim.agent_velocity
        np.testing.assert_allclose(predicted, np.stack([position, velocity]), atol=1e-9)


def test_the_pusher_is_where_the_observation_layout_puts_it() -> None:
    keypoints, pusher = np.arange(18.0).reshape(9, 2), np.array([300.0, 40.0])
    observations = observation(keypoints, pusher)[None]
    np.testing.assert_array_equal(PUSHT_ROBOT.pusher(observations), [[300.0, 40.0]])
    assert PUSHT_ROBOT.substeps == 10 and PUSHT_ROBOT.workspace == (0.0, 0.0, 512.0, 512.0)


@pytest.mark.parametrize("change", [{"workspace": (0, 0, 0, 512)}, {"kp": 0.0},
                                    {"control_hz": 200.0}, {"pusher_in_observation": (18, 21)}])
def test_a_robot_that_makes_no_sense_is_refused(change: dict) -> None:
    fields = {**PUSHT_ROBOT.__dict__, **change}
    with pytest.raises(ValueError, match=r"robot|pusher"):
        RobotModel(**fields)


@pytest.mark.parametrize("position, previous, seconds, why", [
    ((1e6, 1e6), None, 0.0, "outside the workspace"),
    ((-300.0, 200.0), None, 0.0, "outside the workspace"),
    ((float("nan"), 200.0), None, 0.0, "outside the workspace"),
    ((500.0, 500.0), (12.0, 12.0), 0.1, "farther than it can move"),
    # Issue 41: at the simulator's next stamp, from the pusher where seed 100001 starts it and
    # from where the reference's reset puts it (the old bound allowed 467 px a step).
    ((500.0, 500.0), (365.0, 182.0), 0.1, "farther than it can move"),
    ((500.0, 500.0), AGENT_START, 0.1, "farther than it can move"),
])
def test_a_pusher_no_pd_robot_can_be_is_named_implausible(position, previous, seconds,
                                                          why) -> None:
    assert why in PUSHT_ROBOT.implausible(np.array(position), previous, seconds)


def test_every_pusher_the_simulator_reports_is_plausible() -> None:
    """Driven corner to corner with the largest setpoint jumps the workspace allows, the
    simulated pusher never moves farther than `implausible` allows."""
    sim = PushTSim()
    sim.set_state([20.0, 20.0, 300.0, 300.0, 0.0])
    previous = sim.state[:2].copy()
    for setpoint in [(512.0, 512.0), (0.0, 0.0), (512.0, 0.0), (0.0, 512.0)] * 3:
        sim.step(np.array(setpoint))
        position = sim.state[:2].copy()
        assert PUSHT_ROBOT.implausible(position, previous, 1 / PUSHT_ROBOT.control_hz) is None
        previous = position


def test_a_steps_reach_is_exactly_the_farthest_the_simulated_pusher_moves() -> None:
    """At rest in one corner with the opposite one commanded, the second step moves the
    simulated pusher exactly `reach` (the bound is attained: it cannot be tighter), and that
    step is plausible; a tenth more than the slack allows is not."""
    sim = PushTSim()
    sim.set_state([5.0, 5.0, 100.0, 400.0, 0.0])  # the T off the diagonal
    for _ in range(50):  # at rest in the corner (walls do not stop the kinematic pusher)
        sim.step((0.0, 0.0))
    sim.step((512.0, 512.0))
    before = sim.state[:2].copy()
    sim.step((512.0, 512.0))
    moved = float(np.linalg.norm(sim.state[:2] - before))
    assert moved == pytest.approx(PUSHT_ROBOT.reach(0.1), rel=1e-9)
    assert 200.0 < moved < 250.0
    assert PUSHT_ROBOT.implausible(sim.state[:2], before, 0.1) is None
    direction = (sim.state[:2] - before) / moved
    farther = before + 1.1 * REACH_SLACK * moved * direction
    assert "farther than it can move" in PUSHT_ROBOT.implausible(farther, before, 0.1)


def test_the_reach_grows_with_the_time_between_reports_up_to_the_workspace() -> None:
    """Rounded up to control steps; never beyond the diagonal (the PD law settles without
    overshoot), which a long gap allows."""
    one, two = PUSHT_ROBOT.reach(0.1), PUSHT_ROBOT.reach(0.2)
    assert PUSHT_ROBOT.reach(0.05) == one == PUSHT_ROBOT.reach(0.1 + 1e-9) and two > one
    diagonal = float(np.hypot(512.0, 512.0))
    assert PUSHT_ROBOT.reach(3600.0) == pytest.approx(diagonal, rel=1e-6)
    assert PUSHT_ROBOT.implausible(np.array([500.0, 500.0]), np.array([12.0, 12.0]), 60.0) \
        is None


CORNERS = st.sampled_from([(0.0, 0.0), (512.0, 0.0), (0.0, 512.0), (512.0, 512.0)])
SETPOINTS = st.one_of(CORNERS, st.tuples(st.floats(0.0, 512.0), st.floats(0.0, 512.0)))


@settings(max_examples=80, deadline=None)
@given(start=st.tuples(st.floats(5.0, 506.0), st.floats(5.0, 506.0)),
       setpoints=st.lists(SETPOINTS, min_size=1, max_size=12))
def test_no_simulated_pusher_moves_farther_than_its_reach(start, setpoints) -> None:
    """From rest anywhere, under any setpoints in the workspace (corners, reversals), the
    simulator's pusher never moves farther in m steps than `reach` of m steps, slack aside."""
    sim = PushTSim()
    sim.set_state([*start, 256.0, 256.0, 0.0])
    positions = [sim.state[:2].copy()]
    for setpoint in setpoints:
        sim.step(setpoint)
        positions.append(sim.state[:2].copy())
    positions = np.array(positions)
    for steps in range(1, 5):
        moved = np.linalg.norm(positions[steps:] - positions[:-steps], axis=-1)
        assert np.all(moved <= PUSHT_ROBOT.reach(steps / PUSHT_ROBOT.control_hz) + 1e-6)


def test_every_demonstrated_pusher_step_is_plausible(dataset) -> None:
    """The human demonstrations (the motion the policy learned) move the pusher at most a
    quarter of a step's reach."""
    ends = dataset["episode_ends"]
    for start, end in zip(np.r_[0, ends[:-1]], ends):
        pusher = dataset["state"][start:end, :2]
        for previous, position in itertools.pairwise(pusher):
            assert PUSHT_ROBOT.implausible(position, previous, 0.1) is None
        moved = np.linalg.norm(np.diff(pusher, axis=0), axis=-1)
        assert moved.max(initial=0.0) < PUSHT_ROBOT.reach(0.1) / 3
