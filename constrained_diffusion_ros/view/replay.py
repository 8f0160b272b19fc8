"""A recorded trial as the live view showed it: the view's scene at every control step of a bag,
written to an MCAP file the Foxglove app opens with the same layout (the same channels, the
same frames, top down), so a bag is watched as the robot was."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import foxglove
from foxglove.channels import FrameTransformChannel, SceneUpdateChannel

from constrained_diffusion_ros.view.layout import view_channels
from constrained_diffusion_ros.view.scene import (
    PARTS,
    SceneState,
    scene_update,
    take_policy_status,
    view_transform,
)
from msg_schemas import TOPICS


def write_scene(messages: Iterable[tuple[int, str, object]], output: Path,
                inflating: set[str], pusher_radius: float) -> int:
    """The scene after each pusher message of `messages` ((record time ns, topic, message), in
    recording order, as `recording.bags.read_timed_messages` gives them) into `output`, logged
    at the record time; `inflating`: the configurations that grow the zones. Returns the frames
    written."""
    messages = list(messages)
    pusher_topics = [topic for _, topic, _ in messages if topic.rsplit("/", 1)[-1] == "pusher"]
    namespace = pusher_topics[0].rsplit("/", 1)[0] if pusher_topics else ""
    parts = {TOPICS[topic].resolved(namespace): (part, convert)
             for part, (topic, convert) in PARTS.items()}
    policy = f"{namespace}/policy_node"
    state = SceneState(pusher_radius=pusher_radius)
    context = foxglove.Context()
    channels = view_channels(namespace)
    scene = SceneUpdateChannel(channels["scene"], context=context)
    transforms = FrameTransformChannel(channels["transforms"], context=context)
    frames = 0
    with foxglove.open_mcap(output, allow_overwrite=True, context=context):
        for time_ns, topic, message in messages:
            if topic in parts:
                part, convert = parts[topic]
                setattr(state, part, convert(message))
                if part == "pusher":
                    transforms.log(view_transform(time_ns), log_time=time_ns)
                    scene.log(scene_update(state, time_ns), log_time=time_ns)
                    frames += 1
            elif topic == TOPICS["diagnostics"].name:
                for status in message.status:
                    if status.name == policy:
                        take_policy_status(state, status.message,
                                           {kv.key: kv.value for kv in status.values},
                                           inflating)
    return frames
