"""Two policies' evaluation reports side by side: today's policy and the zone-aware one, cell by
cell (same scenarios, configurations and seeds), as the markdown table docs/zone_aware_policy.md
shows. Per scenario: s with its 95% interval, success and interventions per episode for each
configuration asked for, and the guarantees (r; r_body outside the episodes that start in a
zone) of both policies. Prints; asserts nothing.

  .venv/bin/python scripts/compare_policies.py docs/zone_aware/today/results.json \
      docs/zone_aware/zones/results.json --configs ddim10_r_g10_p ddim10_r_g10_p_safe
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def cells(path: Path) -> dict[tuple[str, str], dict]:
    return {(row["scenario"], row["configuration"]): row
            for row in json.loads(path.read_text())}


def figure(cell: dict | None) -> str:
    if cell is None:
        return "-"
    low, high = cell["s_ci"]
    return (f"{cell['s']:.3f} [{low:.2f}, {high:.2f}], {100 * cell['success_rate']:.0f}%, "
            f"{cell['interventions']:.1f}")


def guarantee(cell: dict | None) -> str:
    if cell is None:
        return "-"
    return f"{cell['r']:.2f} / {cell['r_body_outside_starts']:.2f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("today", type=Path, help="results.json of today's policy")
    parser.add_argument("aware", type=Path, help="results.json of the zone-aware policy")
    parser.add_argument("--configs", nargs="+", required=True)
    args = parser.parse_args()
    today, aware = cells(args.today), cells(args.aware)
    scenarios = list(dict.fromkeys(s for s, _ in today))
    header = ["scenario"]
    for config in args.configs:
        header += [f"{config} today", f"{config} zone-aware"]
    header += [f"r / r_body {c} (today, zone-aware)" for c in args.configs]
    print("| " + " | ".join(header) + " |")
    print("|" + " --- |" * len(header))
    for scenario in scenarios:
        row = [scenario]
        for config in args.configs:
            row += [figure(today.get((scenario, config))), figure(aware.get((scenario, config)))]
        row += [f"{guarantee(today.get((scenario, c)))}; {guarantee(aware.get((scenario, c)))}"
                for c in args.configs]
        print("| " + " | ".join(row) + " |")
    print("\ncells: s [95% interval], success, interventions per episode")
    return 0


if __name__ == "__main__":
    sys.exit(main())
