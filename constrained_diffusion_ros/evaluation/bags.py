"""Trial bags read back with rosbags (no ROS needed): messages per topic, keyed by step."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from msg_schemas import TOPICS, Endpoint
from msg_schemas.conversions import step_of_stamp
from sim_bridge import CONTROL_HZ

TRIAL_TOPICS = {"pusher": "pusher", "block": "block_pose",
                "setpoint": "setpoint"}


def read_messages(bag: str | Path) -> dict[str, list]:
    """Every message of a bag, deserialised, in recording order, per topic."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    messages: dict[str, list] = defaultdict(list)
    with Reader(Path(bag)) as reader:
        for connection, _timestamp, raw in reader.messages():
            messages[connection.topic].append(
                typestore.deserialize_cdr(raw, connection.msgtype))
    return dict(messages)


def messages_of(messages: dict[str, list], endpoint: Endpoint) -> list:
    """The messages of a contract topic in a bag recorded in any namespace: the default one's
    if present, else the only topic of that name; a bag of several robots has to be asked by
    full name."""
    if endpoint.resolved() in messages:
        return messages[endpoint.resolved()]
    found = [topic for topic in messages if topic.rsplit("/", 1)[-1] == endpoint.name]
    if len(found) > 1:
        raise ValueError(f"the bag has {endpoint.name!r} in several namespaces: {found}")
    return messages[found[0]] if found else []


def read_trial(bag: str | Path) -> dict[str, dict[int, object]]:
    """Pusher, block pose and setpoint messages keyed by control step (from header stamps)."""
    messages = read_messages(bag)
    trial: dict[str, dict[int, object]] = {}
    for kind, topic in TRIAL_TOPICS.items():
        trial[kind] = {}
        for msg in messages_of(messages, TOPICS[topic]):
            trial[kind][step_of_stamp(msg.header.stamp, CONTROL_HZ)] = msg
    return trial
