"""Which torch device the network runs on: CPU by default, a GPU when asked and present.

Only the network moves: zones, hooks and the simulator stay on the CPU, and the sampling noise is
drawn on the CPU too, so a seed gives the same noise on every device.
"""

from __future__ import annotations

import argparse
import os

import torch

from constrained_diffusion_ros.cli import positive_int

DEVICES = "cpu, cuda or cuda:N"


def add_compute_arguments(parser: argparse.ArgumentParser) -> None:
    """--device and --threads, alike in every command that runs the network."""
    parser.add_argument("--device", default="cpu", help=f"where the network runs: {DEVICES}")
    parser.add_argument("--threads", type=positive_int, default=os.cpu_count() or 1,
                        help="torch threads (default: this machine's cores; fewer if other "
                             "work runs beside it)")


def use_compute_arguments(args: argparse.Namespace) -> torch.device:
    """Sets the torch threads asked for; the device, checked (ValueError in one line)."""
    torch.set_num_threads(args.threads)
    return resolve_device(args.device)


def resolve_device(name: str) -> torch.device:
    """'cpu', 'cuda' or 'cuda:N' -> the torch device; ValueError in one line when it is not
    one or not available here."""
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError):
        raise ValueError(f"unknown device {name!r}; use {DEVICES}") from None
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise ValueError(f"device {name!r} is not supported; use {DEVICES}")
    if not torch.cuda.is_available():
        why = "this torch was built without CUDA" if torch.version.cuda is None \
            else "no CUDA GPU is visible"
        raise ValueError(f"device {name!r} is not available: {why}; use --device cpu (or the "
                         f"node's device:=cpu)")
    if device.index is not None and device.index >= torch.cuda.device_count():
        raise ValueError(f"device {name!r} is not available: {torch.cuda.device_count()} CUDA "
                         f"GPU(s) visible")
    return device
