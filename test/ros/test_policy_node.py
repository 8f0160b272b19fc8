"""policy_node over real DDS, in a loop with the simulator closed through the test: a zone
from another process obeyed, malformed ones refused, and a removed zone no longer obeyed.

The policy is a tiny random network (saved to a temporary directory) with 5-step DDIM
configurations, so a trial takes seconds. Its unconstrained setpoints are noise-like and pile up
at the workspace edges: measured on scene 100000 with noise seed 0, about a third of them fall in
the top band y < 64, which is therefore the zone the lifecycle test places, so that obeying it is
not vacuous. Everything here is deterministic (lockstep simulation, seeded noise, zone changes at
fixed steps); the waits only absorb process start-up and discovery.
"""

from __future__ import annotations

import time

import numpy as np
import shapely
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Point32, PointStamped, PolygonInstanceStamped, PolygonStamped
from nav_msgs.msg import Path as PathMsg
from ros_helpers import Ros, observation_messages, shown_zone_ids, stamp_step, step_stamp
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from constrained_diffusion_ros.nodes.observation_input import PENDING_HALVES, keep_pending
from constrained_diffusion_ros.nodes.policy_status import ReactionTimes
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from msg_schemas import FRAME_ID, SERVICES, TOPICS
from sim_bridge import AGENT_RADIUS

SEED = 100000
ZONE_ID = 7
ZONE = ((0.0, 0.0), (512.0, 0.0), (512.0, 64.0), (0.0, 64.0))  # the top band, see above
ZONE_SHAPE = shapely.Polygon(ZONE)
BOW_TIE = ((100.0, 100.0), (200.0, 200.0), (200.0, 100.0), (100.0, 200.0))
TWO_POINTS = ((300.0, 300.0), (350.0, 350.0))
PRE_ZONE_STEPS = 12  # mid-chunk (chunks of 8 start at steps 0, 8, 16, ...)
PROBE_STEP = 10_000  # stamps of the test's own probe observations: far past any trial step
# The sim's setpoint input is remapped here, so only setpoints the test forwards reach it.
GATED_SETPOINT = TOPICS["setpoint"].name + "_gated"


def depth(msg: PointStamped) -> float:
    """How far a setpoint lies inside the zone (px); negative outside, 0 on its boundary."""
    point = shapely.Point(msg.point.x, msg.point.y)
    distance = ZONE_SHAPE.exterior.distance(point)
    return distance if ZONE_SHAPE.contains(point) else -distance


def values(report: DiagnosticArray) -> dict[str, str]:
    """The policy's counters in one /diagnostics message."""
    return {kv.key: kv.value for kv in report.status[0].values}


class GatedLoop:
    """The sim and the policy closed through the test node: the policy publishes on the contract
    topic, the sim listens on a remapped one, and the test forwards one setpoint at a time. So
    the test knows exactly which setpoints were computed after a zone change took effect."""

    def __init__(self, ros: Ros) -> None:
        self.ros = ros
        self.setpoints: dict[int, PointStamped] = {}
        self.received = 0  # distinct setpoints; the policy publishes one status with each
        self.duplicates: list[bool] = []  # per repeated answer: identical to the first?
        ros.inbox("setpoint", PointStamped, self._keep)
        self.statuses = ros.inbox("diagnostics", DiagnosticArray)
        self.markers = ros.inbox("zone_markers", MarkerArray)
        self.gate = ros.publisher("setpoint", PointStamped, GATED_SETPOINT)
        self.zones = ros.publisher("zones", PolygonInstanceStamped)
        self.probe_keypoints = ros.publisher("keypoints", PolygonStamped)
        self.probe_pusher = ros.publisher("pusher", PointStamped)
        self.reset = ros.node.create_client(Trigger, SERVICES["reset"].name)
        self.forwarded = 0  # setpoints forwarded to the sim so far = steps executed

    def _keep(self, msg: PointStamped) -> None:
        step = stamp_step(msg.header.stamp)
        if step in self.setpoints:  # the policy re-sends its answer to a re-sent observation
            first = self.setpoints[step].point
            self.duplicates.append((msg.point.x, msg.point.y) == (first.x, first.y))
            return
        self.received += 1
        self.setpoints[step] = msg

    def discovered(self) -> bool:
        """Every endpoint of the test node matched, as the test node sees it, and the policy
        subscribed to the sim's observations (`probe` checks the policy's side)."""
        graph = self.ros.node
        return (all(s.get_publisher_count() >= 1 for s in graph.subscriptions)
                and self.gate.get_subscription_count() >= 1
                and self.zones.get_subscription_count() >= 1
                and self.probe_keypoints.get_subscription_count() >= 1
                and self.probe_pusher.get_subscription_count() >= 1
                and graph.count_subscribers(TOPICS["pusher"].name) >= 1
                and graph.count_subscribers(TOPICS["keypoints"].name) >= 1
                and self.reset.service_is_ready())

    def wait_answer(self, step: int) -> PointStamped:
        """The policy's setpoint for observation `step`, and its status."""
        assert self.ros.spin_until(lambda: step in self.setpoints, 15.0), \
            f"no setpoint for step {step}"
        assert self.ros.spin_until(lambda: len(self.statuses) >= self.received, 5.0)
        return self.setpoints[step]

    def probe(self) -> None:
        """Observations from the test node until the policy answers one.

        Matching is not symmetric: the test's reader can see the policy's writer before that
        writer sees the reader, and a setpoint published in between is lost for good (the
        policy answers each observation once; the sim's re-sends are dropped as repeats). An
        answer to a probe proves both of the policy's writers (setpoint, status) reach the test.
        The sim's first observation (stamp 0) then starts a new episode in the policy (chunk
        dropped, noise reseeded), so the probes leave no trace in the trial."""
        def answered() -> bool:
            return any(step >= PROBE_STEP for step in self.setpoints)

        for step in range(PROBE_STEP, PROBE_STEP + 40):  # a new stamp each: never a repeat
            stamp = step_stamp(step)
            keypoints = PolygonStamped()
            keypoints.header.stamp, keypoints.header.frame_id = stamp, FRAME_ID
            keypoints.polygon.points = [Point32(x=256.0, y=256.0 + i, z=0.0) for i in range(9)]
            pusher = PointStamped()
            pusher.header = keypoints.header
            pusher.point.x, pusher.point.y = 100.0, 100.0
            self.probe_keypoints.publish(keypoints)
            self.probe_pusher.publish(pusher)
            if self.ros.spin_until(answered, 0.5):
                assert self.ros.spin_until(lambda: len(self.statuses) >= self.received, 5.0)
                return
        raise AssertionError("the policy never answered a probe observation")

    def start(self) -> None:
        self.probe()
        future = self.reset.call_async(Trigger.Request())
        assert self.ros.spin_until(future.done, 10.0) and future.result().success
        self.wait_answer(0)

    def forward(self, n: int) -> None:
        """Execute the next `n` setpoints, one step each; ends holding the next answer."""
        for _ in range(n):
            self.gate.publish(self.setpoints[self.forwarded])
            self.forwarded += 1
            self.wait_answer(self.forwarded)

    def answers(self, first: int, last: int) -> list[PointStamped]:
        return [self.setpoints[step] for step in range(first, last + 1)]

    def zones_shown(self) -> list[np.ndarray] | None:
        """Polygons of the policy's latest zone markers (closing vertex dropped); None before
        any."""
        if not self.markers:
            return None
        return [np.array([(p.x, p.y) for p in m.points])[:-1]
                for m in self.markers[-1].markers if m.action == m.ADD]

    def publish_zone(self, zone_id: int, vertices) -> None:
        msg = PolygonInstanceStamped()
        msg.header.frame_id = FRAME_ID
        msg.polygon.id = zone_id
        msg.polygon.polygon.points = [Point32(x=x, y=y, z=0.0) for x, y in vertices]
        self.zones.publish(msg)


def test_zone_from_another_process_obeyed_refused_and_removed(
        ros, processes, tiny_model, configurations_file):
    loop = GatedLoop(ros)
    _, sim_log = processes.start("sim_node",
                                 remap={TOPICS["setpoint"].name: GATED_SETPOINT},
                                 seed=SEED, mode="lockstep", autostart=False)
    policy, policy_log = processes.start("policy_node", model=tiny_model,
                                         configurations_file=configurations_file,
                                         configuration="fast_project")

    def logs() -> str:
        return "\n".join(f"--- {log.name}\n{log.read_text()}" for log in processes.log_dir.glob(
            "*.log"))

    assert ros.spin_until(loop.discovered), f"nodes not discovered:\n{logs()}"
    loop.start()

    # (a) A zone arrives mid-trial from a zone_publisher process; every later setpoint obeys it.
    loop.forward(PRE_ZONE_STEPS)  # answers 0..12 computed with no zone; 0..11 executed
    unconstrained = loop.answers(0, loop.forwarded)
    assert sum(depth(m) > 1.0 for m in unconstrained) >= 2, \
        "the tiny policy no longer goes where the zone will be: the test would be vacuous"
    text = ";".join(f"{x:g},{y:g}" for x, y in ZONE)
    processes.start("zone_publisher_add", "zone_publisher", polygon=text,
                    zone_id=ZONE_ID, rate_hz=0.0)  # once, latched
    assert ros.spin_until(lambda: loop.zones_shown() is not None and len(loop.zones_shown()) == 1),\
        f"the policy never showed the zone:\n{logs()}"
    shown = loop.zones_shown()[0]
    assert shapely.Polygon(shown).equals(ZONE_SHAPE)
    first_constrained = loop.forwarded + 1  # the held answer was computed before the zone
    loop.forward(16)
    constrained = loop.answers(first_constrained, loop.forwarded)
    assert len(constrained) == 16
    assert max(depth(m) for m in constrained) < 0.0, \
        [(m.point.x, m.point.y) for m in constrained if depth(m) >= 0.0]
    status = values(loop.statuses[-1])
    assert status["zones"] == "1" and status["violations"] == "0"
    assert status["configuration"] == "fast_project"

    # (c) Malformed zones from the test node: refused with a warning naming the fault; the zone
    # in force (same id 7 for the bow-tie) stays, setpoints keep coming and keep obeying it.
    markers_before, statuses_before = len(loop.markers), len(loop.statuses)
    loop.publish_zone(ZONE_ID, BOW_TIE)
    loop.publish_zone(ZONE_ID + 1, TWO_POINTS)

    def refused() -> bool:
        text = policy_log.read_text()
        return all(s in text for s in ("zone 7 refused", "Self-intersection", "zone 8 refused",
                                       "at least 3 distinct vertices"))

    assert ros.spin_until(refused, 10.0), policy_log.read_text()
    mark = loop.forwarded
    loop.forward(12)  # past a chunk boundary: at least one new plan after the refusals
    after_refusal = loop.answers(mark + 1, loop.forwarded)
    assert max(depth(m) for m in after_refusal) < 0.0
    statuses = loop.statuses[statuses_before:]
    assert len(statuses) >= 12 and {values(s)["zones"] for s in statuses} == {"1"}
    warned = [s.status[0] for s in statuses if s.status[0].level == DiagnosticStatus.WARN]
    assert warned and "refused" in warned[0].message  # then OK again: nothing new refused
    assert statuses[-1].status[0].level == DiagnosticStatus.OK
    assert len(loop.markers) == markers_before  # the zones in force never changed
    assert policy.poll() is None and "Traceback" not in policy_log.read_text()

    # (b) Removal by another zone_publisher process (empty polygon for id 7): the policy is free
    # to enter the former zone again, and the tiny policy does within a few chunks.
    assert processes.stop("zone_publisher_add") == 0  # rate 0: it would not re-send anyway
    processes.start("zone_publisher_remove", "zone_publisher", remove_id=ZONE_ID, rate_hz=0.0)
    assert ros.spin_until(lambda: loop.zones_shown() == []), \
        f"the policy never removed the zone:\n{logs()}"
    first_free = loop.forwarded + 1
    for _ in range(32):
        if depth(loop.setpoints[loop.forwarded]) > 1.0 and loop.forwarded >= first_free:
            break
        loop.forward(1)
    reentered = [m for m in loop.answers(first_free, loop.forwarded) if depth(m) > 1.0]
    assert reentered, "no setpoint entered the former zone within 32 steps after its removal"
    assert values(loop.statuses[-1])["zones"] == "0"
    assert all(loop.duplicates)  # a repeated answer is the same setpoint: nothing replanned
    assert "Traceback" not in sim_log.read_text()




REALTIME_PERIOD_S = 4.0  # long ticks: a setpoint between two of them was not a tick's
PUSHER = (40.0, 470.0)  # px: where the test's observations put the pusher
EVERYTHING_ID = 500  # a zone id no other test of the module uses (their zones are replayed)


def publish_observation(keypoints_pub, pusher_pub, step: int) -> None:
    """One observation of control step `step`: a fixed T and the pusher at PUSHER."""
    keypoints, pusher = observation_messages(step, PUSHER)
    keypoints_pub.publish(keypoints)
    pusher_pub.publish(pusher)


def test_realtime_a_zone_mid_chunk_gets_a_safe_setpoint_before_the_next_tick(
        ros, processes, tiny_model, configurations_file):
    """The realtime node on its own clock: the test feeds it observations, waits for a tick
    that executes a planned waypoint, drops a zone on that setpoint and expects a setpoint
    outside the zone grown by the pusher radius well before the next tick."""
    arrivals: list[tuple[float, np.ndarray]] = []
    ros.inbox("setpoint", PointStamped, lambda m: arrivals.append(
        (time.monotonic(), np.array([m.point.x, m.point.y]))))
    statuses = ros.inbox("diagnostics", DiagnosticArray)
    plans = ros.inbox("plan", PathMsg)
    zones = ros.publisher("zones", PolygonInstanceStamped)
    keypoints_pub = ros.publisher("keypoints", PolygonStamped)
    pusher_pub = ros.publisher("pusher", PointStamped)
    processes.start("policy_node", model=tiny_model, configurations_file=configurations_file,
                    configuration="fast_safe", mode="realtime", rate_hz=1 / REALTIME_PERIOD_S)
    graph = ros.node
    assert ros.spin_until(lambda: all(p.get_subscription_count() >= 1
                                      for p in (zones, keypoints_pub, pusher_pub))
                          and graph.count_publishers(TOPICS["setpoint"].name) >= 1)

    def observe(step: int) -> None:
        publish_observation(keypoints_pub, pusher_pub, step)

    step = 0
    while not plans:  # observations until a plan is in (the first tick holds the pusher)
        observe(step)
        step += 1
        ros.spin_until(lambda: bool(plans), 0.5)
    ticks = len(arrivals)
    assert ros.spin_until(lambda: len(arrivals) > ticks, 2 * REALTIME_PERIOD_S + 5)
    tick_time, setpoint = arrivals[-1]  # a tick that executed a planned waypoint
    x, y = setpoint
    zone = ((x - 15, y - 15), (x + 15, y - 15), (x + 15, y + 15), (x - 15, y + 15))
    grown = shapely.Polygon(zone).buffer(AGENT_RADIUS - 0.5)
    msg = PolygonInstanceStamped()
    msg.header.frame_id, msg.polygon.id = FRAME_ID, 1
    msg.polygon.polygon.points = [Point32(x=float(a), y=float(b), z=0.0) for a, b in zone]
    before = len(arrivals)
    zones.publish(msg)
    assert ros.spin_until(lambda: len(arrivals) > before, REALTIME_PERIOD_S)
    reaction_time, safe = arrivals[before]
    assert reaction_time - tick_time < 0.75 * REALTIME_PERIOD_S  # not the next tick's
    assert not grown.contains(shapely.Point(*safe)), (setpoint, safe)
    assert ros.spin_until(lambda: statuses and int(values(statuses[-1]).get(
        "zone_reactions", 0)) >= 1, 2 * 0.5 + 5)


def test_zones_that_leave_no_free_space_hold_the_pusher_and_report_an_error(
        ros, processes, tiny_model, configurations_file):
    """A zone over everything (from -1e30 to 1e30: clipped to the workspace, so accepted and
    enforced): no setpoint can be safe, so the node holds the pusher where it is (never an
    out-of-range setpoint) and says ERROR; when the zone goes, it plans again and says OK."""
    answers: list[PointStamped] = []
    ros.inbox("setpoint", PointStamped, answers.append)
    reports = ros.inbox("diagnostics", DiagnosticArray)
    markers = ros.inbox("zone_markers", MarkerArray)
    zones = ros.publisher("zones", PolygonInstanceStamped)
    # Observations on topics of its own: the module's simulator keeps publishing on the others.
    private = {name: f"{name}_no_free_space" for name in ("keypoints", "pusher")}
    keypoints_pub = ros.publisher("keypoints", PolygonStamped, private["keypoints"])
    pusher_pub = ros.publisher("pusher", PointStamped, private["pusher"])
    processes.start("policy_node", model=tiny_model, configurations_file=configurations_file,
                    configuration="fast_safe", remap=private)
    assert ros.spin_until(lambda: all(p.get_subscription_count() >= 1
                                      for p in (keypoints_pub, pusher_pub))
                          and zones.get_subscription_count() == 2), processes.logs()

    def answer(step: int) -> tuple[np.ndarray, DiagnosticStatus]:
        count = len(reports)
        publish_observation(keypoints_pub, pusher_pub, step)
        assert ros.spin_until(lambda: len(reports) > count and answers
                              and stamp_step(answers[-1].header.stamp) == step, 30.0)
        return np.array([answers[-1].point.x, answers[-1].point.y]), reports[-1].status[0]

    everything = PolygonInstanceStamped()
    everything.header.frame_id, everything.polygon.id = FRAME_ID, EVERYTHING_ID
    everything.polygon.polygon.points = [Point32(x=x, y=y, z=0.0) for x, y in (
        (-1e30, -1e30), (1e30, -1e30), (1e30, 1e30), (-1e30, 1e30))]
    zones.publish(everything)

    def shows_everything() -> bool:  # (the test node's earlier zones are replayed too)
        return EVERYTHING_ID in (shown_zone_ids(markers) or [])

    assert ros.spin_until(shows_everything), processes.logs()
    # Steps of their own (from 500): no other node of the module answers these stamps.
    for step in range(500, 503):
        setpoint, report = answer(step)
        assert np.array_equal(setpoint, PUSHER)  # held where it is, inside the workspace
        assert report.level == DiagnosticStatus.ERROR
    removal = PolygonInstanceStamped()
    removal.header.frame_id, removal.polygon.id = FRAME_ID, EVERYTHING_ID
    zones.publish(removal)
    assert ros.spin_until(lambda: not shows_everything())
    setpoint, report = answer(503)
    assert report.level == DiagnosticStatus.OK, report.message  # space again: sound setpoints
    assert not PUSHT_ROBOT.outside(setpoint)


def test_observation_halves_that_never_pair_cannot_pile_up() -> None:
    """Keypoints with future stamps (or a pusher topic gone quiet) keep at most PENDING_HALVES
    waiting; the newest stay."""
    pending: dict[float, np.ndarray] = {}
    for k in range(1000):
        keep_pending(pending, 1e9 + k, np.zeros(2))
    assert len(pending) == PENDING_HALVES and min(pending) == 1e9 + 1000 - PENDING_HALVES


def test_replan_latency_counts_only_a_plan_that_knows_the_zone() -> None:
    """`replan_latency_ms`: NaN from a zone change until a plan planned with it is installed;
    a plan made before it, installed meanwhile, does not count."""
    reaction = ReactionTimes()
    reaction.zone_changed()
    assert reaction.status()["replan_latency_ms"] == "nan"
    reaction.plan_installed(knows_zones=False)
    assert reaction.status()["replan_latency_ms"] == "nan"
    time.sleep(0.002)
    reaction.plan_installed(knows_zones=True)
    first = float(reaction.status()["replan_latency_ms"])
    assert first >= 2.0
    reaction.plan_installed(knows_zones=True)  # a later plan: the zone's answer stays
    assert float(reaction.status()["replan_latency_ms"]) == first
