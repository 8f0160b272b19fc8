"""The evaluation's units (`runner.Unit`) as Ray tasks: `evaluate --ray [ADDRESS]`.

A unit's episodes depend on its seeds and the study only, so a unit run here, on one worker or
on another gives the same figures, and a unit that a dead worker left unfinished is simply run
again (Ray's task retries) and counted once (results are kept by unit). The policy travels as
its files (safetensors and JSON config) in the object store: put once, copied to each node once,
rebuilt once per worker process and study. The code does not travel: each worker machine has
the package installed (docs/cluster.md). Ray is imported inside the functions that use
it: a run without --ray never imports it.
"""

from __future__ import annotations

import argparse
import os
import socket
import tempfile
from collections import Counter
from collections.abc import Iterator, Sequence
from contextlib import closing, contextmanager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from constrained_diffusion_ros.cli import positive_int
from msg_schemas.text import one_line

if TYPE_CHECKING:
    from constrained_diffusion_ros.evaluation.runner import Unit, UnitRun
    from constrained_diffusion_ros.evaluation.scenarios import Scenario
    from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
    from constrained_diffusion_ros.policy.modeling import DiffusionPolicy

TASK_RETRIES = 3  # runs of a unit after the first when its worker dies
REACH_TIMEOUT_S = 5.0  # a cluster that does not answer a TCP connect by then is unreachable
RAY_CLIENT_PORT = 10001  # the defaults of `ray start --head`: client server and GCS
GCS_PORT = 6379
LOCAL_CLUSTER = "local"  # what `--ray` without an address stands for
# runner.DEFAULT_UNIT_SIZE written out: runner imports torch, and --help shows it before any of
# it (test/unit/test_help_imports.py keeps the two equal).
DEFAULT_UNIT_SIZE = 25


@dataclass(frozen=True)
class Group:
    """Configurations that share a sampler, each on its scenarios, with one inference delay
    and handover (`ChunkLoop`): what each unit runs a block of seeds of."""

    configs: list[ConstraintConfig]
    scenario_lists: list[list[Scenario]]
    delay: int = 0
    handover: str = "sync"


@dataclass(frozen=True)
class Study:
    """What every unit of a study shares, put in the object store once: the policy's files,
    how to run it, and the groups."""

    model_files: dict[str, bytes]  # file name -> contents: what load_policy reads
    device: str
    runtime: str
    threads: int  # torch threads per task
    groups: list[Group]
    n_steps: int


def model_files(directory: str | Path) -> dict[str, bytes]:
    """The files of a policy directory that `load_policy` reads, by name."""
    from constrained_diffusion_ros.policy.weights import CONFIG_FILE, WEIGHTS_FILE

    return {name: (Path(directory) / name).read_bytes() for name in (CONFIG_FILE, WEIGHTS_FILE)}


def rebuild_policy(study: Study) -> DiffusionPolicy:
    """The study's policy, loaded from its files as from a directory (never unpickled)."""
    from constrained_diffusion_ros.policy.inference import use_runtime
    from constrained_diffusion_ros.policy.weights import load_policy

    with tempfile.TemporaryDirectory(prefix="policy-") as directory:
        for name, contents in study.model_files.items():
            (Path(directory) / name).write_bytes(contents)
        policy = load_policy(directory, study.device)
    use_runtime(policy, study.runtime)
    return policy


# In a worker process: the study it last ran and its rebuilt policy, by the study's object id.
_worker_study: dict[str, tuple[Study, DiffusionPolicy]] = {}


def run_unit_task(boxed_study: list[Any], unit: Unit) -> UnitRun:
    """A Ray task: one unit of the study whose ObjectRef comes boxed in a list (so that Ray
    passes the reference, not the value, and a worker fetches and rebuilds it only once)."""
    import ray
    import torch

    (reference,) = boxed_study
    if reference.hex() not in _worker_study:
        study = ray.get(reference)
        torch.set_num_threads(study.threads)
        _worker_study.clear()
        _worker_study[reference.hex()] = (study, rebuild_policy(study))
    study, policy = _worker_study[reference.hex()]
    return run_group_unit(policy, study.groups[unit.group], unit, study.n_steps)


def run_group_unit(policy: DiffusionPolicy, group: Group, unit: Unit, n_steps: int,
                   progress: bool = False) -> UnitRun:
    """One unit of `group`, here."""
    from constrained_diffusion_ros.evaluation.runner import run_unit

    return run_unit(policy, group.configs, group.scenario_lists, unit.seeds, n_steps,
                    unit.noise_seed, progress, group.delay, group.handover)


def check_reachable(address: str) -> None:
    """ValueError in one line unless `address` (host:port or ray://host:port; 'auto' is Ray's
    to find) answers a TCP connect within REACH_TIMEOUT_S: Ray itself waits minutes."""
    if address == "auto":
        return
    client = address.startswith("ray://")
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        host, port = address.removeprefix("ray://"), str(RAY_CLIENT_PORT if client else GCS_PORT)
    try:
        socket.create_connection((host, int(port)), timeout=REACH_TIMEOUT_S).close()
    except OSError as error:
        raise ValueError(f"cannot reach the Ray cluster at {address}: {one_line(error)}"
                         ) from None


@contextmanager
def ray_session(address: str | None, workers: int) -> Iterator[None]:
    """Connected to the cluster at `address` ('auto', host:port, ray://host:port), or to a
    local one of `workers` CPUs started for the run (None); when Ray is already initialised in
    this process (a notebook, a test's cluster), that connection is used and left as found.
    ValueError in one line when the cluster cannot be reached."""
    import ray

    if address is not None:
        check_reachable(address)
    if ray.is_initialized():
        yield
        return
    try:
        if address is None:
            ray.init(address="local", num_cpus=workers, include_dashboard=False,
                     logging_level="ERROR")
        else:
            ray.init(address=address, logging_level="ERROR")
    except (ConnectionError, RuntimeError, ValueError) as error:
        raise ValueError(f"cannot reach the Ray cluster at {address}: {one_line(error)}"
                         ) from None
    try:
        yield
    finally:
        ray.shutdown()


def unit_runs(study: Study, units: Sequence[Unit]) -> Iterator[tuple[Unit, UnitRun]]:
    """Each unit as a Ray task on the connected cluster (`ray_session`), (unit, run) as they
    finish. A task whose worker dies is retried up to TASK_RETRIES times; leaving early
    (Ctrl-C) cancels the tasks not yet done."""
    import ray

    task = ray.remote(run_unit_task).options(
        num_cpus=study.threads, max_retries=TASK_RETRIES,
        runtime_env={"env_vars": {"OMP_NUM_THREADS": str(study.threads)}})
    boxed = [ray.put(study)]
    pending = {task.remote(boxed, unit): unit for unit in units}
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for reference in done:
                unit = pending.pop(reference)
                try:
                    run = ray.get(reference)
                except ray.exceptions.RayTaskError as error:  # the unit's own error, as here
                    raise error.cause from None
                yield unit, run
    finally:
        for reference in pending:
            ray.cancel(reference)  # not force: killing a worker mid-reply crashed the driver


def group_results(policy: DiffusionPolicy, groups: Sequence[Group], seeds: Sequence[int],
                  n_steps: int, args: argparse.Namespace) -> Iterator[tuple[int, tuple]]:
    """Every group on `seeds`, in units of `args.unit` seeds, run here one after the other or
    with `args.ray` as Ray tasks, with a progress bar over episodes; yields (group index,
    `runner.assemble`'s cells, log and first rows) as soon as all of a group's units are in.
    Closing it early (Ctrl-C) cancels what Ray has not finished."""
    from tqdm import tqdm

    from constrained_diffusion_ros.evaluation.runner import (
        assemble,
        episodes_per_seed,
        study_units,
    )

    units = study_units(len(groups), seeds, args.unit)
    per_seed = [episodes_per_seed(group.configs, group.scenario_lists) for group in groups]
    if not units:  # every cell reused: no cluster to start
        return
    if args.ray:
        study = Study(model_files(args.model), getattr(args, "device", "cpu"),
                      getattr(args, "runtime", "torch"), args.ray_threads, list(groups),
                      n_steps)
        session = ray_session(cluster_address(args), args.ray_workers)
    else:
        session = nullcontext()
    runs: dict[tuple[int, int], UnitRun] = {}  # by unit: a unit run twice is kept once
    left = Counter(unit.group for unit in units)
    with session, tqdm(total=sum(len(u.seeds) * per_seed[u.group] for u in units),
                       desc="episodes", unit="episode") as bar:
        stream = (unit_runs(study, units) if args.ray else
                  ((unit, run_group_unit(policy, groups[unit.group], unit, n_steps, True))
                   for unit in units))
        with closing(stream):
            for unit, result in stream:
                if unit.key in runs:  # cannot happen (one task per unit); never counted twice
                    continue
                runs[unit.key] = result
                bar.update(len(unit.seeds) * per_seed[unit.group])
                left[unit.group] -= 1
                if not left[unit.group]:
                    group = groups[unit.group]
                    own = [runs[u.key] for u in units if u.group == unit.group]
                    yield unit.group, assemble(group.configs, group.scenario_lists, own)


def add_ray_arguments(parser: argparse.ArgumentParser) -> None:
    """--unit, --ray, --ray-workers and --ray-threads, alike in every command that runs units."""
    parser.add_argument("--unit", type=positive_int, default=DEFAULT_UNIT_SIZE, metavar="SEEDS",
                        help="seeds per unit of work: each sampler group runs its seeds in "
                             "blocks of this many, one batch and one noise seed each, here or "
                             "as one Ray task; part of what defines the episodes, like the "
                             "seeds (the same for any worker count)")
    parser.add_argument("--ray", nargs="?", const=LOCAL_CLUSTER, default=None, metavar="ADDRESS",
                        help="run the units as Ray tasks: on the cluster at ADDRESS ('auto', "
                             "host:port or ray://host:port), or without ADDRESS on a local "
                             "cluster started for the run (docs/cluster.md)")
    parser.add_argument("--ray-workers", type=positive_int, default=os.cpu_count() or 1,
                        help="CPUs of the local cluster that --ray without ADDRESS starts")
    parser.add_argument("--ray-threads", type=positive_int, default=1,
                        help="torch threads of each Ray task (and the CPUs it asks Ray for)")


def cluster_address(args: argparse.Namespace) -> str | None:
    """The address of a --ray run, None for a local cluster started for the run; ValueError
    for arguments that do not go together."""
    if getattr(args, "device", "cpu") != "cpu":
        raise ValueError(f"--ray runs the network on the workers' CPUs, not --device "
                         f"{args.device}")
    return None if args.ray == LOCAL_CLUSTER else args.ray
