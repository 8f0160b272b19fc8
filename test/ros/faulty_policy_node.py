"""The policy node with a fault injected into its executor, for the fail-safe tests
(`test_fail_safe.py`); `FAULT` in the environment says which, at the first zone message of id
`FAULT_ZONE`:
- "raise": its callback raises, as rclpy's take raised under a flood of 300k-vertex zones
  (`RuntimeError: Unable to convert call argument`), and the executor dies;
- "stall": its callback blocks, and the executor answers nothing more.

Not part of the package: the fault is injected from outside, as any other would come."""

from __future__ import annotations

import os
import sys
import time

from geometry_msgs.msg import PolygonInstanceStamped
from rclpy.serialization import deserialize_message

from constrained_diffusion_ros.nodes import policy_node, zone_ingest


def faulty(fault: str, zone_id: int):
    """ZoneIngest._on_zone with `fault` at a message of `zone_id`."""
    on_zone = zone_ingest.ZoneIngest._on_zone

    def on_faulty_zone(self, data: bytes, info: dict) -> None:
        if deserialize_message(data, PolygonInstanceStamped).polygon.id == zone_id:
            if fault == "raise":
                raise RuntimeError("Unable to convert call argument")
            time.sleep(3600)
        on_zone(self, data, info)
    return on_faulty_zone


if __name__ == "__main__":
    zone_ingest.ZoneIngest._on_zone = faulty(os.environ["FAULT"],
                                             int(os.environ["FAULT_ZONE"]))
    sys.exit(policy_node.main())
