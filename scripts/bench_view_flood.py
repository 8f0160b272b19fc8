"""A client floods the live view with zone requests: how many the view counts and refuses, and
how many zone messages reach ROS (coalesced per id, one batch per frame). Only view_node runs,
in a ROS domain of its own, with a free port; prints figures, asserts nothing.

Run: OMP_NUM_THREADS=1 python scripts/bench_view_flood.py [--requests 10000] [--ids 30]
"""

from __future__ import annotations

import argparse
import json
import socket
import struct
import sys
import tempfile
import time
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PolygonInstanceStamped
from websockets.sync.client import connect

from constrained_diffusion_ros.evaluation.launcher import Stack
from constrained_diffusion_ros.view.layout import view_channels
from constrained_diffusion_ros.view.zone_requests import ZONE_REQUEST_SCHEMA_NAME
from msg_schemas import TOPICS, qos_profile
from node_support.spin import spin_until

GARBAGE_EVERY = 7  # one request in this many is not JSON (7: every id gets good ones too)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--requests", type=int, default=10_000)
    parser.add_argument("--ids", type=int, default=30, help="distinct zone ids asked for")
    parser.add_argument("--settle", type=float, default=5.0, help="s to listen after it")
    args = parser.parse_args(argv)
    port = free_port()
    stack = Stack("bench_view_flood", Path(tempfile.mkdtemp(prefix="bench_view_flood_")))
    node, executor = stack.node, stack.executor
    published, statuses = [], []
    node.create_subscription(PolygonInstanceStamped, TOPICS["zones"].name,
                             lambda msg: published.append(msg.polygon.id),
                             qos_profile(TOPICS["zones"]))
    node.create_subscription(DiagnosticArray, TOPICS["diagnostics"].name,
                             lambda msg: statuses.extend(
                                 s for s in msg.status if s.name.endswith("/view_node")),
                             qos_profile(TOPICS["diagnostics"]))

    try:
        stack.start("view_node", port=port)
        spin_until(executor, lambda: node.count_publishers(TOPICS["zones"].name) >= 1, 30.0)
        ws = None
        for _ in range(100):
            try:
                ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"])
                break
            except OSError:
                time.sleep(0.2)
        if ws is None:
            print("bench_view_flood: the view never accepted a connection", file=sys.stderr)
            return 1
        with ws:
            ws.send(json.dumps({"op": "advertise", "channels": [
                {"id": 1, "topic": view_channels()["zone_requests"], "encoding": "json",
                 "schemaName": ZONE_REQUEST_SCHEMA_NAME}]}))
            time.sleep(0.5)  # the advertisement before the data
            started = time.monotonic()
            for k in range(args.requests):
                zone_id = k % args.ids
                polygon = [[100 + zone_id, 100], [150 + zone_id, 100], [150 + zone_id, 150]]
                payload = b"garbage" if k % GARBAGE_EVERY == 0 else \
                    json.dumps({"id": zone_id, "polygon": polygon}).encode()
                ws.send(bytes([1]) + struct.pack("<I", 1) + payload)
            sending = time.monotonic() - started
            spin_until(executor, lambda: False, args.settle)  # what comes meanwhile
        counts = {kv.key: kv.value for kv in statuses[-1].values} if statuses else {}
        print(f"sent {args.requests} zone requests over {args.ids} ids in {sending:.2f} s, "
              f"one in {GARBAGE_EVERY} not JSON")
        print(f"view counted {counts.get('zone_messages')}, refused {counts.get('zones_refused')}"
              f" ({counts.get('zone_refusal', '')})")
        print(f"zone messages on ROS: {len(published)}, {len(set(published))} distinct ids "
              f"(coalesced per id at each frame)")
        print(f"view process still running: {stack.failed() is None}")
    finally:
        stack.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
