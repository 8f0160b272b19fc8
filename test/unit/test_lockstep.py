"""The chunk loop in lockstep (a simulated worker, no delay), with a planner whose chunks say who
made them: which waypoints execute, when it replans (chunk used up; zones changed into the rest
of it), the guard's last word, and a new episode."""

from __future__ import annotations

import numpy as np
import torch

from constrained_diffusion_ros.planning.action_queue import ObservationHistory
from constrained_diffusion_ros.planning.chunk_loop import ChunkLoop
from constrained_diffusion_ros.policy.policy_config import PolicyConfig
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones import RestrictedArea, ZoneSet, rectangle

CONFIG = PolicyConfig()  # 2 observations, chunks of 16, 8 executed from index 1


class Scripted:
    """Waypoint i of the chunk planned at call c for row r is (1000 c + i, r); records calls."""

    policy_config = CONFIG
    robot = PUSHT_ROBOT  # the pusher's position: entries 18, 19 of an observation

    def __init__(self, keep_out: RestrictedArea | None = None) -> None:
        self.calls: list[tuple[int, list[int], RestrictedArea | None]] = []
        self.guarded: list[np.ndarray] = []
        self.keep_out, self.resets = keep_out, 0

    def plan(self, observations, zones, rows, generator, prefix=None):
        call = len(self.calls)
        self.calls.append((int(observations[0, -1, 0]), list(rows), zones))
        index = torch.arange(CONFIG.horizon, dtype=torch.float64)
        chunks = torch.stack([torch.stack([1000.0 * call + index,
                                           torch.full_like(index, float(r))], dim=-1)
                              for r in rows])
        return chunks

    def violates(self, waypoints, zones, rows):  # (its waypoints lie far outside on purpose)
        if zones is None:
            return torch.zeros(waypoints.shape[:-1], dtype=torch.bool)
        return zones.contains(waypoints)

    def guard(self, zones, observations, setpoints, step):
        self.guarded.append(setpoints.copy())
        return setpoints + 0.5  # visibly the guard's

    def reset(self) -> None:
        self.resets += 1


class Zones:
    """A zone source whose zones the test switches."""

    def __init__(self) -> None:
        self.area: RestrictedArea | None = None
        self.version = 0

    def set(self, area: RestrictedArea | None) -> None:
        self.area, self.version = area, self.version + 1

    def area_at(self, step: int) -> RestrictedArea | None:
        return self.area

    def version_at(self, step: int) -> int:
        return self.version


def observations(step: int, batch: int = 2) -> np.ndarray:
    """Observation of step `step`: its first number is the step, so plans show what they saw."""
    out = np.zeros((batch, CONFIG.obs_dim), dtype=np.float32)
    out[:, 0] = step
    return out


def lockstep(planner, zones=None, generator: torch.Generator | None = None, delay: int = 0,
             handover: str = "sync") -> ChunkLoop:
    """The loop as the evaluation runs it."""
    return ChunkLoop.simulated(planner, zones, generator, delay, handover)


def run(loop: ChunkLoop, steps: range, batch: int = 2) -> np.ndarray:
    return np.stack([loop.observe(t, observations(t, batch)) for t in steps])


def test_executes_the_chunk_from_the_first_executed_waypoint_and_replans_when_used_up() -> None:
    planner = Scripted()
    setpoints = run(lockstep(planner), range(20))
    assert [step for step, _, _ in planner.calls] == [0, 8, 16]  # every n_action_steps
    assert all(rows == [0, 1] for _, rows, _ in planner.calls)
    expected_x = np.r_[1000 * 0 + np.arange(1, 9), 1000 * 1 + np.arange(1, 9),
                       1000 * 2 + np.arange(1, 5)]
    np.testing.assert_array_equal(setpoints[:, 0, 0], expected_x + 0.5)  # after the guard
    np.testing.assert_array_equal(setpoints[:, 1, 1], 1.5)  # row 1's own chunk
    np.testing.assert_array_equal(planner.guarded[3][:, 0], [4.0, 4.0])  # the guard saw all


def test_a_zone_change_into_the_rest_of_a_chunk_replans_those_rows_at_once() -> None:
    planner, zones = Scripted(), Zones()
    executor = lockstep(planner, zones)
    run(executor, range(3))  # chunk 0 planned at step 0; waypoints 1..3 executed
    # A zone over row 1's remaining waypoints (y = 1), not row 0's (y = 0), not the executed ones.
    zones.set(ZoneSet.from_polygons([rectangle(4.5, 0.5, 7.5, 1.5)]))
    setpoints = run(executor, range(3, 5))
    assert [(step, rows) for step, rows, _ in planner.calls] == [(0, [0, 1]), (3, [1])]
    assert planner.calls[1][2] is zones.area  # planned with the zones in force
    np.testing.assert_array_equal(setpoints[0, :, 0], [4.5, 1001.5])  # row 1 starts afresh
    # The same zones again: nothing changed, nothing replanned, though row 0's chunk is free.
    run(executor, range(5, 8))
    assert len(planner.calls) == 2


def test_changed_zones_the_chunk_stays_out_of_do_not_replan() -> None:
    planner, zones = Scripted(), Zones()
    executor = lockstep(planner, zones)
    run(executor, range(2))
    zones.set(ZoneSet.from_polygons([rectangle(300, 300, 400, 400)]))  # far from every waypoint
    run(executor, range(2, 6))
    zones.set(None)  # and removed
    run(executor, range(6, 8))
    assert [step for step, _, _ in planner.calls] == [0]


def test_a_new_episode_starts_afresh_and_reseeds_the_noise() -> None:
    planner = Scripted()
    generator = torch.Generator().manual_seed(5)
    executor = lockstep(planner, generator=generator)
    run(executor, range(3))
    torch.rand(3, generator=generator)  # noise drawn in the first episode
    executor.reset(noise_seed=5)
    fresh = torch.Generator().manual_seed(5)
    assert planner.resets == 1
    assert torch.equal(torch.rand(4, generator=generator), torch.rand(4, generator=fresh))
    run(executor, range(2))
    assert [step for step, _, _ in planner.calls] == [0, 0]  # a new plan at the new step 0
    assert executor.stats.planner_calls == 2 and executor.stats.planned_chunks == 4


def test_the_history_repeats_the_observation_before_a_missed_step() -> None:
    """A real-time node may miss an observation: the step it missed repeats the one before;
    after a gap as long as the history, the newest stands for every step, as at the start."""
    history = ObservationHistory(np.array([[1.0]]), n_steps=3)
    history.push(np.array([[2.0]]))
    history.push(np.array([[4.0]]), steps=2)  # step 3 missed
    np.testing.assert_array_equal(history.frames[0, :, 0], [2.0, 2.0, 4.0])
    history.push(np.array([[5.0]]), steps=0)  # step 4 again
    np.testing.assert_array_equal(history.frames[0, :, 0], [2.0, 2.0, 5.0])
    history.push(np.array([[9.0]]), steps=3)
    np.testing.assert_array_equal(history.frames[0, :, 0], [9.0, 9.0, 9.0])
