"""How the policy node meets time, one class per mode (`MODES`), so that the node itself has no
mode flag to branch on:

- `Lockstep`: the simulator waits for each answer. An observation is answered at once with the
  setpoint for it, planned in this process when due; nothing is sent between observations.
- `Realtime`: a control clock sends the setpoint in force at every tick, plans are made in the
  background, and a zone change is answered at once with a safe setpoint. This mode owns the
  operating-system tuning a live loop needs (the interpreter's switch interval, a frozen
  collector, the clock's and the executor's priorities: runtime/os_scheduling.py asks for them).

Each is handed the node (a `PolicyNode`), and uses what configure built on it: `observations`,
`output`, `loop`, `robot`, `values`, `take` (the checked observation) and the status callbacks.
"""

from __future__ import annotations

import gc
import sys
import time

import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.lifecycle import Node as LifecycleNode

from constrained_diffusion_ros.planning.chunk_loop import ChunkLoop
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.runtime.clock import ControlClock
from constrained_diffusion_ros.runtime.live_loop import live_chunk_loop, loop_status, warm_up
from constrained_diffusion_ros.runtime.os_scheduling import request_fifo
from msg_schemas.conversions import step_of_stamp
from msg_schemas.text import one_line

STATUS_PERIOD_S = 0.5  # realtime: status this often
SWITCH_INTERVAL_S = 0.0002  # realtime: the clock thread waits at most this for another's GIL


class Lockstep:
    """Each observation answered at once, the simulator waiting for it (evaluation in ROS)."""

    name = "lockstep"
    default_runtime = "torch"  # bit for bit the in-process evaluation
    realtime = False  # for ZoneIngest: masks built in line, batches taken as they come

    def __init__(self, node: LifecycleNode) -> None:
        self.node = node
        self.last_stamp = -1.0  # the observation answered last
        self.runs_restarted = 0  # a reset is a new episode here, not a restarted run

    def tune(self) -> None:
        pass

    def watchdog_s(self) -> float:
        return 0.0  # nothing is sent between observations: nothing to withhold

    def plans_here(self) -> bool:
        return True

    def make_loop(self, planner: ConstrainedPlanner) -> ChunkLoop:
        """A fresh loop for every planner, as a fresh node would run."""
        node = self.node
        return ChunkLoop.simulated(planner, node.zones, node.generator,
                                   noise_seed=node.values["noise_seed"],
                                   on_install=node.after_plan)

    def start(self) -> None:
        pass

    def observe(self, stamp: float, stamp_msg) -> None:
        node = self.node
        if stamp == self.last_stamp:
            # The simulator re-sends an observation until answered: the answer may have been
            # lost to a subscriber not yet matched, so send it again (no new plan, no noise).
            node.output.repeat()
            return
        observation = node.take(stamp)
        if stamp < self.last_stamp or stamp == 0.0:  # the simulator was reset: a new episode
            node.loop.reset()
        self.last_stamp = stamp
        if observation is None:  # the simulator waits for an answer: the last sound setpoint
            if node.sound.last_sound is not None:
                node.send(node.sound.last_sound, stamp_msg)
            return
        started = time.perf_counter()
        setpoint = node.loop.observe(step_of_stamp(stamp_msg, node.robot.control_hz),
                                     observation.astype(np.float32))
        planning_ms = 1000 * (time.perf_counter() - started)
        node.send(setpoint, stamp_msg)
        node.publish_status(planning_ms)

    def zones_changed(self, received: float) -> None:
        pass  # the next observation is answered against them

    def status(self) -> dict[str, object]:
        return {}

    def shutdown(self, wait: bool = True) -> None:
        pass


class Realtime:
    """A control clock sends the setpoint in force at every tick; plans are made in the
    background and installed when the worker wakes the node; zones are answered at once."""

    name = "realtime"
    default_runtime = "onnxruntime"  # a plan at batch 1 is mostly torch's dispatch overhead
    realtime = True  # for ZoneIngest: masks built off the executor, zone batches paced

    def __init__(self, node: LifecycleNode) -> None:
        self.node = node
        self.latest_stamp = None  # the newest observation's stamp
        self.runs_restarted = 0  # observations whose stamp went back (a new run)
        self.clock: ControlClock | None = None
        self.executor_realtime: bool | None = None  # asked for on the executor's own thread

    def watchdog_s(self) -> float:
        return self.node.values["executor_watchdog_s"]

    def plans_here(self) -> bool:
        return not self.node.values["planning_process"]

    def make_loop(self, planner: ConstrainedPlanner) -> ChunkLoop:
        """One loop for the node's life; a new planner (a configuration set at run time) goes
        into it, so the planning process and the clock keep running."""
        node, values = self.node, self.node.values
        warm_up(planner)  # the first zone does not pay for first calls
        if node.loop is not None:
            node.loop.use_planner(planner)
            return node.loop
        lead = values["lead"]
        return live_chunk_loop(
            planner, node.zones,
            values["torch_threads"] if values["planning_process"] else None,
            values["planning_idle"], noise_seed=values["noise_seed"],
            lead=None if lead < 0 else lead, soft=values["prefix_soft"], rate_hz=node.rate_hz,
            wake=node.create_guard_condition(self._on_plan_ready).trigger,
            every_tick=values["replan_every_tick"],
            replan_on_zone_change=values["replan_on_zone_change"], on_install=node.after_plan)

    def tune(self) -> None:
        """Before the policy loads: the clock thread waits at most SWITCH_INTERVAL_S for the
        interpreter lock."""
        sys.setswitchinterval(SWITCH_INTERVAL_S)

    def start(self) -> None:
        """The clock, the status timer and the watchdog's feed, once the rest is built."""
        node = self.node
        # What start-up built (policy, torch, rclpy) lives as long as the node: out of the
        # collector's sight, so a full collection does not hold the GIL to scan it all. Before
        # the clock starts: this last full pass holds the GIL (about 150 ms on a 2-core VM), and
        # a clock thread cannot send a tick without it.
        gc.collect()
        gc.freeze()
        self.clock = ControlClock(node.rate_hz, node.output.repeat)
        if not self.clock.realtime:
            node.get_logger().warning(
                "control clock without real-time priority (not allowed here: raise rtprio in "
                "/etc/security/limits.conf); ticks may be late on a busy machine")
        node.create_timer(STATUS_PERIOD_S, self._on_status_timer)
        watchdog_s = self.watchdog_s()
        if watchdog_s > 0:  # the clock's watchdog, fed 5x in its time, sim time or not
            node.create_timer(watchdog_s / 5, node.output.beat,
                              clock=Clock(clock_type=ClockType.STEADY_TIME))

    def observe(self, stamp: float, stamp_msg) -> None:
        """The setpoint the clock sends from now on."""
        node = self.node
        new_run = node.observations.starts_run(stamp)
        # A reset, or a participant sending old stamps: said either way (WARN).
        self.runs_restarted += node.observations.ends_run(stamp)
        if new_run:  # a reset: the run before's setpoint is never sent again, and nothing is
            self.latest_stamp = None  # sent until this run's first observation is taken
            node.output.withdraw()
        observation = node.take(stamp)
        if observation is None:
            return
        if new_run:  # none of the run before's plans (one in flight) goes into this one,
            node.loop.reset()  # even where its first stamp equals the last
        self.latest_stamp = stamp_msg
        step = step_of_stamp(stamp_msg, node.robot.control_hz)
        self._send(node.loop.observe(step, observation))

    def zones_changed(self, received: float) -> None:
        """The held setpoint checked now, and a safe one published at once (how long after:
        `zone_to_setpoint_ms` in the status)."""
        node = self.node
        node.reaction.safe_setpoint_sent(received, self._send(node.loop.zones_changed(),
                                                              publish=True))

    def _on_plan_ready(self) -> None:
        """Woken by the planning worker (or a zone change): plans installed, and whatever is
        due asked for."""
        self._send(self.node.loop.install_results())

    def _send(self, setpoint: np.ndarray | None, publish: bool = False) -> float | None:
        """Stamped with the newest observation's stamp; sent by the clock's next tick unless
        `publish`."""
        return self.node.send(setpoint, self.latest_stamp, publish)

    def _on_status_timer(self) -> None:
        if self.executor_realtime is None:
            # On the thread that runs the callbacks: with FIFO priority it answers a zone
            # without waiting for other processes' time slices (the planning process, started
            # before, keeps normal scheduling).
            self.executor_realtime = request_fifo(self.node.values["executor_priority"])
        self.node.publish_status(self.node.loop.stats.last_plan_ms)

    def status(self) -> dict[str, object]:
        values = {**loop_status(self.node.loop), **self.clock.status(),
                  "executor_realtime": self.executor_realtime}
        values["planning_error"] = one_line(values["planning_error"] or "")
        return values

    def shutdown(self, wait: bool = True) -> None:
        """The clock stopped (`wait`: its thread joined)."""
        if self.clock is not None:
            if wait:
                self.clock.shutdown()
            else:
                self.clock.shutdown(timeout=0.0)


MODES = {mode.name: mode for mode in (Lockstep, Realtime)}
