"""sim_node over real DDS: lockstep stepping, refusal of bad setpoints, resets, autostart."""

from __future__ import annotations

import math

import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy.parameter import Parameter
from ros_helpers import SEED, stamp_ns, step_ns
from std_srvs.srv import Trigger

from msg_schemas import FRAME_ID, TOPICS, qos_profile
from sim_bridge.physics import PushTSim
from sim_bridge.scene import seeded_state


def test_sim_lockstep_one_observation_per_setpoint(ros, sim):
    first = sim.latest()
    expected = PushTSim()
    expected.reset(SEED)
    assert stamp_ns(first.header.stamp) == 0 and first.header.frame_id == FRAME_ID
    assert (first.point.x, first.point.y) == tuple(seeded_state(SEED)[:2])
    keypoints = sim.keypoints[-1]
    assert stamp_ns(keypoints.header.stamp) == 0
    assert np.allclose([(p.x, p.y) for p in keypoints.polygon.points], expected.keypoints(),
                       atol=1e-3)  # Point32 is float32

    before = sim.stamps()
    targets = [(first.point.x + 30.0 * (i + 1), first.point.y - 20.0 * (i + 1)) for i in range(5)]
    for target in targets:  # each answers the observation in force, whose stamp it carries
        sim.send(*target)
        sim.wait_new_stamps(sim.stamps(), 1)
    sim.send(*targets[-1], stamp=first.header.stamp)  # a stale duplicate: dropped
    new = sim.stamps()[len(before):]
    ros.spin_for(0.3)
    assert sim.stamps()[len(before):] == new == [step_ns(k) for k in range(1, 6)]

    positions = {stamp_ns(m.header.stamp): (m.point.x, m.point.y) for m in sim.pushers}
    previous = np.array([first.point.x, first.point.y])
    for k, target in enumerate(targets, start=1):
        state = expected.step(target)
        now = np.array(positions[step_ns(k)])
        assert tuple(now) == tuple(state[:2])  # same simulator, bit for bit
        assert np.linalg.norm(now - target) < np.linalg.norm(previous - target)
        previous = now
    pose_stamps = {stamp_ns(m.header.stamp) for m in sim.poses}
    keypoint_stamps = {stamp_ns(m.header.stamp) for m in sim.keypoints}
    assert set(new) <= pose_stamps and set(new) <= keypoint_stamps
    assert all(0.0 <= m.data <= 1.0 for m in sim.scores)


def test_sim_refuses_malformed_setpoint_and_keeps_going(ros, sim):
    before = sim.stamps()
    sim.send(math.nan, 100.0)
    sim.send(float("inf"), 100.0)
    sim.send(1e9, 100.0)
    sim.send(200.0, 200.0)
    new = sim.wait_new_stamps(before, 1)
    ros.spin_for(0.3)
    assert len(sim.stamps()) == len(before) + 1
    assert new[0] == before[-1] + step_ns(1)
    assert sim.process.poll() is None
    log = sim.log.read_text()
    assert "not finite" in log and "outside" in log and "Traceback" not in log


def test_sim_reset_to_seed_parameter(ros, sim):
    seed = SEED + 7
    response = sim.reset(seed)
    assert response.success and str(seed) in response.message
    first = sim.pushers[0]
    assert stamp_ns(first.header.stamp) == 0
    assert (first.point.x, first.point.y) == tuple(seeded_state(seed)[:2])
    assert sim.stamps() == [0]

    future = sim.params.set_parameters([Parameter("seed", value=-1)])  # refused with a reason
    assert ros.spin_until(future.done, 10.0)
    refused = future.result().results[0]
    assert not refused.successful and "parameter seed must be in [0, inf]" in refused.reason
    assert sim.process.poll() is None
    assert sim.reset(SEED).success  # back to the scene the other tests expect


def test_sim_without_autostart_waits_for_reset(ros, processes):
    """A second sim, renamed and remapped so it does not meet the first one."""
    topics = ("/pusht/pusher", "/pusht/keypoints", "/pusht/block_pose", "/pusht/score",
              "/pusht/setpoint", "/pusht/reset")
    remap = {"__node": "sim_b", **{name: name.replace("/pusht/", "/b/") for name in topics}}
    _, log = processes.start("sim_b", "sim_node", remap=remap,
                             seed=SEED + 3, autostart=False)
    received: list[PointStamped] = []
    ros.node.create_subscription(PointStamped, "/b/pusher", received.append,
                                 qos_profile(TOPICS["pusher"]))
    client = ros.node.create_client(Trigger, "/b/reset")
    assert ros.spin_until(client.service_is_ready), log.read_text()
    ros.spin_for(0.8)  # longer than the lockstep re-send period: still nothing
    assert received == []
    future = client.call_async(Trigger.Request())
    assert ros.spin_until(future.done, 10.0) and future.result().success
    assert ros.spin_until(lambda: len(received) > 0, 10.0)
    assert stamp_ns(received[0].header.stamp) == 0
    assert (received[0].point.x, received[0].point.y) == tuple(seeded_state(SEED + 3)[:2])


def test_realtime_sim_after_a_reset_drops_setpoints_stamped_for_the_run_before(ros, processes):
    """Issue 41: after a reset the realtime sim stepped toward setpoints the policy's clock
    still sent for the run before (stamped for its steps 300-302), across a keep-out bar. Now
    a setpoint stamped later than the newest observation of the run is dropped and counted:
    the pusher is held where the new scene put it. A setpoint of the new run still moves it.
    A third sim, remapped so that it meets neither of the others."""
    topics = ("/pusht/pusher", "/pusht/keypoints", "/pusht/block_pose", "/pusht/score",
              "/pusht/setpoint", "/pusht/reset")
    remap = {"__node": "sim_c", **{name: name.replace("/pusht/", "/c/") for name in topics}}
    _, log = processes.start("sim_c", "sim_node", remap=remap, seed=SEED + 1, mode="realtime")
    pushers: list[PointStamped] = []
    ros.node.create_subscription(PointStamped, "/c/pusher", pushers.append,
                                 qos_profile(TOPICS["pusher"]))
    setpoints = ros.node.create_publisher(PointStamped, "/c/setpoint",
                                          qos_profile(TOPICS["setpoint"], "publisher"))
    client = ros.node.create_client(Trigger, "/c/reset")
    assert ros.spin_until(lambda: client.service_is_ready() and pushers
                          and setpoints.get_subscription_count() >= 1), log.read_text()

    def send(x: float, y: float, stamp) -> None:
        msg = PointStamped()
        msg.header.stamp, msg.header.frame_id = stamp, FRAME_ID
        msg.point.x, msg.point.y = x, y
        setpoints.publish(msg)

    corner = (480.0, 480.0)
    assert ros.spin_until(lambda: stamp_ns(pushers[-1].header.stamp) >= step_ns(1), 10.0)
    send(*corner, pushers[-1].header.stamp)  # the old run heads for the corner
    assert ros.spin_until(lambda: stamp_ns(pushers[-1].header.stamp) >= step_ns(20), 10.0)
    old = pushers[-1]
    assert (old.point.x, old.point.y) != tuple(seeded_state(SEED + 1)[:2])  # it moved
    future = client.call_async(Trigger.Request())
    assert ros.spin_until(future.done, 10.0) and future.result().success
    assert ros.spin_until(lambda: stamp_ns(pushers[-1].header.stamp) < stamp_ns(old.header.stamp))
    mark = next(i for i in range(len(pushers) - 1, -1, -1)
                if stamp_ns(pushers[i].header.stamp) == 0)
    for _ in range(3):  # the old run's setpoint, as a clock that has not heard of the reset
        send(*corner, old.header.stamp)
        ros.spin_for(0.05)
    assert ros.spin_until(lambda: stamp_ns(pushers[-1].header.stamp) >= step_ns(5), 10.0)
    start = tuple(seeded_state(SEED + 1)[:2])
    new_run = pushers[mark:]
    assert [(m.point.x, m.point.y) for m in new_run] == [start] * len(new_run)
    assert ros.spin_until(lambda: "dropped 1 setpoint(s) stamped later" in log.read_text(),
                          10.0), log.read_text()  # then throttled
    send(*corner, pushers[-1].header.stamp)  # this run's: taken
    assert ros.spin_until(lambda: (pushers[-1].point.x, pushers[-1].point.y) != start, 10.0)


# --------------------------------------------------------------------------- zone_publisher


