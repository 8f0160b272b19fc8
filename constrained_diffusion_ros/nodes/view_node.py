"""view_node: the robot live in the Foxglove app, and zones drawn from there.

Serves the scene over the Foxglove WebSocket protocol (foxglove-sdk): the walls and the goal T,
the T block, the pusher and its setpoint, the planned chunk, the zones in force with their ids
(keep-out masks included) and, where the policy's configuration inflates them, the grown
outline the planner keeps the pusher's centre out of; the score and the filter's state (held,
shielded, cornered, no free space). In the app: "Open connection", Foxglove WebSocket,
ws://localhost:8765, then import the layout config/foxglove_layout.json.

Zones from the app: a JSON message `{"id": 7, "polygon": [[x, y], ...]}` (px; [] removes the
id) on the client channel `<namespace>/view/zone_requests` becomes the same
PolygonInstanceStamped on `zones` that every other publisher sends. A request whose polygon the
policy node would refuse (its checks and vertex cap) is refused here; what the policy refuses
itself (its cap on zones in force) comes back on its /diagnostics. Either reason is shown in the
view and sent to the app as a warning; the view's refusals are counted on /diagnostics.

The view is a process of its own, off the control path: it draws at most `rate_hz` frames a
second from the latest messages, and a client that cannot keep up loses frames (a bounded
backlog per client), never delays anything.

Examples:
  view_node
  view_node --ros-args -p host:=0.0.0.0 -p port:=8766
"""

from __future__ import annotations

import sys
from functools import partial

from constrained_diffusion_ros.nodes.policy_parameters import DEFAULT_MAX_VERTICES
from constrained_diffusion_ros.paths import config_dir
from node_support.parameters import Param, answered_help

PARAMETERS = (
    Param("host", "127.0.0.1", "interface the WebSocket server binds (0.0.0.0: every one)",
          read_only=True),
    Param("port", 8765, "WebSocket port; 0: any free one (logged)", read_only=True, low=0,
          high=65535),
    Param("rate_hz", 20.0, "frames a second at most (the scene as the latest messages say)",
          read_only=True, low=0.5, high=100.0),
    Param("backlog", 32, "messages queued per client at most; a slow client loses the oldest",
          read_only=True, low=1, high=10_000),
    Param("policy_node", "policy_node", "the policy node whose state and configuration are "
          "shown (a name in this namespace)", read_only=True),
    Param("configurations_file", str(config_dir() / "configurations.yaml"),
          "constraint configurations YAML (which ones inflate the zones)", read_only=True),
    Param("max_vertices", DEFAULT_MAX_VERTICES, "vertices a zone request may have at most, as "
          "the policy node's parameter", read_only=True, low=3, high=100_000),
)


def main(args: list[str] | None = None) -> int:
    if answered_help(args, "view_node", __doc__, PARAMETERS):
        return 0  # before rclpy, torch and foxglove are imported: --help at once
    from constrained_diffusion_ros.nodes.view_node_impl import ViewNode
    from node_support.spin import spin_node

    return spin_node(partial(ViewNode, PARAMETERS), "view_node", args, PARAMETERS, __doc__)


if __name__ == "__main__":
    sys.exit(main())
