"""The Foxglove app layout shipped with the view (config/foxglove_layout.json): the scene top
down in a 3D panel, a Publish panel that draws a zone, and the view's status. Generated here
from the channel names the view serves, so the file cannot name a channel that is not served:
`python -m constrained_diffusion_ros.view.layout > config/foxglove_layout.json`."""

from __future__ import annotations

import json

from constrained_diffusion_ros.view.scene import VIEW_FRAME
from constrained_diffusion_ros.view.zone_requests import (
    ZONE_REQUEST_EXAMPLE,
    ZONE_REQUEST_SCHEMA_NAME,
)
from msg_schemas import NAMESPACE

VIEW_HEIGHT_PX = 600.0  # the 512 px workspace and the status lines above it


def view_channels(namespace: str = NAMESPACE) -> dict[str, str]:
    """What the view serves (and takes, `zone_requests`), by role."""
    prefix = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return {role: f"{prefix}/view/{role}"
            for role in ("scene", "transforms", "status", "zone_requests")}


def layout(namespace: str = NAMESPACE) -> dict:
    channels = view_channels(namespace)
    three_d = {
        "followTf": VIEW_FRAME, "followMode": "follow-none",
        "cameraState": {"perspective": False, "distance": VIEW_HEIGHT_PX, "phi": 0.0,
                        "thetaOffset": 0.0, "target": [0, 0, 0], "targetOffset": [0, 20, 0],
                        "targetOrientation": [0, 0, 0, 1], "fovy": 45, "near": 0.5,
                        "far": 5000},
        "scene": {}, "transforms": {}, "layers": {}, "imageMode": {},
        "topics": {channels["scene"]: {"visible": True},
                   channels["transforms"]: {"visible": True}},
    }
    publish = {"topicName": channels["zone_requests"], "datatype": ZONE_REQUEST_SCHEMA_NAME,
               "buttonText": "Publish zone", "advancedView": True,
               "value": json.dumps(ZONE_REQUEST_EXAMPLE)}
    status = {"topicPath": channels["status"], "diffEnabled": False, "diffMethod": "custom",
              "diffTopicPath": "", "showFullMessageForDiff": False}
    return {
        "configById": {"3D!scene": three_d, "Publish!zone": publish,
                       "RawMessages!status": status},
        "globalVariables": {}, "userNodes": {}, "playbackConfig": {"speed": 1.0},
        "layout": {"direction": "row", "splitPercentage": 70, "first": "3D!scene",
                   "second": {"direction": "column", "splitPercentage": 45,
                              "first": "Publish!zone", "second": "RawMessages!status"}},
    }


if __name__ == "__main__":
    print(json.dumps(layout(), indent=2))
