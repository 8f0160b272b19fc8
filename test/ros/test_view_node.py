"""The live view end to end: the simulator, the realtime policy and the view node over DDS, and
a Foxglove WebSocket client written here against the published protocol (subprotocol
foxglove.sdk.v1: JSON ops, binary message data, protobuf schemas as FileDescriptorSets)."""

from __future__ import annotations

import base64
import json
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
import shapely
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from ros_helpers import SEED
from visualization_msgs.msg import MarkerArray
from websockets.sync.client import connect

from constrained_diffusion_ros.evaluation.launcher import NODES
from constrained_diffusion_ros.view.layout import layout, view_channels
from msg_schemas.conversions import zone_outlines_of
from sim_bridge.scene import AGENT_RADIUS

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01  # opcode of binary message data, both ways


class ViewClient:
    """A Foxglove WebSocket client: subscribes, decodes protobuf messages, publishes JSON."""

    def __init__(self, ws) -> None:
        self.ws = ws
        self.channels: dict[str, dict] = {}
        self.statuses: list[dict] = []
        self.decoders: dict[int, type] = {}  # subscription id -> message class
        self.latest: dict[int, tuple[float, object]] = {}  # subscription id -> (time, message)
        self._ids = iter(range(1, 1 << 30))

    def pump(self, seconds: float) -> None:
        """Take what the server sends for `seconds`."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                frame = self.ws.recv(timeout=left)
            except TimeoutError:
                return
            if isinstance(frame, str):
                op = json.loads(frame)
                if op["op"] == "advertise":
                    self.channels.update({c["topic"]: c for c in op["channels"]})
                elif op["op"] == "status":
                    self.statuses.append(op)
                continue
            assert frame[0] == MESSAGE_DATA
            subscription, _log_time = struct.unpack_from("<IQ", frame, 1)
            decoded = self.decoders[subscription]()
            decoded.ParseFromString(frame[13:])
            self.latest[subscription] = (time.monotonic(), decoded)

    def subscribe(self, topic: str) -> int:
        channel = self.channels[topic]
        assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf"
        files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
        pool = descriptor_pool.DescriptorPool()
        for file in files.file:
            pool.Add(file)
        subscription = next(self._ids)
        self.decoders[subscription] = message_factory.GetMessageClass(
            pool.FindMessageTypeByName(channel["schemaName"]))
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": subscription, "channelId": channel["id"]}]}))
        return subscription

    def advertise(self, topic: str, schema_name: str) -> int:
        channel = next(self._ids)
        self.ws.send(json.dumps({"op": "advertise", "channels": [
            {"id": channel, "topic": topic, "encoding": "json", "schemaName": schema_name}]}))
        return channel

    def publish(self, channel: int, payload: bytes) -> None:
        self.ws.send(bytes([MESSAGE_DATA]) + struct.pack("<I", channel) + payload)



def entity(scene, entity_id: str):
    return next((e for e in scene.entities if e.id == entity_id), None)


def status_values(statuses: list, name: str) -> dict[str, str] | None:
    for array in reversed(statuses):
        for status in array.status:
            if status.name == name:
                return {kv.key: kv.value for kv in status.values} | {"_level": status.level}
    return None


@pytest.fixture
def stack(ros, processes, tiny_model, configurations_file):
    """sim_node and a realtime policy node on the fast body-safe configuration, and the view
    on a free port (read from its /diagnostics); yields the client, connected."""
    statuses = ros.inbox("diagnostics", DiagnosticArray)
    processes.start("sim_node", seed=SEED, mode="realtime")
    processes.start("policy_node", model=tiny_model, configurations_file=configurations_file,
                    configuration="fast_safe", mode="realtime", planning_process=False)
    processes.start("view_node", port=0, configurations_file=configurations_file)
    assert ros.spin_until(lambda: status_values(statuses, "/pusht/view_node") is not None,
                          30.0), processes.logs()
    port = int(status_values(statuses, "/pusht/view_node")["port"])
    with connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None,
                 open_timeout=10) as ws:
        yield ViewClient(ws), statuses


def test_the_view_shows_the_pusher_and_takes_zones_the_policy_obeys_or_refuses(ros, stack):
    client, statuses = stack
    pushers = ros.inbox("pusher", PointStamped)
    setpoints: list[np.ndarray] = []
    ros.inbox("setpoint", PointStamped,
              lambda m: setpoints.append(np.array([m.point.x, m.point.y])))
    markers = ros.inbox("zone_markers", MarkerArray)
    client.pump(1.0)
    channels = view_channels()
    assert set(channels.values()) <= set(client.channels)  # zone_requests: advertised for the app
    scene = client.subscribe(channels["scene"])
    client.subscribe(channels["transforms"])

    # The pusher in the view is the pusher of /pusht/pusher within a tick (0.1 s).
    assert ros.spin_until(lambda: len(pushers) > 20, 30.0)
    matched = 0
    for _ in range(10):
        client.pump(0.15)
        ros.spin_until(lambda: False, 0.05)
        if scene not in client.latest or entity(client.latest[scene][1], "pusher") is None:
            continue
        shown = entity(client.latest[scene][1], "pusher").cylinders[0].pose.position
        recent = [(m.point.x, m.point.y) for m in pushers[-3:]]
        assert any(abs(shown.x - x) < 1e-6 and abs(shown.y - y) < 1e-6 for x, y in recent), \
            (shown, recent)
        matched += 1
    assert matched >= 5
    frame = client.latest[scene][1]
    assert {"workspace", "goal", "block", "pusher", "setpoint", "status"} <= \
        {e.id for e in frame.entities}

    # A zone from the app, on the setpoint in force: on the zones topic, in force in the
    # policy, obeyed (every setpoint after it outside the zone grown by the pusher's radius).
    requests = client.advertise(channels["zone_requests"], "constrained_diffusion_ros/ZoneRequest")
    assert ros.spin_until(lambda: bool(setpoints), 15.0)
    cx, cy = setpoints[-1].tolist()
    square = [[cx - 15, cy - 15], [cx + 15, cy - 15], [cx + 15, cy + 15], [cx - 15, cy + 15]]
    grown = shapely.Polygon(square).buffer(AGENT_RADIUS - 0.5)
    assert grown.contains(shapely.Point(*setpoints[-1]))  # the setpoint had to change
    client.publish(requests, json.dumps({"id": 42, "polygon": square}).encode())
    assert ros.spin_until(lambda: markers and "42" in zone_outlines_of(markers[-1]), 15.0)
    first = len(setpoints)
    assert ros.spin_until(lambda: len(setpoints) >= first + 20, 15.0)
    assert not any(grown.contains(shapely.Point(*p)) for p in setpoints[first:])
    client.pump(0.5)
    zone = entity(client.latest[scene][1], "zone/42")
    assert zone is not None and len(zone.lines) == 2  # its outline, and the grown one (inflate)

    # Malformed requests: refused with the reason, shown in the view and counted.
    client.publish(requests, b"not json at all")
    client.publish(requests, json.dumps({"id": 43, "polygon": [[10, 10], [90, 90], [90, 10],
                                                                [10, 90]]}).encode())
    assert ros.spin_until(lambda: int((status_values(statuses, "/pusht/view_node") or {})
                                      .get("zones_refused", 0)) >= 2, 10.0)
    client.pump(0.5)
    texts = [t.text for t in entity(client.latest[scene][1], "status").texts]
    assert any("zone refused: zone 43: invalid polygon, Self-intersection" in t for t in texts)
    assert any("zone refused" in s["message"] for s in client.statuses)
    assert "43" not in zone_outlines_of(markers[-1])

    # Removal from the app.
    client.publish(requests, json.dumps({"id": 42, "polygon": []}).encode())
    assert ros.spin_until(lambda: "42" not in zone_outlines_of(markers[-1]), 15.0)


def test_the_layout_parses_and_names_only_what_the_view_serves() -> None:
    from constrained_diffusion_ros.paths import config_dir
    shipped = json.loads((config_dir() / "foxglove_layout.json").read_text())
    assert shipped == layout()
    served = set(view_channels().values())
    config = shipped["configById"]
    named = {*config["3D!scene"]["topics"], config["Publish!zone"]["topicName"],
             config["RawMessages!status"]["topicPath"]}
    assert named <= served and len(named) == 4


def test_a_port_in_use_or_an_address_not_here_is_one_line_and_exit_code_2(processes) -> None:
    import socket

    def start(*parameters: str) -> tuple[int, list[str]]:
        arguments = [arg for parameter in parameters for arg in ("-p", parameter)]
        done = subprocess.run([sys.executable, "-m", NODES["view_node"], "--ros-args",
                               *arguments], capture_output=True, text=True, timeout=60,
                              env=processes.environment())
        return done.returncode, [line for line in (done.stdout + done.stderr).splitlines()
                                 if line.strip()]

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code, lines = start(f"port:={port}")
    assert code == 2 and len(lines) == 1, lines
    assert f"cannot serve the view on 127.0.0.1:{port}" in lines[0] and "in use" in lines[0]
    code, lines = start("host:=192.0.2.1", "port:=0")  # TEST-NET-1: no machine has it
    assert code == 2 and len(lines) == 1, lines
    assert "cannot serve the view on 192.0.2.1:0" in lines[0]
