"""The robot model the planning core gets: built from the PushT constants, it predicts the
simulated pusher exactly, and bad robot parameters are refused."""

from __future__ import annotations

import numpy as np
import pytest

from constrained_diffusion_ros.planning.robot import RobotModel
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from sim_bridge import PushTSim
from sim_bridge.scene import observation

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
