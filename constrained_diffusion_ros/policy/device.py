"""Which torch device the network runs on: CPU by default, a GPU when asked and present.

Only the network moves: zones, hooks and the simulator stay on the CPU, and the sampling noise is
drawn on the CPU too, so a seed gives the same noise on every device.
"""

from __future__ import annotations

import torch

DEVICES = "cpu, cuda or cuda:N"


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
