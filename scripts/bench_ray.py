"""Episodes per second of one study run here and as Ray tasks on a local cluster of 1 and 2
workers, in one run, with Ray's overhead per task: `python scripts/bench_ray.py --help`.

Here: the units one after the other in this process (after a warm-up unit), with 1 torch thread
and with as many as Ray workers are compared against. Ray: a local cluster of N CPUs, its
workers started (a warm-up unit each) before the clock runs, tasks of 1 thread; the start of the
cluster is printed apart. Overhead per task: the Ray run's wall time less the units' own
compute, over the tasks, with 1 worker (nothing runs in parallel there). Every run's figures are
checked equal to those of the 1-thread run here.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from constrained_diffusion_ros.cli import positive_int
from constrained_diffusion_ros.evaluation import distributed
from constrained_diffusion_ros.paths import config_dir, default_model_dir

TIMING = ("ms_per_chunk", "ms_per_call", "batch_wall_s")


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--model", default=str(default_model_dir()))
    parser.add_argument("--configs", nargs="+", default=["ddim10_r_g10_p_safe"])
    parser.add_argument("--scenarios", nargs="+", default=["center_0.2", "left_0.1"])
    parser.add_argument("--episodes", type=positive_int, default=40, help="seeds")
    parser.add_argument("--steps", type=positive_int, default=100)
    parser.add_argument("--unit", type=positive_int, default=10, help="seeds per unit")
    parser.add_argument("--workers", type=positive_int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=positive_int, default=2,
                        help="runs of each, the fastest kept (other work on the machine "
                             "slows some)")
    return parser.parse_args()


def study(args: argparse.Namespace, ray: bool, threads: int) -> argparse.Namespace:
    """The arguments `distributed.group_results` reads."""
    return argparse.Namespace(model=args.model, device="cpu", runtime="torch",
                              unit=args.unit, ray=distributed.LOCAL_CLUSTER if ray else None,
                              ray_workers=1, ray_threads=threads)


def timed(policy, groups, seeds, steps, namespace, repeats: int
          ) -> tuple[float, float, int, list]:
    """(wall s, the units' own compute s, units, figures) of the fastest of `repeats` runs of
    the study."""
    return min((once(policy, groups, seeds, steps, namespace) for _ in range(repeats)),
               key=lambda result: result[0])


def once(policy, groups, seeds, steps, namespace) -> tuple[float, float, int, list]:
    started = time.monotonic()
    cells = [cell for _, (done, _, _) in
             distributed.group_results(policy, groups, seeds, steps, namespace)
             for cell in done]
    wall = time.monotonic() - started
    compute = sum(wall for _, wall in {(c.batch, c.batch_wall_s) for c in cells})  # per group
    units = len(groups) * -(-len(seeds) // namespace.unit)
    figures = [{k: v for k, v in c.to_dict().items() if k not in TIMING} for c in cells]
    return wall, compute, units, figures


def main() -> int:
    args = parse()
    import ray
    import torch

    from constrained_diffusion_ros.evaluation.evaluated_configurations import load_evaluated
    from constrained_diffusion_ros.evaluation.runner import episodes_per_seed
    from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
    from constrained_diffusion_ros.policy.weights import load_policy

    scenarios = load_scenarios(config_dir() / "scenarios.yaml")
    known = load_evaluated(config_dir())
    grouped: dict[tuple, distributed.Group] = {}
    for name in args.configs:
        config = known[name].config
        group = grouped.setdefault(config.sampler_key, distributed.Group([], []))
        group.configs.append(config)
        group.scenario_lists.append([scenarios[s] for s in args.scenarios])
    groups = list(grouped.values())
    seeds = list(range(100000, 100000 + args.episodes))
    episodes = len(seeds) * sum(episodes_per_seed(g.configs, g.scenario_lists) for g in groups)
    policy = load_policy(args.model)
    print(f"{episodes} episodes ({', '.join(args.configs)} on {', '.join(args.scenarios)}, "
          f"{args.episodes} seeds, {args.steps} steps) in units of {args.unit} seeds; "
          f"{os.cpu_count()} cores; the fastest of {args.repeats} runs each", flush=True)

    rows, reference = [], None
    warm_here = argparse.Namespace(**{**vars(study(args, False, 1)), "unit": 1})
    list(distributed.group_results(policy, groups[:1], seeds[:1], 1, warm_here))
    for threads in sorted({1, *args.workers}):
        torch.set_num_threads(threads)
        wall, _, _, figures = timed(policy, groups, seeds, args.steps,
                                    study(args, False, threads), args.repeats)
        reference = reference or figures
        same = "yes" if figures == reference else "no (other thread count, other rounding)"
        rows.append((f"here, {threads} thread(s)", wall, same, ""))
    torch.set_num_threads(1)
    for workers in args.workers:
        started = time.monotonic()
        ray.init(address="local", num_cpus=workers, include_dashboard=False,
                 logging_level="ERROR")
        warm = study(args, True, 1)
        list(distributed.group_results(policy, groups[:1], seeds[:workers], 1,
                                       argparse.Namespace(**{**vars(warm), "unit": 1})))
        start_s = time.monotonic() - started
        wall, compute, units, figures = timed(policy, groups, seeds, args.steps, warm,
                                              args.repeats)
        ray.shutdown()
        note = f"cluster start and warm-up {start_s:.1f} s"
        if workers == 1:
            note += f"; overhead per task {1000 * (wall - compute) / units:.0f} ms"
        rows.append((f"Ray, {workers} worker(s)", wall, "yes" if figures == reference else "NO",
                     note))
    print("\n| run | wall s | episodes/s | figures as here, 1 thread | notes |\n"
          "|---|---|---|---|---|")
    for name, wall, same, note in rows:
        print(f"| {name} | {wall:.1f} | {episodes / wall:.2f} | {same} | {note} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
