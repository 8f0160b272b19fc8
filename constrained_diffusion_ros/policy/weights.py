"""Policy weights as safetensors plus a JSON config: loading never unpickles anything."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from constrained_diffusion_ros.policy.device import resolve_device
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy, build_unet
from constrained_diffusion_ros.policy.policy_config import (
    MAX_CONFIG_BYTES,
    PolicyConfig,
    read_text_file,
    regular_file,
)

WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"


def save_policy(policy: DiffusionPolicy, directory: str | Path, extra: dict | None = None) -> Path:
    """Writes `model.safetensors` and `config.json` (plus `extra`, e.g. training facts)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    tensors = {name: tensor.detach().contiguous().cpu()
               for name, tensor in policy.unet.state_dict().items()}
    save_file(tensors, str(directory / WEIGHTS_FILE))
    document = {"policy": policy.config.to_dict(), **(extra or {})}
    (directory / CONFIG_FILE).write_text(json.dumps(document, indent=2) + "\n")
    return directory


def read_config(directory: str | Path) -> PolicyConfig:
    """The directory's config.json, checked; any fault (no file, a FIFO, /proc/self/mem behind
    a link, bad JSON, a bad field) is one ValueError line naming the file."""
    path = Path(directory) / CONFIG_FILE
    if not path.exists():
        raise ValueError(f"no {CONFIG_FILE} in {directory}: not a policy directory")
    text = read_text_file(path, MAX_CONFIG_BYTES)
    try:
        return PolicyConfig.from_dict(json.loads(text)["policy"])
    except (KeyError, TypeError, ValueError) as error:  # JSONDecodeError is a ValueError
        raise ValueError(f"{path} is not a valid policy config: {error}") from error
    except RecursionError:  # "[[[[..." nested past the parser's stack
        raise ValueError(f"{path} is not a valid policy config: nested too deeply") from None


def load_policy(directory: str | Path, device: str | torch.device = "cpu") -> DiffusionPolicy:
    """Rebuilds the network from the JSON config and fills it, on `device` (device.py); a
    mismatch is a ValueError, found from the weights file's header and a network without
    storage (meta device) before anything is allocated."""
    target = resolve_device(device)
    config = read_config(directory)
    path = regular_file(Path(directory) / WEIGHTS_FILE)  # a FIFO would block safe_open
    try:
        with safe_open(str(path), "pt") as weights:
            stored = {name: tuple(weights.get_slice(name).get_shape())
                      for name in weights.keys()}  # noqa: SIM118 (a safe_open is no dict)
    except (FileNotFoundError, SafetensorError, OSError) as error:
        raise ValueError(f"cannot read weights {path}: {error}") from error
    with torch.device("meta"):  # the network only: tensor arithmetic on meta tensors (the
        # normalisers') runs torch's Python reference kernels, which import its slow compiler
        expected = {name: tuple(tensor.shape)
                    for name, tensor in build_unet(config).state_dict().items()}
    missing = sorted(set(expected) - set(stored))
    unexpected = sorted(set(stored) - set(expected))
    wrong_shape = [k for k in expected if k in stored and stored[k] != expected[k]]
    if missing or unexpected or wrong_shape:
        raise ValueError(
            f"weights in {path} do not match its config: {len(missing)} missing, "
            f"{len(unexpected)} unexpected, {len(wrong_shape)} of the wrong shape "
            f"(first: {(missing + unexpected + wrong_shape)[:3]})"
        )
    policy = DiffusionPolicy(config)
    try:
        tensors = load_file(str(path))
    except (SafetensorError, OSError) as error:
        raise ValueError(f"cannot read weights {path}: {error}") from error
    broken = [name for name, tensor in tensors.items()
              if tensor.is_floating_point() and not bool(tensor.isfinite().all())]
    if broken:
        raise ValueError(f"weights in {path} hold NaN or inf ({len(broken)} tensors, first: "
                         f"{broken[0]}): a diverged training run?")
    policy.unet.load_state_dict(tensors)
    return policy.to(target).eval().requires_grad_(False)

