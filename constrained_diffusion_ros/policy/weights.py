"""Policy weights as safetensors plus a JSON config: loading never unpickles anything."""

from __future__ import annotations

import json
from pathlib import Path

from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from constrained_diffusion_ros.policy.config import PolicyConfig
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy

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
    path = Path(directory) / CONFIG_FILE
    if not path.is_file():
        raise ValueError(f"no {CONFIG_FILE} in {directory}: not a policy directory")
    try:
        return PolicyConfig.from_dict(json.loads(path.read_text())["policy"])
    except (json.JSONDecodeError, KeyError, TypeError) as error:
        raise ValueError(f"{path} is not a valid policy config: {error}") from error


def load_policy(directory: str | Path) -> DiffusionPolicy:
    """Rebuilds the network from the JSON config and fills it; a mismatch is a ValueError."""
    config = read_config(directory)
    policy = DiffusionPolicy(config)
    path = Path(directory) / WEIGHTS_FILE
    try:
        tensors = load_file(str(path))
    except (FileNotFoundError, SafetensorError, OSError) as error:
        raise ValueError(f"cannot read weights {path}: {error}") from error
    expected = policy.unet.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    wrong_shape = [k for k in expected if k in tensors and tensors[k].shape != expected[k].shape]
    if missing or unexpected or wrong_shape:
        raise ValueError(
            f"weights in {path} do not match its config: {len(missing)} missing, "
            f"{len(unexpected)} unexpected, {len(wrong_shape)} of the wrong shape "
            f"(first: {(missing + unexpected + wrong_shape)[:3]})"
        )
    broken = [name for name, tensor in tensors.items()
              if tensor.is_floating_point() and not bool(tensor.isfinite().all())]
    if broken:
        raise ValueError(f"weights in {path} hold NaN or inf ({len(broken)} tensors, first: "
                         f"{broken[0]}): a diverged training run?")
    policy.unet.load_state_dict(tensors)
    return policy.eval().requires_grad_(False)

