"""Stress the moving-zone guarantee offline: `evaluate`, with every moving zone shown to the
filter LATE control steps after it was where it is shown (a tracker and a node behind, as on a
busy machine), aged by as much, while contacts are counted against where the zone really is.

    OMP_NUM_THREADS=2 .venv/bin/python scripts/stress_late_zones.py --late 3 --episodes 100 \
        --scenarios hand_homing@200 hand_homing@300 --configs ddim10_r_g10_p_safe \
        --threads 2 --output /tmp/late3

Every other argument is `evaluate`'s (`evaluate --help`). The filter is told each zone's age,
so a zone known to move is grown by its speed over the lag as well; what a lag costs is the
time a zone that has set off is still shown standing where it waited (the guarantee's
assumption "a zone never seen moving stands still", docs/moving_zones.md), and plans made
against older zones.
"""

from __future__ import annotations

import argparse
import sys


def late_zones(late: int) -> type:
    """`ScenarioZones` whose moving zones are shown `late` control steps late."""
    import numpy as np
    import torch

    from constrained_diffusion_ros.evaluation import runner
    from constrained_diffusion_ros.pusht import PUSHT_ROBOT
    from constrained_diffusion_ros.zones.area import RestrictedArea, Translated
    from constrained_diffusion_ros.zones.episodes import EpisodeZones
    from constrained_diffusion_ros.zones.geometry import ZoneSet
    from constrained_diffusion_ros.zones.motion import MovingZones, assumed_speeds

    class LateZones(runner.ScenarioZones):
        def __init__(self, *args: object, **kwargs: object) -> None:
            super().__init__(*args, **kwargs)
            self.speeds: dict[int, np.ndarray] = {}  # step -> assumed speeds known then

        def offsets_at(self, step: int) -> np.ndarray:
            fresh = step not in self.offsets
            offsets = super().offsets_at(step)
            if fresh:
                self.speeds[step] = assumed_speeds(self.moved, self.fastest, self.speed_bound)
            return offsets

        def area_at(self, step: int) -> RestrictedArea:
            if not self.movers:
                return super().area_at(step)
            self.offsets_at(step)
            seen = max(0, step - late)
            shown = torch.from_numpy(self.offsets[seen])
            areas, still, moving = [], [], []
            for index, scenario in enumerate(self.scenarios):
                if index in self.movers:
                    areas.append(Translated(scenario.zones_at(0), shown[self.rows[index]]))
                    still.append(ZoneSet.empty())
                    moving.append(areas[-1])
                else:
                    areas.append(scenario.zones_at(step))
                    still.append(areas[-1])
                    moving.append(ZoneSet.empty())
            velocity = (self.offsets[seen] - self.offsets.get(seen - 1, self.offsets[seen])) \
                * PUSHT_ROBOT.control_hz
            area, still, moving = (EpisodeZones(parts, self.scenario_of_row)
                                   for parts in (areas, still, moving))
            return MovingZones(area, still, moving, torch.from_numpy(self.speeds[seen]),
                               (step - seen) / PUSHT_ROBOT.control_hz, PUSHT_ROBOT.reaction_s,
                               drift=[(moving, torch.from_numpy(velocity))])

    return LateZones


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], add_help=False)
    parser.add_argument("--late", type=int, default=2,
                        help="control steps (0.1 s each) moving zones are shown late")
    known, rest = parser.parse_known_args(argv)
    if "-h" in rest or "--help" in rest:
        print(__doc__)
        return 0
    if known.late < 0:
        print("stress_late_zones: --late must be 0 or more", file=sys.stderr)
        return 2
    from constrained_diffusion_ros.evaluation import runner
    from constrained_diffusion_ros.evaluation.evaluate import main as evaluate

    runner.ScenarioZones = late_zones(known.late)
    return evaluate(rest)


if __name__ == "__main__":
    sys.exit(main())
