"""Messages whose size is checked before they are read.

rclpy turns a message into Python objects before any callback sees it: a `Point32` object per
vertex, holding the interpreter lock all along (seconds for a million vertices). A node that
takes messages from any participant on the network (zones, keep-out masks, observations)
subscribes to their serialized bytes instead (`raw=True`), refuses those longer than the
largest message it would accept, and deserializes only the rest. Refusing costs the length of
a bytes object.
"""

from __future__ import annotations

from geometry_msgs.msg import Point32, PolygonInstanceStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.serialization import deserialize_message, serialize_message

from msg_schemas.contract import FRAME_ID

FRAME_ID_SLACK = 64  # bytes of frame id a message may carry beyond FRAME_ID before it is too big


def largest(message) -> int:
    """Bytes of `message` serialized with a frame id longer than FRAME_ID: the largest message
    of its shape worth reading (one of another frame is refused in words, once read)."""
    message.header.frame_id = "f" * (len(FRAME_ID) + FRAME_ID_SLACK)
    return len(serialize_message(message))


def zone_message_cap(max_vertices: int) -> int:
    """Bytes of the largest zone message worth reading: `max_vertices` vertices."""
    message = PolygonInstanceStamped()
    message.polygon.polygon.points = [Point32()] * max_vertices
    return largest(message)


def mask_message_cap(max_cells: int) -> int:
    """Bytes of the largest keep-out mask worth reading: `max_cells` cells (one byte each)."""
    return largest(OccupancyGrid()) + max_cells


def zone_id_unread(data: bytes) -> int | None:
    """The id of a serialized `PolygonInstanceStamped`, read without reading the message: the
    id is its last field, an int64, so the message's last 8 bytes (CDR pads only before a
    field, never after the last), in the byte order the encapsulation header's second byte
    gives (odd: little-endian). A batch of zone messages keeps the last per id, so the ones a
    later message of their id replaces need never be read. None for bytes too short to be one.
    A sender can make the last 8 bytes lie: whoever reads the message checks its id (a
    message whose id is not there is refused)."""
    if len(data) < 12:
        return None
    return int.from_bytes(data[-8:], "little" if data[1] & 1 else "big", signed=True)


def read_capped(data: bytes, msg_type: type, max_bytes: int) -> tuple[object | None, str]:
    """(the message, "") from its serialized `data`, or (None, why not) when `data` is longer
    than `max_bytes` (not read at all) or cannot be read as `msg_type`."""
    if len(data) > max_bytes:
        return None, f"message of {len(data)} bytes, more than the {max_bytes} allowed"
    try:
        return deserialize_message(data, msg_type), ""
    except Exception as error:  # bytes from a writer that lied about its type
        return None, f"unreadable message of {len(data)} bytes ({type(error).__name__})"
