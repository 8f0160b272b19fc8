"""The live view's ROS-free parts: the scene it draws, the zone requests it takes from the app,
and a recording replayed as the view showed it."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import shapely
from foxglove.messages import SceneUpdate
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from constrained_diffusion_ros.view.replay import write_scene
from constrained_diffusion_ros.view.scene import SceneState, scene_update, take_policy_status
from constrained_diffusion_ros.view.zone_requests import (
    MAX_PENDING_ZONES,
    ZoneRequests,
    parse_zone_request,
)

pytestmark = pytest.mark.unit
WORKSPACE = (0.0, 0.0, 512.0, 512.0)
SQUARE = np.array([[100.0, 100.0], [160.0, 100.0], [160.0, 160.0], [100.0, 160.0]])


def scene_class():
    schema = SceneUpdate.get_schema()
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))


def decoded(update) -> dict:
    scene = scene_class()()
    scene.ParseFromString(update.encode())
    return {entity.id: entity for entity in scene.entities}


def test_the_scene_draws_every_part_in_the_workspace_frame() -> None:
    state = SceneState(pusher=np.array([200.0, 300.0]), setpoint=np.array([210.0, 300.0]),
                       block_pose=np.array([256.0, 256.0, 0.5]), plan=np.ones((15, 2)),
                       zones={"1": SQUARE, "keepout/0": SQUARE + 200}, score=0.5,
                       inflate_px=15.0, filter_state="shielded", refusal="zone 9: why")
    entities = decoded(scene_update(state, 10**9))
    assert {"workspace", "goal", "block", "plan", "pusher", "setpoint", "status", "zone/1",
            "zone/keepout/0"} == set(entities)
    assert all(e.frame_id == "workspace" for e in entities.values())
    pusher = entities["pusher"].cylinders[0]
    assert (pusher.pose.position.x, pusher.pose.position.y) == (200.0, 300.0)
    assert pusher.size.x == 2 * state.pusher_radius
    zone = entities["zone/1"]
    grown = [(p.x, p.y) for p in zone.lines[1].points]  # the inflated outline, 15 px out
    assert shapely.Polygon(SQUARE).exterior.distance(shapely.Polygon(grown).exterior) == \
        pytest.approx(15.0, abs=0.1)
    area = sum(shapely.Polygon([(p.x, p.y) for p in zone.triangles[0].points[k:k + 3]]).area
               for k in range(0, len(zone.triangles[0].points), 3))
    assert area == pytest.approx(60 * 60)
    texts = " | ".join(t.text for t in entities["status"].texts)
    assert "score 0.500" in texts and "shielded" in texts and "zone refused: zone 9: why" in texts
    assert len(decoded(scene_update(SceneState(inflate_px=0.0, zones={"1": SQUARE})))
               ["zone/1"].lines) == 1  # no grown outline where the configuration does not grow


@pytest.mark.parametrize(("payload", "reason"), [
    (b"garbage", "not JSON"),
    (b"[1, 2]", "expected"),
    (b'{"id": 1.5, "polygon": []}', "64-bit integer"),
    (b'{"id": 1, "polygon": [[0, 0], [10, 10], [10, 0], [0, 10]]}', "Self-intersection"),
    (b'{"id": 1, "polygon": [[900, 900], [950, 900], [950, 950]]}', "outside the workspace"),
    (b'{"id": 1, "polygon": [[0, 0], [1, "a"], [2, 0]]}', r"\[x, y\] numbers"),
    (json.dumps({"id": 1, "polygon": [[i, i * i] for i in range(70)]}).encode(), "vertices"),
    (b" " * 70_000, "bytes"),
])
def test_zone_requests_the_policy_would_refuse_are_refused_with_the_reason(payload, reason):
    with pytest.raises(ValueError, match=reason):
        parse_zone_request(payload, 64, WORKSPACE)


def test_a_zone_request_becomes_an_id_and_vertices_and_an_empty_one_a_removal() -> None:
    zone_id, vertices = parse_zone_request(
        json.dumps({"id": 7, "polygon": SQUARE.tolist()}).encode(), 64, WORKSPACE)
    assert zone_id == 7 and np.array_equal(vertices, SQUARE)
    assert parse_zone_request(b'{"id": 7, "polygon": []}', 64, WORKSPACE)[1].shape == (0, 2)


def test_the_policy_status_sets_the_filter_state_inflation_and_a_new_refusal() -> None:
    state = SceneState()
    values = {"configuration": "safe", "holding": "False", "shielded": "True",
              "no_free_space": "False", "zone_refusal": "zone 3: cap"}
    take_policy_status(state, "running", values, {"safe"})
    assert (state.filter_state, state.inflate_px, state.refusal) == ("shielded", 15.0,
                                                                     "zone 3: cap")
    state.refusal = "zone 4: the view's own, newer"
    take_policy_status(state, "running", values, set())  # the same refusal: not news
    assert state.refusal == "zone 4: the view's own, newer" and state.inflate_px == 0.0
    take_policy_status(state, "cornered: ...", {**values, "cornered": "True"}, set())
    assert state.filter_state == "cornered, shielded"


def test_a_recording_replays_as_one_scene_frame_per_pusher_message(tmp_path) -> None:
    def point(x, y):
        return SimpleNamespace(point=SimpleNamespace(x=x, y=y))

    marker = SimpleNamespace(action=0, ADD=0, text="5", id=5, points=[
        SimpleNamespace(x=x, y=y) for x, y in [*SQUARE, SQUARE[0]]])
    messages = [(1, "/robot/zone_markers", SimpleNamespace(markers=[marker])),
                (2, "/robot/pusher", point(10.0, 20.0)), (3, "/robot/setpoint", point(11, 21)),
                (4, "/robot/pusher", point(12.0, 22.0)), (5, "/elsewhere/pusher", point(0, 0))]
    assert write_scene(messages, tmp_path / "scene.mcap", set(), 15.0) == 2
    with (tmp_path / "scene.mcap").open("rb") as stream:
        frames = [(channel.topic, message.log_time, message.data)
                  for _, channel, message in make_reader(stream).iter_messages()]
    scenes = [(time, data) for topic, time, data in frames if topic == "/robot/view/scene"]
    assert [time for time, _ in scenes] == [2, 4]
    last = scene_class()()
    last.ParseFromString(scenes[-1][1])
    entities = {e.id: e for e in last.entities}
    assert entities["pusher"].cylinders[0].pose.position.x == 12.0 and "zone/5" in entities


def test_zone_requests_are_taken_on_their_channel_only_coalesced_per_id_and_capped() -> None:
    requests = ZoneRequests("/pusht/view/zone_requests", 64, WORKSPACE)
    requests.advertised(1, 3, "/pusht/view/zone_requests")
    requests.advertised(1, 4, "/elsewhere")

    def request(zone_id: int, vertices) -> bytes:
        return json.dumps({"id": zone_id, "polygon": np.asarray(vertices).tolist()}).encode()

    requests.received(1, 3, request(7, SQUARE))
    requests.received(1, 3, request(7, SQUARE + 10))  # the last per id is what goes out
    requests.received(1, 3, request(8, []))
    requests.received(1, 4, request(9, SQUARE))  # another topic
    requests.received(2, 3, request(9, SQUARE))  # a channel this client never advertised
    taken = requests.take()
    assert sorted(taken) == [7, 8] and np.array_equal(taken[7], SQUARE + 10)
    assert taken[8].shape == (0, 2) and requests.take() == {}
    assert requests.counts == {"zone_messages": 5, "zones_refused": 2}
    assert "takes zones on /pusht/view/zone_requests, not on None" in requests.reason
    for zone_id in range(MAX_PENDING_ZONES + 1):
        requests.received(1, 3, request(zone_id, SQUARE))
    requests.received(1, 3, request(0, SQUARE + 1))  # an id waiting already is replaced
    assert len(requests.take()) == MAX_PENDING_ZONES and requests.counts["zones_refused"] == 3
    assert "waiting already" in requests.reason
