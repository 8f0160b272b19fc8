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
import functools
import sys


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

    # every batch's zone source shows moving zones late (`ScenarioZones`'s `late`)
    runner.ScenarioZones = functools.partial(runner.ScenarioZones, late=known.late)
    return evaluate(rest)


if __name__ == "__main__":
    sys.exit(main())
