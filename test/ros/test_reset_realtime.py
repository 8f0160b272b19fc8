"""A reset while the realtime policy runs (issue 41, finding 3): with a keep-out mask in force,
the policy went on sending setpoints stamped for the run before up to about 110 ms after the
new run's first observation, the simulator stepped toward them, and they dragged the pusher
across a keep-out bar. A reset ends the old run's commands on both sides: the simulator drops
setpoints stamped for another run, and the policy stops sending them.

The first tests run the policy node's observation path on stand-ins (no DDS); the others run
the nodes over DDS in a domain of this module's own, so no zone latched by another module's
test is in force.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import shapely
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
from nav_msgs.msg import OccupancyGrid
from nav_msgs.msg import Path as PathMsg
from rclpy.logging import get_logger
from realtime_link import TICK_S, RealtimeLink, status_values
from ros_helpers import observation_messages, stamp_ns, step_ns, step_stamp
from std_srvs.srv import Trigger

from constrained_diffusion_ros.nodes.observation_input import ObservationInput
from constrained_diffusion_ros.nodes.policy_modes import Realtime
from constrained_diffusion_ros.nodes.policy_node import PolicyNode
from constrained_diffusion_ros.nodes.setpoint_output import SetpointOutput
from constrained_diffusion_ros.planning.chunk_loop import ChunkLoop
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.planning.liveness import StandstillCounts
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.planning.sound_setpoints import SoundSetpoints
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones import LiveZones
from msg_schemas import FRAME_ID, SERVICES, TOPICS
from msg_schemas.conversions import occupancy_grid, stamp_nanoseconds
from sim_bridge import AGENT_RADIUS
from sim_bridge.scene import seeded_state

# --------------------------------------------------------------------------- on stand-ins


class StandInNode:
    """What `ObservationInput` and `SetpointOutput` ask of a node, without rclpy: setpoints
    published are kept in `published`."""

    def __init__(self) -> None:
        self.published: list[PointStamped] = []
        self.context = SimpleNamespace(ok=lambda: True)

    def create_subscription(self, *args: object, **kwargs: object) -> None:
        return None

    def create_publisher(self, *args: object) -> SimpleNamespace:
        return SimpleNamespace(publish=self.published.append)

    def get_logger(self):
        return get_logger("stand_in")


class RealtimeObservations:
    """The policy node's realtime observations (`policy_modes.Realtime.observe`), on
    stand-ins: the node's own observation input and setpoint output, and a chunk loop whose
    plans arrive `delay` steps after they are asked for. `observe` feeds one observation's two
    halves, `tick` is the clock's."""

    def __init__(self, policy, delay: int = 2) -> None:
        self.stand_in = StandInNode()
        zones = LiveZones(workspace=PUSHT_ROBOT.workspace)
        sound = SoundSetpoints(PUSHT_ROBOT, zones)
        config = ConstraintConfig("safe", sampler="ddim", denoising_steps=3, project=True,
                                  inflate=True, shield=True)
        planner = ConstrainedPlanner(policy, config, PUSHT_ROBOT)
        self.loop = ChunkLoop.simulated(planner, zones, delay=delay, handover="async")
        node = SimpleNamespace(robot=PUSHT_ROBOT, zones=zones, sound=sound, loop=self.loop,
                               standstills=StandstillCounts(),
                               output=SetpointOutput(self.stand_in, sound))
        for method in ("take", "send"):
            setattr(node, method, getattr(PolicyNode, method).__get__(node))
        self.timing = Realtime(node)
        node.observations = ObservationInput(self.stand_in, PUSHT_ROBOT, self.timing.observe)
        self.node = node

    def observe(self, step: int, pusher: tuple[float, float]) -> None:
        keypoints, message = observation_messages(step, pusher)
        self.node.observations._on_keypoints(keypoints, {})
        self.node.observations._on_pusher(message, {})

    def tick(self) -> list[tuple[int, tuple[float, float]]]:
        """The clock's tick: what it sent, as (stamp ns, point)."""
        before = len(self.stand_in.published)
        self.node.output.repeat()
        return [(stamp_nanoseconds(m.header.stamp), (m.point.x, m.point.y))
                for m in self.stand_in.published[before:]]


def test_after_a_reset_whose_first_observation_is_refused_no_setpoint_of_the_run_before_is_sent(
        tiny_policy) -> None:
    """The clock re-sent the run before's setpoint until the new run's first observation was
    taken; one that is refused left it in force for good. A new run's first observation (a
    stamp no later than the last) ends it, taken or not."""
    node = RealtimeObservations(tiny_policy)
    for step in range(6):
        node.observe(step, (100.0, 100.0))
    assert [stamp for stamp, _ in node.tick()] == [step_ns(5)]
    node.observe(0, (1e6, 1e6))  # the new run's first: refused
    assert node.tick() == []
    node.observe(1, (300.0, 300.0))  # taken: this run's setpoint, the pusher held
    assert node.tick() == [(step_ns(1), (300.0, 300.0))]


def test_a_new_run_stays_new_until_one_of_its_observations_is_taken(tiny_policy) -> None:
    """The run before reached step 1; the new run's first two observations are refused, so its
    third is stamped later than the run before's last. It still starts a run: taken (not
    judged a jump from the old run's pusher), counted once, the loop started afresh."""
    node = RealtimeObservations(tiny_policy)
    for step in range(2):
        node.observe(step, (100.0, 100.0))
    for step in range(2):
        node.observe(step, (1e6, 1e6))  # the new run's first two: refused
    assert node.timing.runs_restarted == 1
    node.observe(2, (400.0, 400.0))
    assert node.node.observations.refused == 2
    assert node.timing.runs_restarted == 1
    assert node.node.observations.moved is None  # a new episode's first
    assert node.tick() == [(step_ns(2), (400.0, 400.0))]
    assert node.loop.stats.plans_asked == 2  # the run before's, and this one's afresh


def test_a_plan_asked_for_the_run_before_never_goes_into_a_run_that_starts_at_the_same_stamp(
        tiny_policy) -> None:
    """A reset right after the first step: the new run starts at the stamp of the last one
    (0), which the loop alone (it resets on an earlier step) cannot tell from a repeat. The
    plan asked for the run before, on its way, is dropped; the new run's own goes in."""
    node = RealtimeObservations(tiny_policy, delay=2)
    node.observe(0, (100.0, 100.0))  # run A: its plan comes at step 2
    node.observe(0, (400.0, 400.0))  # run B
    for step in (1, 2):
        node.observe(step, (400.0, 400.0))
    stats = node.loop.stats
    assert (stats.plans_asked, stats.plans_dropped, stats.plans_installed) == (2, 1, 1)
    assert node.tick()[0][0] == step_ns(2)


# --------------------------------------------------------------------------- over DDS


BAR = shapely.box(240.0, 232.0, 480.0, 256.0)  # the keep-out bar: 4 px cells 58-63, 60-119


def keepout_bar() -> OccupancyGrid:
    """`BAR` as a 128 x 128 keep-out mask of 4 px cells (the same in every test of the module:
    a mask another test latched may reach a node first)."""
    mask = np.zeros((128, 128), dtype=np.int8)
    mask[58:64, 60:120] = 100
    return occupancy_grid(mask, 4.0, (0.0, 0.0), step_stamp(0))


def test_the_policy_sends_nothing_of_the_run_before_once_the_new_run_begins(
        ros, processes, tiny_model, configurations_file) -> None:
    """The realtime node fed by the test, a keep-out mask in force: the new run's first
    observation is refused (a pusher no robot can be at), and no setpoint stamped for the run
    before goes out after it; the next, taken, starts this run's setpoints."""
    link = RealtimeLink(ros, processes, tiny_model, configurations_file)
    stamps: list[int] = []
    ros.inbox("setpoint", PointStamped, lambda m: stamps.append(stamp_ns(m.header.stamp)))
    link.masks.publish(keepout_bar())
    link.latest_status(lambda v: any(i.startswith("keepout/") for i in v["zone_ids"].split(",")))
    link.planning()
    last = link.step - 1
    assert link.ros.spin_until(lambda: stamps and stamps[-1] == step_ns(last), 2 * TICK_S + 5)
    link.step = 0  # a reset
    link.observe((1e6, 1e6))
    link.latest_status(lambda v: int(v["observations_refused"]) >= 1)
    mark = len(stamps)
    ros.spin_for(2.5 * TICK_S)  # two ticks: nothing of the run before
    assert stamps[mark:] == [], link.processes.logs()
    link.observe()  # step 1, taken
    assert ros.spin_until(lambda: step_ns(1) in stamps[mark:], 2 * TICK_S + 5)
    assert set(stamps[mark:]) == {step_ns(1)}
    # A new run is said (it may as well be a participant sending old stamps).
    status = link.latest_status(lambda v: v.get("runs_restarted") == "1")
    assert any("new run(s)" in s.status[0].message for s in link.statuses), status


def targets_held(positions: np.ndarray) -> np.ndarray:
    """(K - 1, 2) the setpoint the simulator held over each step of the pusher's K positions,
    from rest at the first: the PD law inverted (`RobotModel.transition`), exact because the
    pusher is kinematic (nothing but its setpoint moves it)."""
    (a, b, c), (d, e, f) = PUSHT_ROBOT.transition(PUSHT_ROBOT.substeps)[-1]
    position, velocity, held = positions[0], np.zeros(2), []
    for after in positions[1:]:
        target = (after - a * position - b * velocity) / c
        velocity = d * position + e * velocity + f * target
        position = after
        held.append(target)
    return np.array(held)


def deepest_into(area: shapely.Geometry, positions: np.ndarray) -> float:
    """How deep (px) the pusher's disc went into `area` at any of `positions`."""
    depths = [AGENT_RADIUS - area.exterior.distance(shapely.Point(*p))
              if not area.contains(shapely.Point(*p))
              else AGENT_RADIUS + area.exterior.distance(shapely.Point(*p)) for p in positions]
    return max(0.0, *depths)


def test_after_a_reset_no_setpoint_of_the_run_before_moves_the_pusher(
        ros, processes, tiny_model, configurations_file) -> None:
    """The simulator and the policy, realtime, seed 100001, a keep-out bar between the pusher's
    start and a point below it. The old run goes to step 20, then the sim is reset. Setpoints
    stamped for the old run, aimed across the bar, then reach the sim as the clock of a node
    that has not heard of the reset would send them (whether the policy's own clock falls in
    that window is chance): the sim drops them, and every step of the new run is toward a
    setpoint of the new run (the PD law inverted from the pusher's positions). The policy
    sends none of the old run's after its first of the new one."""
    seed, old_steps, new_steps = 100001, 20, 8
    start = np.array(seeded_state(seed)[:2])  # (365, 182)
    across = (365.0, 330.0)  # straight through the bar from the start
    arrivals: list[PointStamped] = []
    ros.inbox("setpoint", PointStamped, arrivals.append)
    pushers = ros.inbox("pusher", PointStamped)
    statuses = ros.inbox("diagnostics", DiagnosticArray)
    plans = ros.inbox("plan", PathMsg)
    masks = ros.publisher("keepout_mask", OccupancyGrid)
    stale = ros.publisher("setpoint", PointStamped)
    reset = ros.node.create_client(Trigger, SERVICES["reset"].name)
    _, sim_log = processes.start("sim_node", seed=seed, mode="realtime", autostart=False)
    processes.start("policy_node", model=tiny_model, configurations_file=configurations_file,
                    configuration="fast_safe", mode="realtime")
    assert ros.spin_until(lambda: reset.service_is_ready()
                          and masks.get_subscription_count() >= 1
                          and stale.get_subscription_count() >= 2  # the sim's and ours
                          and ros.node.count_publishers(TOPICS["setpoint"].name) >= 2
                          and ros.node.count_subscribers(TOPICS["pusher"].name) >= 2), \
        processes.logs()
    masks.publish(keepout_bar())

    def keepout_in_force() -> bool:
        return bool(statuses) and any(i.startswith("keepout/") for i in status_values(
            statuses[-1]).get("zone_ids", "").split(","))

    assert ros.spin_until(keepout_in_force), processes.logs()

    def call_reset() -> None:
        future = reset.call_async(Trigger.Request())
        assert ros.spin_until(future.done, 10.0) and future.result().success

    call_reset()  # the old run starts: it runs until the policy answers its late steps
    assert ros.spin_until(lambda: plans and arrivals
                          and stamp_ns(arrivals[-1].header.stamp) >= step_ns(old_steps),
                          60.0), processes.logs()
    in_force = stamp_ns(arrivals[-1].header.stamp)
    mark = len(pushers)
    call_reset()
    assert ros.spin_until(lambda: any(stamp_ns(m.header.stamp) == 0 for m in pushers[mark:]))
    first = next(i for i in range(mark, len(pushers)) if stamp_ns(pushers[i].header.stamp) == 0)
    sent_before_reset = len(arrivals)
    for _ in range(10):  # the old run's setpoint, aimed across the bar, for about 0.2 s
        message = PointStamped()
        sec, nanosec = divmod(in_force, 10**9)
        message.header.stamp, message.header.frame_id = Time(sec=sec, nanosec=nanosec), FRAME_ID
        message.point.x, message.point.y = across
        stale.publish(message)
        ros.spin_for(0.02)
    assert ros.spin_until(lambda: stamp_ns(pushers[-1].header.stamp) >= step_ns(new_steps), 10.0)

    new_run = pushers[first:]
    steps = [stamp_ns(m.header.stamp) for m in new_run]
    assert steps[:new_steps + 1] == [step_ns(k) for k in range(new_steps + 1)], steps
    positions = np.array([(m.point.x, m.point.y) for m in new_run[:new_steps + 1]])
    assert np.array_equal(positions[0], start)
    depth = deepest_into(BAR, positions)
    held = targets_held(positions)
    policy_after = [m for m in arrivals[sent_before_reset:]
                    if (m.point.x, m.point.y) != across]
    this_run = np.array([[start]] + [[(m.point.x, m.point.y)] for m in policy_after
                                     if stamp_ns(m.header.stamp) <= step_ns(new_steps)])
    for k, target in enumerate(held, start=1):
        assert np.linalg.norm(target - across) > 1.0, \
            f"step {k} of the new run was toward the old run's setpoint {across}; the disc " \
            f"went {depth:.1f} px into the bar\n{sim_log.read_text()}"
        assert np.min(np.linalg.norm(this_run[:, 0] - target, axis=-1)) < 1e-3, (k, target)
    assert "dropped" in sim_log.read_text()
    new = [i for i, m in enumerate(policy_after) if stamp_ns(m.header.stamp) < in_force]
    assert new and all(stamp_ns(m.header.stamp) < in_force for m in policy_after[new[0]:])
