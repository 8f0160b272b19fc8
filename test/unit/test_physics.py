"""The pymunk PushT physics: replaying the demonstrations reproduces them, bad input is refused
and leaves the state alone, a batch steps like single scenes."""

from __future__ import annotations

import numpy as np
import pytest
from samples import angle_difference

from sim_bridge.physics import PushTBatch, PushTSim


def test_replay_reproduces_dataset(dataset: dict[str, np.ndarray]) -> None:
    """Replaying every demonstration's actions reproduces its recorded states.

    Measured (pymunk 7.3.1): pusher max error 1.5e-5 px (float32 storage); block worst error
    per episode: median 2.6e-5 px, 99th percentile 1.1e-3 px, max 0.23 px; all 206 episodes
    under 1 px.
    """
    states, actions, ends = dataset["state"], dataset["action"], dataset["episode_ends"]
    assert len(ends) == 206
    starts = np.r_[0, ends[:-1]]
    sim = PushTSim()
    pusher_err, block_worst, angle_worst = [], [], []
    for start, end in zip(starts, ends):
        sim.set_state(states[start])
        out = np.array([sim.step(actions[t]) for t in range(start, end - 1)]).reshape(-1, 5)
        ref = states[start + 1 : end]
        pusher_err.append(np.abs(out[:, :2] - ref[:, :2]).max(initial=0.0))
        block_worst.append(np.linalg.norm(out[:, 2:4] - ref[:, 2:4], axis=1).max(initial=0.0))
        angle_worst.append(angle_difference(out[:, 4], ref[:, 4]).max(initial=0.0))
    pusher_err, block_worst = np.array(pusher_err), np.array(block_worst)
    median_block = float(np.median(block_worst))
    frac_under_1 = float(np.mean(block_worst < 1.0))
    print(
        f"\nreplay: pusher max err {pusher_err.max():.3g} px; block worst err per episode: "
        f"median {median_block:.3g} px, max {block_worst.max():.3g} px, "
        f"{frac_under_1:.1%} of episodes < 1 px; median worst angle err "
        f"{np.median(angle_worst):.3g} rad"
    )
    assert pusher_err.max() < 0.01
    assert median_block <= 0.1
    assert frac_under_1 >= 0.85


def _assert_unchanged(sim: PushTSim, state: np.ndarray, vel: np.ndarray) -> None:
    np.testing.assert_array_equal(sim.state, state)
    np.testing.assert_array_equal(sim.agent_velocity, vel)


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        ([np.nan, 100.0], "finite"),
        ([100.0, np.inf], "finite"),
        ([1.0, 2.0, 3.0], "shape"),
        ([[1.0, 2.0]], "shape"),
        ([5000.0, 100.0], "within"),
        ([100.0, -1e9], "within"),
        (["a", "b"], "numbers"),
        (["1", "2"], "numbers"),  # numpy would read them as 1.0 and 2.0
        ([True, False], "numbers"),
    ],
)
def test_bad_action_raises_and_keeps_state(bad: object, match: str) -> None:
    sim = PushTSim()
    sim.reset(0)
    sim.step([200.0, 200.0])
    state, vel = sim.state, sim.agent_velocity
    with pytest.raises(ValueError, match=match):
        sim.step(bad)
    _assert_unchanged(sim, state, vel)


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        ([1.0, 2.0, 3.0, 4.0], "shape"),
        ([100.0, np.nan, 200.0, 200.0, 0.0], "finite"),
        ([100.0, 100.0, 200.0, 200.0, np.inf], "finite"),
        ([100.0, 100.0, 1e5, 200.0, 0.0], "inside the walls"),
        ([100.0, 100.0, 508.0, 200.0, 0.0], "inside the walls"),  # beyond the right wall
        ([2.0, 100.0, 200.0, 200.0, 0.0], "inside the walls"),
    ],
)
def test_bad_state_raises_and_keeps_state(bad: object, match: str) -> None:
    sim = PushTSim()
    sim.reset(1)
    sim.step([200.0, 200.0])
    state, vel = sim.state, sim.agent_velocity
    with pytest.raises(ValueError, match=match):
        sim.set_state(bad)
    _assert_unchanged(sim, state, vel)


def test_batch_rejects_mismatch_and_keeps_states() -> None:
    batch = PushTBatch(3)
    before = batch.reset([0, 1, 2])
    with pytest.raises(ValueError, match="shape"):
        batch.step(np.full((4, 2), 200.0))
    with pytest.raises(ValueError, match="shape"):
        batch.set_states(np.zeros((2, 5)))
    with pytest.raises(ValueError, match="3 seeds"):
        batch.reset([0, 1])
    with pytest.raises(ValueError, match="seed"):
        batch.reset([0, 1, -5])
    actions = np.full((3, 2), 200.0)
    actions[2, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        batch.step(actions)
    np.testing.assert_array_equal(batch.states, before)
    with pytest.raises(ValueError, match="batch size"):
        PushTBatch(0)


def test_batch_equals_single() -> None:
    seeds = [0, 1, 2, 3, 4]
    batch = PushTBatch(len(seeds))
    sims = [PushTSim() for _ in seeds]
    np.testing.assert_array_equal(
        batch.reset(seeds), np.stack([s.reset(k) for s, k in zip(sims, seeds)])
    )
    rs = np.random.RandomState(7)
    for _ in range(30):
        # Aim at each block so that contacts happen, not just free pusher motion.
        actions = batch.states[:, 2:4] + rs.uniform(-60, 60, (len(seeds), 2))
        got = batch.step(actions)
        expect = np.stack([s.step(a) for s, a in zip(sims, actions)])
        np.testing.assert_array_equal(got, expect)
    np.testing.assert_array_equal(batch.keypoints(), np.stack([s.keypoints() for s in sims]))
    np.testing.assert_array_equal(batch.observations(), np.stack([s.observation() for s in sims]))
    np.testing.assert_allclose(batch.coverage(), [s.coverage() for s in sims])
    np.testing.assert_array_equal(batch.success(), [s.success() for s in sims])
    assert batch.observations().shape == (len(seeds), 20)
    assert len(batch) == len(seeds)


def test_observation_layout() -> None:
    sim = PushTSim()
    sim.reset(5)
    obs = sim.observation()
    assert obs.shape == (20,)
    np.testing.assert_array_equal(obs[:18], sim.keypoints().reshape(-1))
    np.testing.assert_array_equal(obs[18:], sim.state[:2])
