"""zone_publisher: puts restricted zones on the zone topic, from a scenario or the command line.

Each zone is one `PolygonInstanceStamped` keyed by its id; an empty polygon removes that id. The
topic is latched (transient local), so a policy node that starts later still gets the zones; they
are also re-sent at `rate_hz` (0: publish once and rely on the latching).

A moving scenario is recomputed for the sim's current control step: with `follow_sim_time` the
step is read from the stamp of `pusher` (stamp * 10) and the zone is published whenever a
new sim step is seen, so a lockstep trial sees the same zone positions however fast it runs;
without it the step is the wall time since start * 10. A zone that homes on the pusher (a
scenario with `home_s`, such as hand_homing@100) heads for the pusher as `pusher` reports it.

Examples:
  zone_publisher --ros-args -p scenario:=center_0.2
  zone_publisher --ros-args -p polygon:="200,200;300,200;300,300" -p zone_id:=7
  zone_publisher --ros-args -p remove_id:=7
"""

from __future__ import annotations

import math
import sys
from functools import partial

from constrained_diffusion_ros.nodes.policy_parameters import MASK_CELLS
from node_support.parameters import Param, answered_help

# Cells a side of the keep-out mask at most: what the policy node takes (`MaskCaps.cells`); a
# resolution of 1e-9 px would ask for 10**23 cells. Over the 512 px workspace: cells at least
# 0.125 px wide. (Not the Param's low bound: 0 means polygons.)
MAX_KEEPOUT_CELLS = math.isqrt(MASK_CELLS)

PARAMETERS = (
    Param("scenario", "", "a scenario name from the scenarios file; empty: none"),
    Param("scenarios_file", "", "scenarios YAML; empty: the shipped config/scenarios.yaml"),
    Param("first_id", 1, "id of the scenario's first zone, then +1 each", low=0,
          high=2**31 - 1),
    Param("polygon", "", "an ad-hoc zone 'x1,y1;x2,y2;...' in workspace px; empty: none"),
    Param("zone_id", -1, "the ad-hoc zone's id; -1: the id after the scenario's zones", low=-1,
          high=2**31 - 1),
    Param("remove_id", -1, "0 or more: publish an empty polygon with this id (removes it)",
          low=-1, high=2**31 - 1),
    Param("rate_hz", 2.0, "re-publish rate; 0: publish once (the topic is latched)", low=0.0,
          high=1000.0),
    Param("keepout_resolution", 0.0, "above 0: publish the scenario's zones as a keep-out "
          "mask of cells this many px wide (keepout_mask, nav2's convention) instead of "
          f"polygons; at most {MAX_KEEPOUT_CELLS} cells a side", low=0.0, high=512.0),
    Param("follow_sim_time", True, "moving zones follow the sim's step (from the pusher "
          "stamps); false: wall time"),
)


def main(args: list[str] | None = None) -> int:
    if answered_help(args, "zone_publisher", __doc__, PARAMETERS):
        return 0  # before rclpy, torch and shapely are imported: --help at once
    import yaml

    from constrained_diffusion_ros.nodes.zone_publisher_impl import ZonePublisher
    from node_support.spin import spin_node

    return spin_node(partial(ZonePublisher, PARAMETERS), "zone_publisher", args, PARAMETERS,
                     __doc__, startup_errors=(OSError, yaml.YAMLError))


if __name__ == "__main__":
    sys.exit(main())
