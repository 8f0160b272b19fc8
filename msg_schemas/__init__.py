"""The topic contract: every topic and service of the package, in one place."""

from msg_schemas.contract import FRAME_ID, SERVICES, TOPICS, Endpoint, qos_profile

__all__ = ["FRAME_ID", "SERVICES", "TOPICS", "Endpoint", "qos_profile"]
