"""Tables and figures of an evaluation: Markdown laid out like the paper's Table I (with its
values beside ours), CSV and JSON of every cell, a Fig. 1-like strip of frames, s against r."""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from constrained_diffusion_ros.evaluation.evaluated_configurations import EvaluatedConfiguration
from constrained_diffusion_ros.evaluation.rollout import RolloutLog
from constrained_diffusion_ros.evaluation.runner import CellResult
from constrained_diffusion_ros.evaluation.scenarios import Scenario
from constrained_diffusion_ros.paths import config_dir
from constrained_diffusion_ros.planning.constraint_configs import read_yaml


def load_paper_table(path: Path | None = None) -> dict[str, dict[str, list[float]]]:
    return read_yaml(path or config_dir() / "paper_table1.yaml")


def markdown_table(cells: Sequence[CellResult], scenarios: Sequence[Scenario],
                   configs: Sequence[EvaluatedConfiguration], paper: dict) -> str:
    """Rows: scenarios; columns: configurations; cells: `s / r` ours, then the paper's."""
    by_key = {(c.scenario, c.configuration): c for c in cells}
    header = "| scenario | " + " | ".join(c.label for c in configs) + " |"
    lines = [header, "|" + " --- |" * (len(configs) + 1)]
    for scenario in scenarios:
        row = [scenario.label]
        for config in configs:
            cell = by_key.get((scenario.name, config.name))
            text = "" if cell is None else f"{cell.s:.3f}{_interval(cell.s_ci)} / {cell.r:.2f}"
            quoted = paper.get(scenario.name, {}).get(config.name)
            if quoted:
                text += f" (paper {quoted[0]:.3g} / {quoted[1]:.3g})"
            row.append(text or "-")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def details_table(cells: Sequence[CellResult]) -> str:
    columns = ["scenario", "configuration", "s", "s_ci", "final_score", "success_rate",
               "success_ci", "r", "r_ci", "r_body", "r_body_outside_starts", "path_crossings",
               "starts_inside", "interventions", "intervention_px", "standstill_steps",
               "ms_per_chunk"]
    if any(cell.contact_steps is not None for cell in cells):  # zones that move
        columns[-1:-1] = ["contact_steps", "avoidable_contact_steps",
                          "unavoidable_contact_steps", "min_separation", "mean_min_separation"]
    lines = ["| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]
    for cell in cells:
        values = cell.to_dict()
        lines.append("| " + " | ".join(_format(values.get(c)) for c in columns) + " |")
    return "\n".join(lines)


def _format(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, (tuple, list)):
        return _interval(value).strip()
    return f"{value:.3f}" if isinstance(value, float) else str(value)


def _interval(ci: Sequence[float] | None) -> str:
    """' [low, high]' of a 95% interval; nothing for cells reported before intervals were."""
    return "" if ci is None else f" [{ci[0]:.3f}, {ci[1]:.3f}]"


def batch_times(cells: Sequence[CellResult]) -> str:
    """Wall time of each batched run the cells came from (configurations sharing a sampler run
    as one batch), kept with the cells so a report rebuilt with --reuse still shows them."""
    batches: dict[tuple, list[CellResult]] = {}
    for cell in cells:
        if cell.batch_wall_s is not None:
            batches.setdefault((cell.batch, cell.batch_wall_s), []).append(cell)
    lines = [f"- {len(group)} cells ({', '.join(dict.fromkeys(c.configuration for c in group))})"
             f", one batch of {episodes} episodes: {wall:.0f} s"
             for (episodes, wall), group in batches.items()]
    return "Batched runs:\n\n" + "\n".join(lines) if lines else ""


def write_tables(cells: Sequence[CellResult], output: Path) -> None:
    rows = [c.to_dict() for c in cells]
    (output / "results.json").write_text(json.dumps(rows, indent=2) + "\n")
    flat = [_flat(row) for row in rows]  # an interval as two columns, <name>_low and _high
    with (output / "results.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(dict.fromkeys(k for r in flat for k in r)))
        writer.writeheader()
        writer.writerows(flat)


def _flat(row: dict) -> dict:
    out = {}
    for key, value in row.items():
        if key.endswith("_ci"):
            low, high = value if value is not None else (None, None)
            out[f"{key}_low"], out[f"{key}_high"] = low, high
        else:
            out[key] = value
    return out


def plot_s_against_r(cells: Sequence[CellResult], configs: Sequence[EvaluatedConfiguration],
                     path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4.8))
    markers = "os^vD<>ph*xP"
    for index, config in enumerate(configs):
        mine = [c for c in cells if c.configuration == config.name]
        points = ax.scatter([c.r for c in mine], [c.s for c in mine], label=config.label,
                            marker=markers[index % len(markers)], alpha=0.8)
        with_ci = [c for c in mine if c.s_ci is not None and c.r_ci is not None]
        if with_ci:  # 95% intervals: bootstrap over episodes
            ax.errorbar([c.r for c in with_ci], [c.s for c in with_ci],
                        xerr=[[c.r - c.r_ci[0] for c in with_ci],
                              [c.r_ci[1] - c.r for c in with_ci]],
                        yerr=[[c.s - c.s_ci[0] for c in with_ci],
                              [c.s_ci[1] - c.s for c in with_ci]],
                        fmt="none", ecolor=points.get_facecolor()[0], alpha=0.4,
                        linewidth=0.8)
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set(xlabel="r: executed steps commanded inside a zone (mean per episode)",
           ylabel="s: mean best score",
           title="Score against violations, every cell (bars: 95% intervals)")
    ax.grid(alpha=0.3)
    # Beside the axes: most cells with r = 0 sit at the left edge, where a legend would hide them.
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_frames(log: RolloutLog, episode: int, scenario: Scenario, path: Path, title: str,
                frames: int = 6) -> None:
    """A strip like the paper's Fig. 1: zone red, pusher blue, T grey, goal green."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim_bridge import render_scene

    n_steps = log.commanded.shape[1]
    picks = np.linspace(0, n_steps, frames).astype(int)
    fig, axes = plt.subplots(1, frames, figsize=(2.2 * frames, 2.6))
    for ax, step in zip(axes, picks):
        setpoint = log.commanded[episode, min(step, n_steps - 1)]
        image = render_scene(log.states[episode, step], size=256,
                             zones=scenario.polygons_at(step), setpoint=setpoint)
        ax.imshow(image)
        ax.set_title(f"step {step}, score {log.scores[episode, max(step - 1, 0)]:.2f}",
                     fontsize=8)
        ax.axis("off")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
