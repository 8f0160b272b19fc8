"""Where the denoising network runs at inference: torch, or ONNX Runtime.

A robot plans one chunk at a time, and at batch 1 a forward of the U-Net in torch's eager mode
is mostly the overhead of dispatching its few hundred small operations. ONNX Runtime runs the
same network, exported from the loaded weights, with much less of it, and without what depends
only on the step and the observation (the FiLM scales and biases of every block, a third of the
weights): their part from the step is computed once per schedule and their part from the
observation once per plan (`DiffusionPolicy.denoiser`; `scripts/bench_planning.py` measures
both). The graph is exported at load, in memory, and checked against torch on probe inputs
before it is used: a runtime that is missing, cannot run the network, or disagrees with torch
by more than TOLERANCE is not used, and one log line says why (never silently).

The graph is kept in a cache between starts (`cached_graph`), keyed by the weights and the
exporter, and checked like a fresh one. It travels with the policy (a planning process gets it
pickled with the weights); each process opens its own session on first use, with as many
threads as torch has there.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import io
import logging
import math
import os
import warnings
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from constrained_diffusion_ros.policy.modeling import DiffusionPolicy

Runtime = Literal["torch", "onnxruntime"]
RUNTIMES: tuple[Runtime, ...] = ("torch", "onnxruntime")
TOLERANCE = 1e-4  # max abs difference from torch on the probes, in the network's output
OPSET = 17
GRAPH_FORMAT = 3  # what is exported (2: the U-Net with its FiLM given; 3: and its Mish and 1D
# convolutions in the forms ONNX Runtime runs fastest); part of the cache key
LOGGER = logging.getLogger(__name__)


class OnnxDenoiser:
    """The U-Net with its FiLM given (`ConditionalUnet1D.forward_filmed`) as an ONNX Runtime
    session: (sample, films) -> noise, as torch."""

    def __init__(self, graph: bytes) -> None:
        self.graph = graph
        self._session = None

    def __getstate__(self) -> dict:
        return {"graph": self.graph}  # a session is per process: opened again on first use

    def __setstate__(self, state: dict) -> None:
        self.graph, self._session = state["graph"], None

    def __call__(self, sample: Tensor, films: Tensor) -> Tensor:
        if self._session is None:
            self._session = open_session(self.graph, torch.get_num_threads())
        feed = {"sample": sample.detach().cpu().numpy().astype(np.float32, copy=False),
                "films": films.detach().cpu().numpy().astype(np.float32, copy=False)}
        return torch.from_numpy(self._session.run(None, feed)[0])


class ExportedMish(torch.nn.Module):
    """Mish as x tanh(log(1 + exp(x))): the same function, exported as Exp, Add and Log, which
    ONNX Runtime's CPU kernels vectorise, where its Softplus (what torch exports Mish with)
    runs element by element at several times the cost. Large x: exp overflows to inf, the
    log is inf, tanh 1, so x, as Mish; very negative x: 0 from below, as Mish."""

    def forward(self, x: Tensor) -> Tensor:
        return x * torch.tanh(torch.log(torch.exp(x) + 1.0))


class Conv1dAs2d(torch.nn.Module):
    """A 1D (transposed) convolution as a 2D one over a height of 1: the same sums, exported as
    a 2D Conv, which ONNX Runtime on x86 runs in its blocked (NCHWc) layout, where it runs a
    1D Conv with generic kernels at a third more time per forward."""

    def __init__(self, conv: torch.nn.Conv1d | torch.nn.ConvTranspose1d) -> None:
        super().__init__()
        kind = torch.nn.Conv2d if isinstance(conv, torch.nn.Conv1d) else torch.nn.ConvTranspose2d
        extra = {} if kind is torch.nn.Conv2d else {"output_padding": (0, conv.output_padding[0])}
        self.conv = kind(conv.in_channels, conv.out_channels, (1, conv.kernel_size[0]),
                         stride=(1, conv.stride[0]), padding=(0, conv.padding[0]),
                         dilation=(1, conv.dilation[0]), groups=conv.groups,
                         bias=conv.bias is not None, **extra)
        with torch.no_grad():
            self.conv.weight.copy_(conv.weight.unsqueeze(2))
            if conv.bias is not None:
                self.conv.bias.copy_(conv.bias)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(x.unsqueeze(2)).squeeze(2)


class FilmedUnet(torch.nn.Module):
    """What is exported: the U-Net from the noisy sample and one step's FiLM outputs (a copy,
    its Mish layers `ExportedMish`, its 1D convolutions `Conv1dAs2d`)."""

    def __init__(self, unet: torch.nn.Module) -> None:
        super().__init__()
        self.unet = copy.deepcopy(unet)
        for module in self.unet.modules():
            for name, child in module.named_children():
                if isinstance(child, torch.nn.Mish):
                    setattr(module, name, ExportedMish())
                elif type(child) in (torch.nn.Conv1d, torch.nn.ConvTranspose1d):
                    setattr(module, name, Conv1dAs2d(child))

    def forward(self, sample: Tensor, films: Tensor) -> Tensor:
        return self.unet.forward_filmed(sample, films)


def open_session(graph: bytes, threads: int):
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3  # errors only: ORT's own warnings are not ours to print
    # Its pool threads would spin after each run and take the cores from the torch work
    # between forwards (the hooks): with 2 threads a body-safe plan took twice as long.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return onnxruntime.InferenceSession(graph, options, providers=["CPUExecutionProvider"])


def export_onnx(policy: DiffusionPolicy) -> bytes:
    """The policy's U-Net with its FiLM given, as an ONNX graph (batch dimension free)."""
    config = policy.config
    sample = torch.zeros(1, config.horizon, config.action_dim)
    films = policy.unet.films(torch.tensor([0]), torch.zeros(1, config.global_cond_dim))[0]
    buffer = io.BytesIO()
    batch = {0: "batch"}
    with warnings.catch_warnings():  # the exporter's notes on its own deprecation
        warnings.simplefilter("ignore")
        torch.onnx.export(FilmedUnet(policy.unet), (sample, films), buffer,
                          input_names=["sample", "films"], output_names=["noise"],
                          dynamic_axes={"sample": batch, "films": batch, "noise": batch},
                          opset_version=OPSET, dynamo=False)
    return buffer.getvalue()


def disagreement(policy: DiffusionPolicy, denoiser: OnnxDenoiser, seed: int = 0) -> float:
    """Max abs difference between the policy's network on `denoiser` (`DiffusionPolicy.
    denoiser`: its FiLM computed for every step of a plan at once) and torch's own forward,
    over probe inputs: batches of 1 and 3, the first and last timesteps and one between."""
    config, generator = policy.config, torch.Generator().manual_seed(seed)
    steps = torch.tensor([config.num_train_timesteps - 1, config.num_train_timesteps // 2, 0])
    worst = 0.0
    fast, policy.fast = policy.fast, denoiser
    try:
        for batch in (1, 3):
            cond = torch.rand(batch, config.global_cond_dim, generator=generator) * 2 - 1
            with torch.inference_mode():
                network = policy.denoiser(steps, cond)
                for index, step in enumerate(steps):
                    sample = torch.randn(batch, config.horizon, config.action_dim,
                                         generator=generator)
                    expected = policy.unet(sample, step, cond)
                    worst = max(worst, float((network(sample, index) - expected).abs().max()))
    finally:
        policy.fast = fast
    return worst


def cache_dir() -> Path:
    """Where exported graphs are kept between starts ($XDG_CACHE_HOME or ~/.cache)."""
    root = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(root) / "constrained_diffusion_ros" / "onnx"


def cached_graph(policy: DiffusionPolicy, fresh: bool = False) -> bytes:
    """The exported graph, from the cache when these weights were exported before by this
    exporter (exporting costs most of a second at every start), unless `fresh`; a graph
    exported is cached. The check that follows is what vouches for it either way. Without a
    writable cache it is exported every time."""
    key = hashlib.sha256(f"{GRAPH_FORMAT} {torch.__version__} {OPSET}".encode())
    for name, tensor in sorted(policy.unet.state_dict().items()):
        key.update(name.encode())
        key.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    path = cache_dir() / f"{key.hexdigest()[:32]}.onnx"
    if not fresh:
        with contextlib.suppress(OSError):
            return path.read_bytes()
    graph = export_onnx(policy)
    with contextlib.suppress(OSError):
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(f".{os.getpid()}.part")
        partial.write_bytes(graph)
        partial.replace(path)  # whole or not at all, whoever else writes it
    return graph


def use_runtime(policy: DiffusionPolicy, runtime: Runtime) -> Runtime:
    """Runs `policy`'s network on `runtime` from now on; returns the runtime in use, which is
    torch (with one warning in the log) where the one asked for cannot run it faithfully."""
    if runtime not in RUNTIMES:
        raise ValueError(f"runtime must be one of {RUNTIMES}, got {runtime!r}")
    policy.fast = None
    if runtime == "torch":
        return "torch"
    if policy.device.type != "cpu":
        LOGGER.warning("runtime onnxruntime runs on the CPU only; the network stays on torch "
                       "(%s)", policy.device)
        return "torch"
    try:
        try:
            denoiser = OnnxDenoiser(cached_graph(policy))
            worst = disagreement(policy, denoiser)
        except Exception:  # a cached graph gone bad, or one that cannot run: see below
            worst = math.inf
        if not worst <= TOLERANCE:  # exported afresh: a fault then is the runtime's
            denoiser = OnnxDenoiser(cached_graph(policy, fresh=True))
            worst = disagreement(policy, denoiser)
    except Exception as error:  # a missing package, an operator it cannot export or run
        LOGGER.warning("runtime onnxruntime cannot run this network (%s: %s); using torch",
                       type(error).__name__, str(error).splitlines()[0] if str(error) else "")
        return "torch"
    if not worst <= TOLERANCE:
        LOGGER.warning("runtime onnxruntime differs from torch by %.2g (over %g); using torch",
                       worst, TOLERANCE)
        return "torch"
    policy.fast = denoiser
    return "onnxruntime"
