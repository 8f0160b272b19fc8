"""Zones in from ROS for a node that obeys them.

`ZoneIngest` is a listener in the manner of tf2_ros's `TransformListener`: built with a node, it
owns the subscriptions that fill the node's `LiveZones` (zone polygons, and keep-out masks with
the thread that builds them) and nothing else. The node hears of a change through one callback
and reads the counts for its diagnostics; the zones themselves it reads from its `LiveZones`,
as the planner does. Markers that show the zones (zone_markers.py) and the ways zones leave
without a message, the clear service and expiry (zone_clearing.py), are helpers of their own.

Zones come in as id-keyed polygons, taken in batches as fast as they come and coalesced to the
last message per id; a malformed one, or one over the caps, is refused with a warning while the
zones in force stay in force. Zones and masks are taken serialized and their length checked
first (`msg_schemas.capped`): a message longer than the largest the caps allow is refused and
counted without being read, so no participant can hold the node with a message too big to read.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import PolygonInstanceStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy

from constrained_diffusion_ros.runtime.mask_builder import MaskBuilder
from constrained_diffusion_ros.zones.area import Bounds
from constrained_diffusion_ros.zones.grid import BuiltMask, MaskCaps, build_mask
from constrained_diffusion_ros.zones.live import BatchOutcome, LiveZones
from msg_schemas import FRAME_ID, TOPICS, qos_profile
from msg_schemas.capped import mask_message_cap, read_capped, zone_id_unread, zone_message_cap
from msg_schemas.conversions import stamp_seconds
from msg_schemas.text import one_line

ZONE_BATCH_MAX = 10_000  # zone messages taken in one callback at most
MARKER_NAMESPACE = "zones"  # zone markers: marker namespace <node namespace>/zones, id = zone id
EXPIRY_PERIOD_S = 0.2  # zones past their lifetime are dropped this often
COUNTS = ("zone_messages", "zones_applied", "zones_refused", "zones_oversized", "zones_stale",
          "zone_batches", "masks_applied", "masks_refused")
OVERSIZED_LOG_PERIOD_S = 1.0  # a flood of oversized messages is logged this often at most


def by_id(messages: list[tuple[bytes, dict]]) -> list[tuple[int | None, list[bytes]]]:
    """(id, its messages newest first) per id (`zone_id_unread`), in the order the ids last
    appeared, as `LiveZones.apply` keeps them; a message too long to read or too short to hold
    an id is one of its own (id None), to be refused when read."""
    groups: dict[object, tuple[int | None, list[bytes]]] = {}
    for index, (data, _info) in enumerate(messages):
        zone_id = None if isinstance(data, Unread) else zone_id_unread(data)
        key = ("unread", index) if zone_id is None else zone_id
        _, older = groups.pop(key, (zone_id, []))
        groups[key] = (zone_id, [data, *older])
    return list(groups.values())


@dataclass(frozen=True)
class Unread:
    """A message too long to read, kept as its length while a batch is taken."""

    size: int

    def __len__(self) -> int:
        return self.size


class ZoneIngest:
    """Feeds `zones` from the node's zone topic and keep-out masks; calls
    `on_change(received, within_reach)` (time.monotonic() the message that changed them came;
    whether the change was only moving zones staying within the reach assumed of them,
    `BatchOutcome.within_reach`) on the node's executor thread whenever the zones in force
    change.

    Reads the node's `zone_lifetime` and `keepout_threshold` parameters at each message: they
    are settable at run time. `realtime`: masks are built on a thread of their own (zones and
    observations are answered meanwhile) and a burst of zone messages gets half the executor
    thread at most; else everything happens in the callback, so a lockstep trial stays
    deterministic. `shutdown` ends the mask thread.
    """

    def __init__(self, node: Node, zones: LiveZones, workspace: Bounds, mask_caps: MaskCaps,
                 on_change: Callable[[float, bool], None], realtime: bool,
                 alive: Callable[[], None] = lambda: None) -> None:
        self.node, self.zones, self.workspace, self.mask_caps = node, zones, workspace, mask_caps
        self.on_change, self.realtime, self.alive = on_change, realtime, alive
        self.counts = dict.fromkeys(COUNTS, 0)
        self.zone_cap = zone_message_cap(zones.max_vertices)  # bytes
        self.mask_cap = mask_message_cap(mask_caps.cells)
        self.last_refusal = ""  # why the last zone or mask was refused
        # From any publisher: a volatile subscription matches every one, a transient-local one
        # also gets a latched publisher's history when the node (re)starts; a message both
        # deliver is taken once.
        latched = qos_profile(TOPICS["zones"])
        volatile = qos_profile(TOPICS["zones"])
        volatile.durability = DurabilityPolicy.VOLATILE
        # A volatile publisher cannot serve the transient-local one, by design: its "incompatible
        # QoS" event is expected, not worth a warning on every run.
        quiet = SubscriptionEventCallbacks(incompatible_qos=lambda _event: None)
        self.subscriptions = [
            node.create_subscription(PolygonInstanceStamped, TOPICS["zones"].name,
                                     self._on_zone, volatile, raw=True),
            node.create_subscription(PolygonInstanceStamped, TOPICS["zones"].name,
                                     self._on_zone, latched, event_callbacks=quiet, raw=True)]
        self._seen: OrderedDict[tuple, None] = OrderedDict()
        self._paced_until = 0.0  # realtime: no zone batch before then (`_on_zone`)
        self._deferred: list[tuple] = []  # (serialized, info) taken, not applied yet
        self._deferred_since = 0.0  # when the first of them came (time.monotonic())
        # Realtime: fires when a batch that came too early is due.
        self._pacer = node.create_timer(1.0, self._on_paced, autostart=False) \
            if realtime else None
        node.create_subscription(OccupancyGrid, TOPICS["keepout_mask"].name,
                                 self._on_serialized_mask, qos_profile(TOPICS["keepout_mask"]),
                                 raw=True)
        self.keepout_ids: list[str] = []
        self.mask_builder: MaskBuilder | None = None
        if realtime:  # masks built off the thread that answers zones
            self._mask_ready = node.create_guard_condition(self._on_mask_ready)
            self._built_mask: BuiltMask | None = None
            self.mask_builder = MaskBuilder(self._on_mask_built, mask_caps, workspace)

    def status(self) -> dict[str, object]:
        return {**self.counts, "zone_refusal": self.last_refusal}

    def shutdown(self) -> None:
        if self.mask_builder is not None:
            self.mask_builder.shutdown()

    # -- zone messages ----------------------------------------------------------------------

    def _on_zone(self, data: bytes, info: dict) -> None:
        """Takes every zone message waiting, not just this one: a flood is applied as one
        batch (the last message per id) and the union is rebuilt once, when next read. Each is
        read only if it is no longer than the caps allow.

        Realtime: a batch right after another waits as long as the last one took, so a flood
        gets half the executor thread at most. The wait is a timer's, not a sleep in this
        callback: the executor answers observations meanwhile (a sleeping callback held them,
        and under a flood the node answered observations up to a second old, from a queue that
        had grown while it slept). Kept busy at SCHED_FIFO by a flood, the thread can be
        throttled by the kernel (its real-time budget spent) while it holds the interpreter
        lock, and the clock's ticks then wait for it (see docs/hostile_inputs.md); the wait
        coalesces the messages meanwhile, so nothing is lost and a zone waits no longer than
        behind a batch."""
        received = time.monotonic()
        if not self._deferred:
            self._deferred_since = received
        self._deferred.append((data, info))
        for subscription in self.subscriptions:
            self._deferred += self._take_waiting(subscription,
                                                 ZONE_BATCH_MAX - len(self._deferred))
        wait = self._paced_until - received if self.realtime else 0.0
        if wait > 0:
            self._pacer.timer_period_ns = max(1, int(wait * 1e9))
            self._pacer.reset()
            return
        self._apply_deferred()

    def _on_paced(self) -> None:
        self._pacer.cancel()
        if self._deferred:
            for subscription in self.subscriptions:
                self._deferred += self._take_waiting(subscription,
                                                     ZONE_BATCH_MAX - len(self._deferred))
            self._apply_deferred()

    def _apply_deferred(self) -> None:
        """The messages taken since the last batch, applied as one: per id the newest that
        reads, so a flood's thousands of messages cost a read per id, not one each."""
        messages, received, self._deferred = self._deferred, self._deferred_since, []
        fresh = [(data, info) for data, info in messages if not self._seen_before(data, info)]
        updates, refused, read = [], 0, 0
        for guessed, newest_first in by_id(fresh):
            for serialized in newest_first:
                read += 1
                update = self._read_zone(serialized, guessed)
                if update is not None:
                    updates.append(update)
                    break
                refused += 1
        lifetime = self.node.get_parameter("zone_lifetime").value or None
        outcome = self.zones.apply(updates, self._now(), lifetime)
        self._count(outcome, refused, len(fresh) - read)
        if outcome.changed:
            self.on_change(received, outcome.within_reach)
        finished = time.monotonic()
        self._paced_until = finished + (finished - max(received, self._paced_until))
        self.alive()  # the executor is at work, not stalled (the clock's watchdog)

    def _read_zone(self, serialized: bytes, guessed: int | None) -> tuple | None:
        """(id, vertices, stamp) of a zone message batched under id `guessed`, or None when it
        is refused (warned, `last_refusal` set)."""
        message, problem = read_capped(serialized, PolygonInstanceStamped, self.zone_cap)
        if message is None:
            self.counts["zones_oversized"] += 1
            self.last_refusal = f"zone {problem} (max_vertices {self.zones.max_vertices})"
            self.node.get_logger().warning(
                f"zone refused unread, zones in force kept: {self.last_refusal}",
                throttle_duration_sec=OVERSIZED_LOG_PERIOD_S)
            return None
        zone_id = int(message.polygon.id)
        if message.header.frame_id not in ("", FRAME_ID):
            problem = f"frame {one_line(repr(message.header.frame_id), 80)} is not {FRAME_ID!r}"
        elif zone_id != guessed:  # its last 8 bytes, which batched it, are not its id
            problem = "its id is not the message's last field (bytes after the message)"
        if problem:
            self.last_refusal = f"zone {zone_id}: {problem}"
            self.node.get_logger().warning(f"zone refused, zones in force kept: "
                                           f"{self.last_refusal}")
            return None
        stamp = stamp_seconds(message.header.stamp) or None  # 0: unstamped, from arrival
        return zone_id, [(p.x, p.y) for p in message.polygon.polygon.points], stamp

    def _seen_before(self, serialized: bytes, info: dict) -> bool:
        """Whether the other zone subscription already delivered this message (a latched
        publisher reaches both): same publication time, sequence number and length."""
        key = (info.get("source_timestamp"), info.get("publication_sequence_number"),
               len(serialized))
        if key in self._seen:
            return True
        self._seen[key] = None
        if len(self._seen) > 2 * ZONE_BATCH_MAX:
            self._seen.popitem(last=False)
        return False

    def _take_waiting(self, subscription, limit: int) -> list[tuple]:
        """The (serialized message, info) pairs already queued on `subscription` (rclpy's own
        take, as its executor does), so a callback can handle a burst at once; one longer than
        the cap is kept as its length only (`Unread`), so a burst of them is not held whole.
        rclpy has no public call for this: with one message per callback (its public API) the
        node took 6,237 of a 1 kHz flood's 10,000 messages and its zones never matched the last
        message per id (docs/hostile_inputs.md, "The private take, measured")."""
        taken = []
        try:
            while len(taken) < limit:
                with subscription.handle:
                    got = subscription.handle.take_message(subscription.msg_type,
                                                           subscription.raw)
                if got is None:
                    break
                data, info = got
                taken.append((data if len(data) <= self.zone_cap else Unread(len(data)), info))
        except (AttributeError, TypeError):  # another rclpy: one message per callback
            pass
        except RuntimeError as error:  # the middleware failed a take: the executor's next one
            self.last_refusal = f"zone batch cut short: {one_line(error)}"
            self.node.get_logger().warning(self.last_refusal, throttle_duration_sec=1.0)
        return taken

    # -- keep-out masks ---------------------------------------------------------------------

    def _on_serialized_mask(self, data: bytes, info: dict) -> None:
        msg, problem = read_capped(data, OccupancyGrid, self.mask_cap)
        if msg is None:
            self._refuse_mask(f"{problem} (cells at most {self.mask_caps.cells})")
        else:
            self._on_keepout_mask(msg, info.get("source_timestamp", 0) * 1e-9 or None)

    def _on_keepout_mask(self, msg: OccupancyGrid, published: float | None = None) -> None:
        """A keep-out mask: its restricted cells become zones ("keepout/<k>", exact polygons)
        in place of the previous mask's; they do not expire. Under the caps, which bound the
        build. A mask's stamp only tells a replay from a new mask (a cleared one stays gone
        when a latched publisher replays it after a restart): an unstamped one goes by when
        it was `published` (the middleware's source timestamp, which a replay keeps)."""
        if msg.header.frame_id not in ("", FRAME_ID):
            self._refuse_mask(f"frame {one_line(repr(msg.header.frame_id), 80)} is not "
                              f"{FRAME_ID!r}")
            return
        info = msg.info
        grid = {"values": np.asarray(msg.data, dtype=np.int8), "resolution": info.resolution,
                "origin": (info.origin.position.x, info.origin.position.y),
                "threshold": self.node.get_parameter("keepout_threshold").value,
                "width": info.width, "height": info.height}
        stamp = stamp_seconds(msg.header.stamp) or published
        if self.mask_builder is not None:
            self.mask_builder.submit(stamp, **grid)
        else:
            self._take_mask(build_mask(grid, self.mask_caps, self.workspace, stamp=stamp))

    def _on_mask_built(self, built: BuiltMask) -> None:
        """On the builder's thread: hand the mask to the executor's thread."""
        self._built_mask = built
        self._mask_ready.trigger()

    def _on_mask_ready(self) -> None:
        built, self._built_mask = self._built_mask, None
        if built is not None and built.sequence == self.mask_builder.latest:
            self._take_mask(built)

    def _refuse_mask(self, reason: str) -> None:
        self.counts["masks_refused"] += 1
        self.last_refusal = f"keep-out mask: {one_line(reason, 200)}"
        self.node.get_logger().warning(f"keep-out mask refused, zones in force kept: {reason}")

    def _take_mask(self, built: BuiltMask) -> None:
        if built.polygons is None:
            self._refuse_mask(built.reason)
            return
        ids = [f"keepout/{k}" for k in range(len(built.polygons))]
        removed = [(old, []) for old in self.keepout_ids if old not in ids]
        # A mask's pieces are not messages: the caps on zone messages do not refuse them (the
        # mask's own caps did). Its stamp goes with them, so a clear outlives a restart.
        outcome = self.zones.apply([*removed, *((i, p, built.stamp) for i, p in
                                                zip(ids, built.polygons))],
                                   self._now(), capped=False)
        in_force = set(self.zones.ids)
        self.keepout_ids = [i for i in ids if i in in_force]
        self._count(outcome, 0)
        self.counts["masks_applied"] += 1
        self.node.get_logger().info(f"keep-out mask: {len(self.keepout_ids)} zone(s), built "
                                    f"in {1000 * built.seconds:.0f} ms")
        if outcome.changed:
            self.on_change(time.monotonic(), False)

    # -- counts -------------------------------------------------------------------------------

    def _count(self, outcome: BatchOutcome, refused_frames: int, unread: int = 0) -> None:
        """`unread`: messages a later one of their id replaced before they were read."""
        counts = self.counts
        counts["zone_batches"] += 1
        counts["zone_messages"] += outcome.received + refused_frames + unread
        counts["zones_applied"] += outcome.applied
        counts["zones_refused"] += len(outcome.refused) + refused_frames
        counts["zones_stale"] += outcome.stale
        for zone_id, reason in outcome.refused:
            self.last_refusal = one_line(reason, 200)
            self.node.get_logger().warning(f"zone {zone_id} refused, zones in force kept: "
                                           f"{one_line(reason)}")

    def _now(self) -> float:
        """s on the node's clock (sim time with use_sim_time), as zone stamps are."""
        return self.node.get_clock().now().nanoseconds * 1e-9
