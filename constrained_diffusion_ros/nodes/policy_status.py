"""The policy node's status on `/diagnostics`: its counters as key-values, and a level from their
rise since the last report (ERROR for a setpoint inside a zone, no sound setpoint, a plug-in zone
check that failed in use or planning that failed; WARN for refused input or planning that missed
its deadline)."""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.duration import Duration
from rclpy.node import Node
from std_msgs.msg import Header

from msg_schemas import TOPICS, qos_profile

# The chunk loop's word on a plug-in zone check (`loop_status`), in every mode.
ZONE_CHECK_KEYS = ("zone_check_errors", "zone_check_failed", "zone_check_error", "cornered",
                   "cornered_steps")
# Their rise since the last report sets the diagnostic level.
HEALTH_COUNTERS = ("violations", "unsound_setpoints", "zones_refused", "masks_refused",
                   "observations_refused", "late_steps", "planning_errors", "ticks_withheld",
                   "configuration_changes", "changes_refused", "zone_check_errors",
                   "runs_restarted", "cornered_steps", "zone_speed_exceeded",
                   "observations_late")


class StatusReporter:
    """Publishes the node's counters on `/diagnostics` with the level they call for."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.publisher = node.create_publisher(DiagnosticArray, TOPICS["diagnostics"].name,
                                               qos_profile(TOPICS["diagnostics"], "publisher"))
        self._counts: dict[str, int] = {}

    def publish(self, values: dict[str, object]) -> None:
        values = {**self._zone_check(), **values}
        self._send(*self.health(values), values)

    def publish_failure(self, reason: str, wait_s: float = 0.5) -> None:
        """ERROR, `reason`: the node stopped commanding the robot (its zone handling died).
        Waits up to `wait_s` for subscribers to have it: the process ends right after."""
        self._send(DiagnosticStatus.ERROR, reason, {})
        self.publisher.wait_for_all_acked(Duration(seconds=wait_s))

    def _send(self, level: bytes, message: str, values: dict[str, object]) -> None:
        status = DiagnosticStatus(level=level, name=self.node.get_fully_qualified_name(),
                                  message=message, hardware_id="pusht")
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        stamp = self.node.get_clock().now().to_msg()
        self.publisher.publish(DiagnosticArray(header=Header(stamp=stamp), status=[status]))

    def _zone_check(self) -> dict[str, object]:
        """The chunk loop's zone-check keys: a node that leaves the loop's status out of its
        values (lockstep) still says when a plug-in check fails and stops the pusher."""
        loop = getattr(self.node, "loop", None)
        if loop is None:  # (the view node reports with this class too, without torch)
            return {}
        from constrained_diffusion_ros.runtime.live_loop import loop_status

        status = loop_status(loop)
        return {key: status[key] for key in ZONE_CHECK_KEYS if key in status}

    def health(self, values: dict) -> tuple[bytes, str]:
        """The diagnostic level since the last report: ERROR if a setpoint sent was inside a
        zone, WARN if zones were refused or (realtime) steps passed with no plan in time."""
        counts = {key: int(values.get(key, 0)) for key in HEALTH_COUNTERS}
        since = {key: counts[key] - self._counts.get(key, 0) for key in counts}
        self._counts = counts
        if since["unsound_setpoints"]:
            return DiagnosticStatus.ERROR, (
                f"no sound setpoint {since['unsound_setpoints']} time(s) (zones leave no free "
                f"space, or a non-finite action): the pusher held")
        if since["violations"]:
            return DiagnosticStatus.ERROR, f"{since['violations']} setpoint(s) inside a zone"
        if since["zone_check_errors"] or values.get("zone_check_failed"):
            return DiagnosticStatus.ERROR, (
                f"zone check failed ({values['zone_check_errors']} fault(s)), the pusher "
                f"stopped: {values['zone_check_error']}")
        if since["cornered_steps"] or values.get("cornered") in (True, "True"):
            return DiagnosticStatus.ERROR, (
                f"cornered: a moving zone left no free space to retreat into "
                f"({since['cornered_steps']} step(s) since the last report); the separation "
                f"kept as large as it can be, the guarantee does not hold")
        if since["planning_errors"] or values.get("planning_failed"):
            # ERROR until a plan arrives again: a planner that died stays news until it plans
            return DiagnosticStatus.ERROR, (
                f"planning failed ({values['planning_errors']} fault(s), "
                f"{values['planning_restarts']} restart(s), no plan since): "
                f"{values['planning_error']}")
        problems = []
        if since["zones_refused"]:
            problems.append(f"{since['zones_refused']} zone message(s) refused")
        if since["masks_refused"]:
            problems.append(f"{since['masks_refused']} keep-out mask(s) refused")
        if since["observations_refused"]:
            problems.append(f"{since['observations_refused']} observation(s) refused (not "
                            f"finite, or a pusher that cannot be the robot's)")
        if since["observations_late"]:
            problems.append(f"{since['observations_late']} observation(s) answered more than a "
                            f"control period after they were published (the executor was held): "
                            f"the shield's guarantee assumes a state at most a period old")
        if since["ticks_withheld"]:
            problems.append(f"{since['ticks_withheld']} tick(s) withheld: the executor that "
                            f"answers zones had stalled")
        if since["changes_refused"]:
            problems.append(f"{since['changes_refused']} run-time parameter change(s) refused "
                            f"(they would weaken the filter)")
        if since["configuration_changes"]:
            problems.append(f"configuration changed at run time, now "
                            f"{values.get('configuration')!r} (guarantee "
                            f"{values.get('guarantee')})")
        if values.get("zones_over_speed_bound"):
            problems.append(f"zone(s) {values['zones_over_speed_bound']} move faster than "
                            f"zone_speed_bound: the separation guarantee does not hold for "
                            f"them")
        if since["zone_speed_exceeded"]:
            problems.append(f"{since['zone_speed_exceeded']} zone update(s) showed a zone "
                            f"faster than it was assumed to move: the separation guarantee did "
                            f"not hold for that update")
        if since["runs_restarted"]:
            problems.append(f"{since['runs_restarted']} new run(s): an observation stamped no "
                            f"later than the last (a reset, or a participant sending old "
                            f"stamps)")
        if since["late_steps"]:
            problems.append(f"planning missed its deadline ({since['late_steps']} step(s) "
                            f"with no waypoint)")
        if problems:
            return DiagnosticStatus.WARN, "; ".join(problems)
        lifecycle = values.get("lifecycle", "active")
        if lifecycle != "active":  # a managed node's own choice: said, not a fault
            return DiagnosticStatus.OK, f"{lifecycle}: sends no setpoints"
        return DiagnosticStatus.OK, "running"


class ReactionTimes:
    """How fast the node answered its last zone change: the safe setpoint sent (from the zone
    message's arrival) and the first plan installed that was planned with it (NaN until one
    is)."""

    def __init__(self) -> None:
        self.zone_changed_at: float | None = None
        self.replan_latency_ms = self.zone_to_setpoint_ms = float("nan")

    def zone_changed(self) -> None:
        self.zone_changed_at = time.monotonic()
        self.replan_latency_ms = float("nan")

    def safe_setpoint_sent(self, received: float, sent: float | None) -> None:
        """The safe setpoint for a zone message that came at `received` went out at `sent`
        (time.monotonic(); None: none sent)."""
        if sent is not None:
            self.zone_to_setpoint_ms = 1000 * (sent - received)

    def plan_installed(self, knows_zones: bool) -> None:
        """A plan was installed; `knows_zones`: planned with the zones in force."""
        if self.zone_changed_at is not None and knows_zones:
            self.replan_latency_ms = 1000 * (time.monotonic() - self.zone_changed_at)
            self.zone_changed_at = None

    def status(self) -> dict[str, object]:
        return {"replan_latency_ms": f"{self.replan_latency_ms:.1f}",
                "zone_to_setpoint_ms": f"{self.zone_to_setpoint_ms:.1f}"}
