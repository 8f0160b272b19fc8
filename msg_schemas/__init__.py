"""The ROS interface: every topic and service (`contract`), the message <-> array and
stamp <-> control-step conversions (`conversions`); how a node runs is `node_support`'s."""

from msg_schemas.contract import (
    FRAME_ID,
    NAMESPACE,
    OPTIONAL_NODES,
    SERVICES,
    TOPICS,
    Endpoint,
    qos_profile,
)

__all__ = ["FRAME_ID", "NAMESPACE", "OPTIONAL_NODES", "SERVICES", "TOPICS", "Endpoint",
           "qos_profile"]
