"""Moving-zone trials for bench_realtime.py: a 60 px square zone, one id per trial, republished
at 20 Hz (stamped with the client's ROS clock) while it moves at a set speed, crossing the
pusher's position or homing on it; the figures are taken from what the client observes (the
pusher as the sim reports it, setpoints as received, the zone as it was published), so they
hold the node to what a robot beside it would see, not to the node's own account.

Kept apart from bench_realtime.py, which runs them: they take the benchmarks' client
(`live_client.Client`) and its scene reset (`start_scene`) as arguments, so nothing here starts
nodes or load.
"""

from __future__ import annotations

import argparse
import time
from bisect import bisect_right
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import shapely
from live_client import Client

from constrained_diffusion_ros.evaluation.runner import unavoidable
from constrained_diffusion_ros.zones.geometry import ZoneSet
from sim_bridge import AGENT_RADIUS
from sim_bridge.scene import WORKSPACE_SIZE

KINDS = ("crossing", "homing")
SIDE = 60.0  # px, the zone's side
CORNERS = SIDE / 2 * np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
REPUBLISH_HZ = 20.0
APPROACH = 150.0  # px: the zone's centre from the pusher's position where it starts (and ends)
HOMING_S, LEAVING_S = 3.0, 1.0  # homing: heading for the pusher, then straight away from it
SEEN_S = 0.03  # a setpoint is held to the zone as published this long before it was received
NEAR_PX = 100.0  # a standstill counts while the zone is this close to the pusher's centre
STILL_PX = 1.0  # px per step: a pusher moving less stands still
SETTLE_S = 0.6  # after the zone is removed: the node's next /diagnostics (every 0.5 s) is in
FIRST_ID = 3000  # zone ids, one per trial (a fresh id: no motion carried over from the last)
DIRECTIONS = 64  # random headings tried for a path that stays inside the workspace


def add_moving_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--moving", nargs="+", choices=KINDS, default=list(KINDS),
                        metavar="KIND",
                        help="moving-zone trials (crossing, homing), run after the others in "
                             "each condition with the first configuration whose name ends in "
                             "_safe (the shield, which answers a zone's motion); none: no "
                             "moving trials")
    parser.add_argument("--moving-speeds", nargs="+", type=float, default=[100.0, 200.0],
                        metavar="PX_PER_S", help="speeds of the moving zone, px/s")
    parser.add_argument("--moving-trials", type=int, default=None,
                        help="moving-zone trials per kind and speed (None: --trials)")
    parser.add_argument("--no-moving", action="store_true", help="skip the moving-zone trials")


def moving_configuration(args: argparse.Namespace) -> str | None:
    """The configuration the moving trials run with: the first with the shield, if any."""
    if args.no_moving:
        return None
    return next((c for c in args.configurations if c.endswith("_safe")), None)


@dataclass
class MovingTrial:
    """One moving-zone trial's figures; px, and steps of the sim's observations."""

    contacts: int = 0  # observations with the disc overlapping the zone as published
    unavoidable: int = 0  # of those, ones no setpoint one step before could have avoided
    deepest: float = 0.0  # the deepest overlap
    least: float = float("inf")  # the least separation: pusher centre to zone less the radius
    inside: int = 0  # setpoints in the zone as published SEEN_S before they were received
    grazing: int = 0  # setpoints within the pusher radius of it (the inside ones included)
    cornered: int = 0  # rise of the node's cornered_steps
    # Rise of its zone_speed_exceeded (None: not reported). The node reports it only while a
    # zone is in force, so updates in the last 0.5 s before the removal may be missed.
    exceeded: int | None = None
    standstill: int = 0  # the longest run of still steps with the zone within NEAR_PX
    # Rise of its zone_updates_within_reach: updates left to the next observation's answer
    within_reach: int = 0
    updates: int = 0  # zone messages published (the removal included)


def inside_box(centres: np.ndarray) -> np.ndarray:
    """How far (px) each centre (..., 2) puts the zone beyond the workspace (0: inside it)."""
    low, high = SIDE / 2, WORKSPACE_SIZE - SIDE / 2
    return np.maximum(np.maximum(low - centres, centres - high), 0).max(axis=-1)


def heading(rng: np.random.Generator, ends: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """A random unit heading whose path ends (`ends(unit)`: (..., 2) centres) keep the zone in
    the workspace; the one that leaves it least if none does (the node refuses a zone wholly
    outside, and one partly outside is clipped)."""
    angles = rng.uniform(0, 2 * np.pi, DIRECTIONS)
    units = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    beyond = np.array([inside_box(ends(u)).max() for u in units])
    return units[int(np.argmax(beyond == 0)) if (beyond == 0).any() else int(np.argmin(beyond))]


def drive(client: Client, kind: str, speed: float, zone_id: int,
          rng: np.random.Generator) -> list[tuple[float, np.ndarray | None]]:
    """Moves the zone, republishing it at REPUBLISH_HZ, then removes it (an empty polygon for
    its id); what was published when (time.monotonic(); None: removed)."""
    pusher = client.pushers[-1][2].copy()
    if kind == "crossing":  # straight across the pusher, offset sideways by up to half a side
        offset = rng.uniform(-SIDE / 2, SIDE / 2)

        def ends(u: np.ndarray) -> np.ndarray:
            across = pusher + offset * np.array([-u[1], u[0]])
            return np.stack([across - APPROACH * u, across + APPROACH * u])

        unit = heading(rng, ends)
        start = ends(unit)[0]
        duration = 2 * APPROACH / speed
    else:
        unit = heading(rng, lambda u: pusher + APPROACH * u)
        start = pusher + APPROACH * unit
        duration = HOMING_S + LEAVING_S
    centre, leaving = start.copy(), None
    published: list[tuple[float, np.ndarray | None]] = []
    began = last = time.monotonic()
    for tick in range(1, int(duration * REPUBLISH_HZ) + 2):
        now = time.monotonic()
        elapsed = min(now - began, duration)
        if kind == "crossing":
            centre = start + unit * speed * elapsed
        elif elapsed < HOMING_S:  # toward where the pusher was last seen, not past it
            towards = client.pushers[-1][2] - centre
            distance = float(np.linalg.norm(towards))
            if distance > 0:
                centre = centre + towards / distance * min(distance, speed * (now - last))
        else:
            if leaving is None:
                away = centre - client.pushers[-1][2]
                norm = float(np.linalg.norm(away))
                leaving = away / norm if norm > 0 else unit
            centre = centre + leaving * speed * (now - last)
        last = now
        vertices = CORNERS + np.clip(centre, 0.0, WORKSPACE_SIZE)  # a quarter stays inside
        client.publish_zone(zone_id, vertices)
        published.append((time.monotonic(), vertices))
        if elapsed >= duration:
            break
        due = began + tick / REPUBLISH_HZ
        client.spin_until(lambda due=due: time.monotonic() >= due, 1.0, "the zone's next update")
    client.publish_zone(zone_id, None)
    published.append((time.monotonic(), None))
    return published


def measure(client: Client, published: list[tuple[float, np.ndarray | None]],
            first_pusher: int, first_setpoint: int, before: dict[str, int | None]) -> MovingTrial:
    """The trial's figures from the observations and setpoints since the zone first went out,
    each against the zone as published at the time (see MovingTrial)."""
    times = [t for t, _ in published]
    workspace = shapely.box(0.0, 0.0, WORKSPACE_SIZE, WORKSPACE_SIZE)
    # As the node enforces it: clipped to the workspace.
    shapes = [None if v is None else shapely.Polygon(v).intersection(workspace)
              for _, v in published]

    def zone_at(t: float) -> int | None:
        index = bisect_right(times, t) - 1
        return index if index >= 0 and shapes[index] is not None else None

    trial = MovingTrial(updates=len(published))
    run = 0
    pushers = client.pushers[max(1, first_pusher):]
    previous = client.pushers[max(1, first_pusher) - 1]
    for received, step, point in pushers:
        index = zone_at(received)
        moved = np.linalg.norm(point - previous[2]) / max(1, step - previous[1])
        before_point, previous = previous[2], (received, step, point)
        if index is None:
            run = 0
            continue
        shape, centre = shapes[index], shapely.Point(*point)
        distance = shape.exterior.distance(centre) * (-1 if shape.contains(centre) else 1)
        separation = distance - AGENT_RADIUS
        trial.least = min(trial.least, separation)
        if separation < 0:
            trial.contacts += 1
            trial.deepest = max(trial.deepest, -separation)
            trial.unavoidable += int(unavoidable(before_point[None], ZoneSet([shape]))[0])
        run = run + 1 if moved < STILL_PX and distance <= NEAR_PX else 0
        trial.standstill = max(trial.standstill, run)
    for setpoint in client.setpoints[first_setpoint:]:
        index = zone_at(setpoint.received - SEEN_S)
        if index is not None:
            point = shapely.Point(*setpoint.point)
            trial.inside += int(shapes[index].contains(point))
            trial.grazing += int(shapes[index].distance(point) < AGENT_RADIUS)
    after = counters(client)
    trial.cornered = (after["cornered_steps"] or 0) - (before["cornered_steps"] or 0)
    trial.within_reach = ((after["zone_updates_within_reach"] or 0)
                          - (before["zone_updates_within_reach"] or 0))
    if after["zone_speed_exceeded"] is not None:
        trial.exceeded = after["zone_speed_exceeded"] - (before["zone_speed_exceeded"] or 0)
    return trial


def counters(client: Client) -> dict[str, int | None]:
    """The node's cornered_steps, zone_speed_exceeded and zone_updates_within_reach as it
    last reported them."""
    return {key: int(float(client.status[key])) if key in client.status else None
            for key in ("cornered_steps", "zone_speed_exceeded", "zone_updates_within_reach")}


def run_moving_trials(client: Client, args: argparse.Namespace, first_seed: int,
                      start_scene: Callable[[Client, int], float]
                      ) -> dict[tuple[str, float], list[MovingTrial]]:
    """`--moving-trials` trials per kind and speed, on scenes from `first_seed` (each kind and
    speed on the same scenes, with the same random headings)."""
    count = args.trials if args.moving_trials is None else args.moving_trials
    results: dict[tuple[str, float], list[MovingTrial]] = {}
    zone_id = FIRST_ID
    for kind in args.moving:
        for speed in args.moving_speeds:
            for seed in range(first_seed, first_seed + count):
                start_scene(client, seed)
                client.spin_for(args.warmup)
                before = counters(client)
                first_pusher, first_setpoint = len(client.pushers), len(client.setpoints)
                published = drive(client, kind, speed, zone_id, np.random.default_rng(seed))
                zone_id += 1
                client.spin_for(SETTLE_S)
                results.setdefault((kind, speed), []).append(
                    measure(client, published, first_pusher, first_setpoint, before))
                print(".", end="", flush=True)
    print()
    return results


def report_moving(configuration: str, results: dict[tuple[str, float], list[MovingTrial]]
                  ) -> None:
    print(f"  moving zones, {configuration} ({SIDE:.0f} px square republished at "
          f"{REPUBLISH_HZ:.0f} Hz; contact: the pusher's disc overlaps the zone as published):")
    for (kind, speed), trials in results.items():
        least = np.array([t.least for t in trials])
        exceeded = [t.exceeded for t in trials if t.exceeded is not None]
        contacts = sum(t.contacts for t in trials)
        unavoidable_steps = sum(t.unavoidable for t in trials)
        print(f"    {kind} {speed:g} px/s: {len(trials)} trials, "
              f"{sum(t.contacts > 0 for t in trials)} with contact "
              f"({sum(t.contacts > 0 and t.cornered > 0 for t in trials)} of them cornered); "
              f"trials cornered {sum(t.cornered > 0 for t in trials)}; contact steps {contacts} "
              f"({contacts - unavoidable_steps} avoidable, {unavoidable_steps} unavoidable); "
              f"deepest overlap {max(t.deepest for t in trials):.2f} px; least separation "
              f"min {least.min():.1f}, median {np.median(least):.1f} px; setpoints in the zone "
              f"as published {1000 * SEEN_S:.0f} ms before {sum(t.inside for t in trials)} "
              f"(within the pusher radius of it {sum(t.grazing for t in trials)}); cornered "
              f"steps {sum(t.cornered for t in trials)}; zone_speed_exceeded "
              f"{sum(exceeded) if exceeded else 'not reported'}; updates within the reach "
              f"assumed (left to the next observation) {sum(t.within_reach for t in trials)} of "
              f"{sum(t.updates for t in trials)}; longest standstill with the zone "
              f"within {NEAR_PX:.0f} px {max(t.standstill for t in trials)} steps")
