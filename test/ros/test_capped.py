"""Messages measured before they are read (`msg_schemas.capped`): at the cap read, past it not
read at all, and bytes that lie about their length cost no more than they hold."""

from __future__ import annotations

import struct

from geometry_msgs.msg import Point32, PolygonInstanceStamped
from hypothesis import given, settings
from hypothesis import strategies as st
from rclpy.serialization import serialize_message

from msg_schemas import FRAME_ID
from msg_schemas.capped import FRAME_ID_SLACK, read_capped, zone_id_unread, zone_message_cap


def zone(vertices: int, frame_id: str = FRAME_ID) -> bytes:
    message = PolygonInstanceStamped()
    message.header.frame_id, message.polygon.id = frame_id, 3
    message.polygon.polygon.points = [Point32(x=float(k), y=1.0, z=0.0) for k in range(vertices)]
    return serialize_message(message)


def test_the_largest_zone_worth_reading_is_read_and_one_byte_more_is_not() -> None:
    cap = zone_message_cap(64)
    largest = zone(64, "f" * (len(FRAME_ID) + FRAME_ID_SLACK))
    assert len(largest) == cap
    message, problem = read_capped(largest, PolygonInstanceStamped, cap)
    assert problem == "" and len(message.polygon.polygon.points) == 64
    message, problem = read_capped(largest + b"\0", PolygonInstanceStamped, cap)
    assert message is None and problem == f"message of {cap + 1} bytes, more than the {cap} " \
                                          f"allowed"
    assert read_capped(zone(64), PolygonInstanceStamped, cap)[0].polygon.id == 3


def test_a_small_message_that_claims_a_billion_vertices_costs_what_it_holds() -> None:
    """The vertex count is read from the bytes: one that claims more than follow is never
    allocated; the type support reads no more than the bytes hold (or refuses them), and what
    is left is refused later in words (fewer than 3 vertices)."""
    data = bytearray(zone(1))
    count_at = len(data) - (4 + 12 + 8)
    assert struct.unpack_from("<I", data, count_at) == (1,)
    struct.pack_into("<I", data, count_at, 1_000_000_000)
    message, problem = read_capped(bytes(data), PolygonInstanceStamped, zone_message_cap(64))
    if message is None:
        assert problem.startswith(f"unreadable message of {len(data)} bytes")
    else:
        assert len(message.polygon.polygon.points) <= 1


@settings(max_examples=200, deadline=None)
@given(zone_id=st.integers(-2**63, 2**63 - 1), vertices=st.integers(0, 64),
       frame_id=st.text(max_size=40))
def test_a_zone_messages_id_is_read_from_its_last_bytes_whatever_it_holds(
        zone_id: int, vertices: int, frame_id: str) -> None:
    """The batch keeps the last message per id without reading the others: the id read from
    the serialized bytes is the message's id, for any frame, vertex count and id."""
    message = PolygonInstanceStamped()
    message.header.frame_id, message.polygon.id = frame_id, zone_id
    message.polygon.polygon.points = [Point32(x=float(k), y=1.0, z=0.0) for k in range(vertices)]
    assert zone_id_unread(serialize_message(message)) == zone_id
