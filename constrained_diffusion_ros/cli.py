"""What every command of the package does with a bad file or argument: one line on stderr naming
it, exit code 2, and the traceback only when asked for with --debug."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, NoReturn

from msg_schemas.text import one_line

if TYPE_CHECKING:
    import torch

USAGE_ERROR = 2  # argparse's exit code for a bad argument; ours for any bad input


class ArgumentParser(argparse.ArgumentParser):
    """argparse with the package's conventions: defaults shown in --help, a --debug flag, and a
    bad argument reported in one line (argparse prints the whole usage first)."""

    def __init__(self, prog: str, description: str) -> None:
        super().__init__(prog=prog, description=description,
                         formatter_class=argparse.ArgumentDefaultsHelpFormatter)
        self.add_argument("--debug", action="store_true",
                          help="show the traceback of an error instead of one line")

    def error(self, message: str) -> NoReturn:
        self.exit(USAGE_ERROR, f"{self.prog}: error: {one_line(message)} (see --help)\n")


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} is not a positive integer")
    return value


def run_command(run: Callable[[argparse.Namespace], int], args: argparse.Namespace,
                prog: str) -> int:
    """`run(args)`, with any error (a bad file, a bad value, a full disk) reported in one line
    and exit code 2. Errors the package does not expect say so, so that they get reported."""
    try:
        return run(args)
    except Exception as error:
        if args.debug:
            raise
        known = isinstance(error, (ValueError, OSError))
        print(f"{prog}: error: " + (one_line(error) if known else
              f"unexpected {type(error).__name__}: {one_line(error)} (--debug shows where)"),
              file=sys.stderr)
        return USAGE_ERROR


def add_compute_arguments(parser: argparse.ArgumentParser) -> None:
    """--device, --runtime and --threads, alike in every command that runs the network."""
    parser.add_argument("--device", default="cpu",
                        help="where the network runs: cpu, cuda or cuda:N")
    parser.add_argument("--runtime", default="torch", choices=["torch", "onnxruntime"],
                        help="what runs the network: torch, or ONNX Runtime (CPU; faster at "
                             "batch 1, slower at large batches; scripts/bench_planning.py)")
    parser.add_argument("--threads", type=positive_int, default=os.cpu_count() or 1,
                        help="torch threads (default: this machine's cores; fewer if other "
                             "work runs beside it)")


def load_policy_for(args: argparse.Namespace):
    """The policy of `--model`, on `--device` with `--threads`, its network on `--runtime`
    (torch, with one log line, where that runtime cannot run it)."""
    from constrained_diffusion_ros.policy.inference import use_runtime
    from constrained_diffusion_ros.policy.weights import load_policy

    policy = load_policy(args.model, use_compute_arguments(args))
    use_runtime(policy, args.runtime)
    return policy


def use_compute_arguments(args: argparse.Namespace) -> torch.device:
    """Sets the torch threads asked for; the device, checked (ValueError in one line)."""
    import torch  # here, so that commands which never run the network start without it

    from constrained_diffusion_ros.policy.device import resolve_device

    torch.set_num_threads(args.threads)
    return resolve_device(args.device)
