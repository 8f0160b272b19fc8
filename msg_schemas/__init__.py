"""The ROS interface: every topic and service (`contract`), the message <-> array and
stamp <-> control-step conversions (`conversions`), and how a node runs (`spin`)."""

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
