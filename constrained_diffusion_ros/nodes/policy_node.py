"""policy_node: the constrained diffusion policy as a ROS 2 node.

Two modes, as the simulator's. `lockstep` (default): every observation (keypoints + pusher with
the same stamp) is answered with one setpoint, planned in the callback: a trial equals the
in-process evaluation bit for bit. `realtime`: a control clock thread publishes one setpoint per
tick (`rate_hz`) while a planning process plans the next chunk; a zone that arrives gets a safe
setpoint before the next tick. Both run the evaluation's `ChunkLoop`. The node is wiring:
observations come in through an `ObservationInput`, zones through a `ZoneIngest` (each owns its
subscriptions, as tf2's listener does); `ZoneClearing` serves the clear service and expiry,
`ZoneMarkers` shows the zones, `/diagnostics` go out through a `StatusReporter`.

It fails safe: should its executor die (the thread that answers zones), `fail_safe` stops every
setpoint, says ERROR and the process exits non-zero (`spin_node`); while the executor stalls,
the clock withholds setpoints (`executor_watchdog_s`). A run-time change of configuration to one
that promises less is refused unless the node was started with `allow_weaker_configuration`.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

from constrained_diffusion_ros.nodes.policy_parameters import PARAMETERS
from node_support.parameters import answered_help

if TYPE_CHECKING:
    from constrained_diffusion_ros.nodes.policy_node_impl import PolicyNode


def main(args: list[str] | None = None) -> int:
    if answered_help(args, "policy_node", __doc__, PARAMETERS):
        return 0  # before torch, rclpy and the planner are imported: --help at once
    from constrained_diffusion_ros.nodes.policy_node_impl import PolicyNode
    from node_support.spin import spin_node

    return spin_node(PolicyNode, "policy_node", args, PARAMETERS, __doc__)


def __getattr__(name: str) -> type[PolicyNode]:
    """`PolicyNode` is still found here, imported when first asked for."""
    if name == "PolicyNode":
        from constrained_diffusion_ros.nodes.policy_node_impl import PolicyNode

        return PolicyNode
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


if __name__ == "__main__":
    sys.exit(main())
