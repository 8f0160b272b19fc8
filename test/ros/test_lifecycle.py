"""The policy node as a managed (lifecycle) node, driven over DDS through its transitions as
nav2's lifecycle manager drives its nodes: unconfigured it has no setpoint publisher; inactive it
answers nothing; active it sends; deactivated it sends nothing again (the last safe setpoint
held); cleanup takes its topics away; shutdown finalizes it. /diagnostics names the state."""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, PolygonStamped
from lifecycle_msgs.srv import ChangeState, GetState
from ros_helpers import observation_messages

from msg_schemas import SERVICES, TOPICS

PUSHER = (200.0, 300.0)


def test_the_policy_node_goes_through_its_lifecycle_transitions_over_dds(
        ros, processes, tiny_model, configurations_file) -> None:
    setpoints = ros.inbox("setpoint", PointStamped)
    statuses = ros.inbox("diagnostics", DiagnosticArray)
    keypoints_pub = ros.publisher("keypoints", PolygonStamped)
    pusher_pub = ros.publisher("pusher", PointStamped)
    change = ros.node.create_client(ChangeState, SERVICES["change_state"].name)
    get = ros.node.create_client(
        GetState, SERVICES["change_state"].name.replace("change_state", "get_state"))
    process, log = processes.start(
        "policy_node", model=tiny_model, configurations_file=configurations_file,
        configuration="fast_safe", mode="realtime", autostart=False)
    step = 0

    def observe(count: int) -> None:
        """`count` observations at the control rate (the pusher standing still)."""
        nonlocal step
        for _ in range(count):
            keypoints, pusher = observation_messages(step, PUSHER)
            keypoints_pub.publish(keypoints)
            pusher_pub.publish(pusher)
            step += 1
            ros.spin_for(0.1)

    def state() -> str:
        answer = get.call_async(GetState.Request())
        assert ros.spin_until(answer.done, 10.0), log.read_text()
        return answer.result().current_state.label

    def transition(label: str) -> None:
        request = ChangeState.Request()
        request.transition.label = label
        answer = change.call_async(request)
        assert ros.spin_until(answer.done, 60.0), log.read_text()
        assert answer.result().success, f"{label} refused:\n{log.read_text()}"

    def said(lifecycle: str) -> bool:
        """The newest report names the state."""
        return bool(statuses) and any(kv.key == "lifecycle" and kv.value == lifecycle
                                      for kv in statuses[-1].status[0].values)

    assert ros.spin_until(lambda: change.service_is_ready() and get.service_is_ready(), 30.0), \
        log.read_text()
    assert state() == "unconfigured"
    assert ros.node.count_publishers(TOPICS["setpoint"].name) == 0  # nothing built yet

    transition("configure")
    assert state() == "inactive"
    assert ros.spin_until(lambda: ros.node.count_publishers(TOPICS["setpoint"].name) >= 1
                          and pusher_pub.get_subscription_count() >= 1
                          and keypoints_pub.get_subscription_count() >= 1, 30.0)
    assert ros.spin_until(lambda: said("inactive"), 10.0)
    observe(15)  # a plan is made meanwhile, but nothing is sent
    assert setpoints == []

    transition("activate")
    observe(10)
    assert ros.spin_until(lambda: len(setpoints) >= 5, 10.0), log.read_text()
    assert ros.spin_until(lambda: said("active"), 10.0)

    transition("deactivate")
    ros.spin_for(0.3)  # what was on its way before the answer
    sent = len(setpoints)
    observe(10)
    assert len(setpoints) == sent, "setpoints sent while inactive"
    transition("activate")
    observe(5)
    assert ros.spin_until(lambda: len(setpoints) > sent, 10.0)  # the held one, and on

    transition("deactivate")
    transition("cleanup")  # the planning process stopped, topics gone
    assert state() == "unconfigured"
    assert ros.spin_until(lambda: ros.node.count_publishers(TOPICS["setpoint"].name) == 0
                          and pusher_pub.get_subscription_count() == 0, 10.0)
    assert ros.spin_until(lambda: said("unconfigured"), 10.0)

    transition("configure")  # built again from nothing
    assert state() == "inactive"
    transition("shutdown")
    assert state() == "finalized"
    assert process.poll() is None and "Traceback" not in log.read_text()
