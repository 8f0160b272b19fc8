"""Benchmark what zones cost against their number and vertices: per zone message and per plan.

Per zone batch: what the policy node does when one zone changes while N are in force: apply it to
the live set, rebuild the union, move the held setpoint out (`keep_out`), shield it (`guard`)
and check the rest of the chunk (`violates`, 15 waypoints). Per plan: one constrained chunk at
batch 1 with those zones. N regular polygons of V vertices (radius 12 px) on a grid over the
workspace, the shipped policy, the live configuration, 1 torch thread (the node's default).
Sizes beyond the caps (`max_zones` 32, `max_vertices` 64) are measured with the caps lifted,
to show what the caps keep out.

Keep-out masks: a 128 x 128 mask of 4 px cells with N separate square pieces. "build" is what
the node's mask builder thread does (`build_mask`: scan, union, caps), off the executor;
"apply" what the executor then does (put the pieces in force, rebuild the union, the
no-free-space check); "per zone batch" one zone message with the mask's pieces in force, as
above. A mask past the caps is refused in "build", and nothing reaches the executor. Prints
tables; asserts nothing.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.planning.constraint_configs import load_configurations
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones.geometry import leaves_no_room
from constrained_diffusion_ros.zones.grid import MaskCaps, build_mask
from constrained_diffusion_ros.zones.live import LiveZones
from sim_bridge.scene import block_keypoints, observation, seeded_state

RADIUS = 12.0


def polygons(n: int, vertices: int) -> list[np.ndarray]:
    """n regular polygons of `vertices` vertices on a grid over the 512 px workspace."""
    side = math.ceil(math.sqrt(n))
    spacing = 512.0 / side
    angles = np.linspace(0, 2 * np.pi, vertices, endpoint=False)
    ring = RADIUS * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    centers = [((i % side + 0.5) * spacing, (i // side + 0.5) * spacing) for i in range(n)]
    return [ring + np.array(c) for c in centers]


def timed(function, repeats: int) -> float:
    """Median wall time of `function()` in ms."""
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        times.append(1000 * (time.perf_counter() - started))
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default=str(default_model_dir()))
    parser.add_argument("--configuration", default="ddim10_r_g10_p_safe")
    parser.add_argument("--zones", type=int, nargs="+", default=[1, 16, 32, 64])
    parser.add_argument("--vertices", type=int, nargs="+", default=[4, 64, 256])
    parser.add_argument("--repeats", type=int, default=8, help="per batch; plans: a quarter")
    parser.add_argument("--mask-pieces", type=int, nargs="+", default=[8, 32, 64, 512, 8192],
                        help="separate pieces of the keep-out masks timed (8192: a checkerboard)")
    args = parser.parse_args()
    torch.set_num_threads(1)

    policy = load_policy(args.model)
    config = load_configurations(config_dir() / "configurations.yaml")[args.configuration]
    planner = ConstrainedPlanner(policy, config, PUSHT_ROBOT)
    state = seeded_state(100000)
    latest = observation(block_keypoints(state[None, 2:])[0], state[:2])
    history = torch.from_numpy(np.stack([latest] * policy.config.n_obs_steps)[None]).float()
    generator = torch.Generator().manual_seed(0)
    chunk = planner.plan(history, None, generator=generator)[0].numpy()
    held, rest = chunk[:1].astype(float), torch.from_numpy(chunk[1:])[None]

    print(f"{args.configuration}, 1 torch thread; median ms")
    print("| zones | vertices | per zone batch | per plan |")
    print("|---:|---:|---:|---:|")
    for n in args.zones:
        for v in args.vertices:
            shapes = polygons(n, v)
            live = LiveZones(workspace=PUSHT_ROBOT.workspace)
            live.apply(list(enumerate(shapes)), now=0.0, capped=False)
            flip = [shapes[0], shapes[0] + 1.0]

            def one_message(flip=flip, live=live) -> None:
                flip.reverse()  # a real change each time: the union is rebuilt
                live.apply([(0, flip[0])], now=0.0, capped=False)
                zones = live.snapshot()
                setpoint = planner.keep_out(zones, held)
                planner.guard(zones, latest[None], setpoint, 0)
                planner.violates(rest, zones, np.array([0]))

            def one_plan(live=live) -> None:
                planner.plan(history, live.snapshot(), generator=generator)

            per_message = timed(one_message, args.repeats)
            per_plan = timed(one_plan, max(2, args.repeats // 4))
            print(f"| {n} | {v} | {per_message:.1f} | {per_plan:.0f} |", flush=True)

    caps = MaskCaps()
    print(f"\nkeep-out masks, 128 x 128 cells of 4 px, default caps ({caps.pieces} pieces, "
          f"{caps.vertices} vertices, {caps.rectangles} rectangles); median ms")
    print("| pieces | build (mask thread) | apply (executor) | per zone batch | outcome |")
    print("|---:|---:|---:|---:|---|")
    for pieces in args.mask_pieces:
        grid = {"values": mask_of(pieces), "resolution": 4.0}
        built = build_mask(grid, caps, PUSHT_ROBOT.workspace)
        build_ms = timed(lambda grid=grid: build_mask(grid, caps, PUSHT_ROBOT.workspace),
                         max(2, args.repeats // 4))
        if built.polygons is None:
            print(f"| {pieces} | {build_ms:.1f} | - | - | refused: {built.reason} |", flush=True)
            continue
        updates = [(f"keepout/{k}", p) for k, p in enumerate(built.polygons)]

        def apply(updates=updates) -> LiveZones:
            live = LiveZones(workspace=PUSHT_ROBOT.workspace)
            live.apply(updates, now=0.0, capped=False)
            leaves_no_room(live.snapshot().geometry, PUSHT_ROBOT.workspace,
                           PUSHT_ROBOT.pusher_radius)
            return live

        apply_ms = timed(apply, args.repeats)
        live = apply()
        zone = [polygons(1, 4)[0] + 3.0, polygons(1, 4)[0] + 4.0]

        def one_message(zone=zone, live=live) -> None:
            zone.reverse()
            live.apply([(0, zone[0])], now=0.0)
            zones = live.snapshot()
            planner.guard(zones, latest[None], planner.keep_out(zones, held), 0)
            planner.violates(rest, zones, np.array([0]))

        per_message = timed(one_message, args.repeats)
        print(f"| {pieces} | {build_ms:.1f} | {apply_ms:.1f} | {per_message:.1f} | "
              f"{len(built.polygons)} zones |", flush=True)


def mask_of(pieces: int, cells: int = 128) -> np.ndarray:
    """A (cells, cells) mask with `pieces` separate keep-out squares: 2 x 2 cells spread evenly
    (a checkerboard of single cells once they no longer fit)."""
    mask = np.zeros((cells, cells), dtype=np.int8)
    side = math.ceil(math.sqrt(pieces))
    if side > cells // 3:
        board = np.add.outer(np.arange(cells), np.arange(cells)) % 2 == 0
        flat = np.flatnonzero(board)[:pieces]
        mask.flat[flat] = 100
        return mask
    spacing = cells // side
    for k in range(pieces):
        row, col = (k // side) * spacing, (k % side) * spacing
        mask[row:row + 2, col:col + 2] = 100
    return mask


if __name__ == "__main__":
    main()
