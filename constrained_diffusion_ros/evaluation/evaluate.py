"""Reproduce the paper's Table I and our extensions in one command: `evaluate --help`.

Configurations that share a sampler run their scenarios x seeds in units: blocks of --unit
consecutive seeds, each one batch of episodes with its own noise seed (25 seeded scenes from seed
100000, 200 action steps each: one unit per sampler group); a configuration that ignores the
zones runs its seeds once and is scored against every scenario. The units run here one after
the other, or with --ray as Ray tasks, with the same episodes either way. Writes table.md,
results.csv/json, s_vs_r.png and frames.png to the output directory and prints the table;
Ctrl-C writes the cells whose units all finished and exits 130.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from contextlib import closing
from pathlib import Path
from typing import TYPE_CHECKING

from constrained_diffusion_ros.cli import (
    ArgumentParser,
    add_compute_arguments,
    load_policy_for,
    positive_int,
    run_command,
)
from constrained_diffusion_ros.evaluation import distributed
from constrained_diffusion_ros.paths import config_dir, default_model_dir

if TYPE_CHECKING:  # torch and shapely come with it: imported once the arguments are read
    from constrained_diffusion_ros.evaluation.runner import CellResult

INTERRUPTED = 130  # a shell's code for a command stopped by Ctrl-C

DEFAULT_FIGURE = ("center_0.2", "r_g10_p_safe")


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser("evaluate", __doc__.split("\n\n")[0])
    parser.add_argument("--model", default=str(default_model_dir()), help="policy directory")
    parser.add_argument("--scenarios", nargs="+", default=["all"],
                        help="scenario names from config/scenarios.yaml, 'paper', 'moving' "
                             "(the zones that move: hands) or 'all'")
    parser.add_argument("--configs", nargs="+", default=["all"],
                        help="configuration names from config/configurations.yaml, 'paper' "
                             "or 'all'")
    parser.add_argument("--episodes", type=positive_int, default=25,
                        help="seeds from --first-seed on")
    parser.add_argument("--first-seed", type=int, default=100000)
    parser.add_argument("--steps", type=positive_int, default=200,
                        help="action steps per episode")
    parser.add_argument("--output", default="docs/evaluation", help="report directory")
    parser.add_argument("--figure", nargs=2, default=None, metavar=("SCENARIO", "CONFIG"),
                        help="cell drawn in frames.png (must be one this run evaluates); "
                             f"default {' '.join(DEFAULT_FIGURE)} when evaluated")
    parser.add_argument("--reuse", action="store_true",
                        help="keep the cells already in OUTPUT/results.json and run only the "
                             "missing ones (after adding a configuration or a scenario, say)")
    add_compute_arguments(parser)
    distributed.add_ray_arguments(parser)
    parser.add_argument("--config-dir", default=str(config_dir()),
                        help="directory with scenarios.yaml, configurations.yaml and "
                             "evaluation.yaml (the report's labels)")
    return parser


def select(available: dict, wanted: list[str], kind: str) -> list:
    if wanted == ["all"]:
        return list(available.values())
    if wanted == ["paper"]:
        return [item for item in available.values() if item.paper]
    if wanted == ["moving"]:  # scenarios whose zones move (hands)
        return [item for item in available.values() if getattr(item, "moving", False)]
    unknown = [name for name in wanted if name not in available]
    if unknown:
        raise ValueError(f"unknown {kind} {unknown}; known: {', '.join(available)}")
    return [available[name] for name in wanted]


def reusable_cells(path: Path, episodes: int) -> dict[tuple[str, str], CellResult]:
    """The cells of an earlier report run on `episodes` episodes and with intervals, by
    (scenario, configuration); ValueError in one line if the file is not a report."""
    from constrained_diffusion_ros.evaluation.runner import CellResult

    try:
        rows = json.loads(path.read_text())
        cells = {(r["scenario"], r["configuration"]): CellResult(**r) for r in rows}
    except (OSError, ValueError, TypeError, KeyError) as error:
        raise ValueError(f"{path} is not a report to reuse ({type(error).__name__}: {error}); "
                         f"move it away or leave out --reuse") from None
    return {key: cell for key, cell in cells.items()  # without intervals: run again
            if cell.s_ci is not None and cell.episodes == episodes}


def figure_cell(args: argparse.Namespace, evaluated: set[tuple[str, str]]) -> tuple | None:
    """The (scenario, configuration) drawn in frames.png: the one asked for, which must be run
    here, or the default one when it is."""
    if args.figure is None:
        return DEFAULT_FIGURE if DEFAULT_FIGURE in evaluated else None
    if tuple(args.figure) not in evaluated:
        raise ValueError(f"--figure {' '.join(args.figure)}: not a cell this run evaluates "
                         f"(scenario and configuration must both be selected, and the "
                         f"configuration must run on that scenario)")
    return tuple(args.figure)


def run(args: argparse.Namespace) -> int:
    import torch
    from tqdm import tqdm

    from constrained_diffusion_ros.evaluation import report
    from constrained_diffusion_ros.evaluation.evaluated_configurations import load_evaluated
    from constrained_diffusion_ros.evaluation.scenarios import load_scenarios

    directory = Path(args.config_dir)
    if not directory.is_dir():
        raise ValueError(f"--config-dir {directory}: no such directory")
    if args.ray:  # arguments that do not go together are said before any work
        distributed.cluster_address(args)
    scenarios = select(load_scenarios(directory / "scenarios.yaml"), args.scenarios, "scenarios")
    configs = select(load_evaluated(directory), args.configs, "configurations")
    chosen_of = {c.name: [s for s in scenarios if s.paper or c.scenarios == "all"]
                 for c in configs}
    for config in configs:  # a cell asked for and not run is said, not left as a bare "-"
        skipped = [s.name for s in scenarios if s not in chosen_of[config.name]]
        if skipped:
            print(f"{config.name} runs on the paper's scenarios only (config/evaluation.yaml): "
                  f"not on {', '.join(skipped)}", file=sys.stderr)
    drawn = figure_cell(args, {(s.name, c) for c, chosen in chosen_of.items() for s in chosen})
    policy = load_policy_for(args)  # here too with --ray: a bad model is said before a cluster
    seeds = list(range(args.first_seed, args.first_seed + args.episodes))
    output = Path(args.output)
    try:
        output.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ValueError(f"cannot write the report to {output}: {error.strerror}") from None
    previous = {}
    if args.reuse and (output / "results.json").is_file():
        previous = reusable_cells(output / "results.json", args.episodes)
        if args.figure:  # a figure asked for is drawn: its cell runs again
            previous.pop(drawn, None)
    cells, started, figure, reused = [], time.monotonic(), None, 0
    pending: dict[tuple, list] = {}  # sampler key -> [(configuration, its scenarios)]
    for config in configs:
        chosen = chosen_of[config.name]
        kept = [previous[key] for s in chosen if (key := (s.name, config.name)) in previous]
        cells, reused = cells + kept, reused + len(kept)
        missing = [s for s in chosen if (s.name, config.name) not in previous]
        if missing:
            pending.setdefault(config.config.sampler_key, []).append((config, missing))
    named = list(pending.values())  # the sampler groups, with the configurations' names
    groups = [distributed.Group([c.config for c, _ in group], [chosen for _, chosen in group])
              for group in named]
    where = (f"as Ray tasks of {args.ray_threads} thread(s), units of {args.unit} seeds"
             if args.ray else
             f"on {torch.get_num_threads()} threads, units of {args.unit} seeds")
    interrupted = False
    try:
        with closing(distributed.group_results(policy, groups, seeds, args.steps, args)
                     ) as results:
            for index, (done, log, first_rows) in results:
                group = named[index]
                cells += done
                tqdm.write(f"{', '.join(c.name for c, _ in group)}: {len(done)} cells x "
                           f"{len(seeds)} episodes, units of up to {done[0].batch} episodes, "
                           f"{done[0].batch_wall_s:.0f} s of compute")
                if drawn in first_rows:
                    scenario = next(s for s in scenarios if s.name == drawn[0])
                    config = next(c for c, _ in group if c.name == drawn[1])
                    figure = (log, first_rows[drawn], scenario, config)
    except KeyboardInterrupt:
        interrupted = True
    wall = time.monotonic() - started
    if interrupted:
        print(f"evaluate: interrupted; {len(cells)} finished cells "
              + (f"written to {output}" if cells else "(nothing written)"), file=sys.stderr)
        if not cells:
            return INTERRUPTED
    order = {(s.name, c.name): (i, j) for i, c in enumerate(configs)
             for j, s in enumerate(scenarios)}
    cells.sort(key=lambda cell: order[(cell.scenario, cell.configuration)])
    paper_cells = sum(1 for c in cells if c.scenario in {s.name for s in scenarios if s.paper}
                      and c.configuration in {k.name for k in configs if k.paper})
    table = report.markdown_table(cells, scenarios, configs, report.load_paper_table())
    report.write_tables(cells, output)
    report.plot_s_against_r(cells, configs, output / "s_vs_r.png")
    if figure:
        log, episode, scenario, config = figure
        report.plot_frames(log, episode, scenario, output / "frames.png",
                           f"{config.label} on {scenario.label}, seed {seeds[0]}")
    summary = (f"{len(cells)} cells ({paper_cells} of the paper's), {len(seeds)} episodes "
               f"each, {args.steps} steps; this run: {wall:.0f} s {where} for "
               f"{len(cells) - reused} cells"
               + (f" ({reused} reused from results.json)" if reused else "")
               + (" (interrupted: the cells whose units all finished)" if interrupted else ""))
    (output / "table.md").write_text(
        f"# Evaluation\n\n{summary}\n\n{report.batch_times(cells)}\n\n"
        f"Cells: `s / r` (ours), then the paper's Table I value.\n\n"
        f"{table}\n\n## Every metric\n\n{report.details_table(cells)}\n")
    print(table)
    print(summary)
    return INTERRUPTED if interrupted else 0


def main(argv: list[str] | None = None) -> int:
    return run_command(run, build_parser().parse_args(argv), "evaluate")


if __name__ == "__main__":
    sys.exit(main())
