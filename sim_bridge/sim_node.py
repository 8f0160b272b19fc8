"""ROS 2 node around the ROS-free PushT simulator: observations out, setpoints in.

Two modes. `lockstep` (default): a setpoint stamped with the current observation's stamp is
exactly one control step, so a trial is deterministic however slow the policy is; setpoints
with any other stamp (duplicates of answers already used) are dropped. `realtime`: a timer
steps at `rate_hz` with the latest setpoint, as a real robot would, holding the last one; a
setpoint stamped later than the newest observation of this run is dropped (`stale_setpoint`).

Every observation is stamped with simulated time (control step * 0.1 s), which also goes out on
`/clock` (nodes started with `use_sim_time:=true` run on it), and published as four messages
with the same stamp: block pose, score, keypoints, then the pusher, last, because the
policy node acts on it. A reset (service `reset`, to the `seed` parameter) returns the
stamp to 0. With `autostart` false the sim publishes nothing and ignores setpoints until the
first reset, so a trial can wait until every node is up before the scene starts.

In lockstep the sim re-sends the current observation (same stamp) every 0.5 s while no setpoint
answers it, so the first one is not lost to subscribers that are still being discovered;
consumers must drop observations whose stamp they have already seen.

Run: `sim_node --ros-args -p seed:=100001 -p mode:=realtime`.
"""

from __future__ import annotations

import sys
from functools import partial

from node_support.parameters import Param, answered_help

MODES = ("lockstep", "realtime")

PARAMETERS = (
    Param("seed", 100000, "scene of the reference environment; the reset service re-reads it",
          low=0),
    Param("mode", "lockstep", "lockstep: one control step per setpoint (deterministic); "
          "realtime: steps at rate_hz with the latest setpoint", read_only=True, choices=MODES),
    Param("rate_hz", 10.0, "realtime: control steps per second", read_only=True, low=0.1,
          high=1000.0),
    Param("max_steps", 0, "stop stepping after this many control steps; 0: unlimited",
          read_only=True, low=0),
    Param("autostart", True, "false: publish nothing and ignore setpoints until the reset "
          "service is called", read_only=True),
)


def main(args: list[str] | None = None) -> int:
    if answered_help(args, "sim_node", __doc__, PARAMETERS):
        return 0  # before rclpy is imported: --help at once
    from node_support.spin import spin_node
    from sim_bridge.sim_node_impl import SimNode

    return spin_node(partial(SimNode, PARAMETERS), "sim_node", args, PARAMETERS, __doc__)


if __name__ == "__main__":
    sys.exit(main())
