"""Dense layers of the SAC networks: torch's matmul on CUDA, oneDNN's or torch's (MKL) on the CPU.

Why: torch's float32 CPU matmul is MKL's sgemm, and MKL takes its AVX2 code path on AMD CPUs
(its AVX-512 kernels are dispatched on Intel only). oneDNN, which torch also ships and its
compiler uses, runs AVX-512 on both vendors. On a 2-core AMD EPYC (AVX-512) a 256 x 512 x 256
product runs at 98 GFLOP/s per core through MKL and 212 through oneDNN (docs/log/benchmarks.md);
the SAC update is ~2/3 matmul. Same products, another summation order: float32 last bits differ
from `F.linear`, the run stays deterministic on one machine.

Which is faster depends on the machine: on a 2-core Zen 4 EPYC on 2026-12-05 MKL was (16 % at two
threads, even at one), on an Intel Xeon MKL too (issue 43). So the default is "auto": timed per
machine and kept (agents/matmul_backend.py).

Backends (`SACConfig.cpu_matmul`): "onednn" or "torch" (`F.linear` and `torch.baddbmm`, the
reference the tests compare against); "auto" resolves to one of them. On CUDA both are torch's (cuBLAS).
oneDNN is reached through `torch.ops.mkldnn._linear_pointwise`, an operator of torch's own
(inductor's CPU linear), checked once per process against `F.linear`; where it is missing or
disagrees, "onednn" falls back to "torch" with a warning.
"""

from __future__ import annotations

import functools
import warnings

import torch
import torch.nn.functional as F

from vkgrl_newton.agents.sac_config import MATMUL_BACKENDS  # noqa: E402,F401  (the names live with the config)


def _onednn_mm(a: torch.Tensor, b_t: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """a (M, K) @ b_t.T (K, N) + bias (N,) through oneDNN; b_t (N, K) may be a strided view."""
    return torch.ops.mkldnn._linear_pointwise(a, b_t, bias, "none", [], "")


@functools.cache
def onednn_available() -> bool:
    """oneDNN's linear exists in this torch and agrees with F.linear on a small product."""
    try:
        if not torch.backends.mkldnn.is_available():
            return False
        gen = torch.Generator().manual_seed(0)
        a, w, b, c = (torch.randn(s, generator=gen, dtype=torch.float32) for s in ((7, 5), (3, 5), (3,), (7, 3)))
        ok = torch.allclose(_onednn_mm(a, w, b), F.linear(a, w, b), rtol=1e-5, atol=1e-5)
        ok &= torch.allclose(_onednn_mm(a.t(), c.t()), a.t() @ c, rtol=1e-5, atol=1e-5)  # strided operands
    except (RuntimeError, AttributeError, NotImplementedError):  # a torch without it, or a build that rejects it
        return False  # -> resolve_backend warns and uses torch's matmul
    return bool(ok)


def resolve_backend(requested: str, device: torch.device) -> str:
    """The backend that will run: "onednn" only on a CPU where it is available."""
    if requested not in MATMUL_BACKENDS:
        raise ValueError(f"cpu_matmul={requested!r}; allowed: {list(MATMUL_BACKENDS)}")
    if requested == "onednn" and device.type == "cpu":
        if onednn_available():
            return "onednn"
        warnings.warn("oneDNN linear unavailable in this torch; SAC uses torch's matmul", stacklevel=2)
    return "torch"


class _OneDNNLinear(torch.autograd.Function):
    """y = x @ weight.T + bias for x (B, in), weight (out, in), bias (out,), as nn.Linear."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        return _onednn_mm(x, weight, bias)

    @staticmethod
    def backward(ctx, grad_y: torch.Tensor):
        x, weight = ctx.saved_tensors
        need_x, need_w, need_b = ctx.needs_input_grad
        grad_x = _onednn_mm(grad_y, weight.t()) if need_x else None  # (B, out) @ (out, in)
        grad_w = _onednn_mm(grad_y.t(), x.t()) if need_w else None  # (out, B) @ (B, in)
        grad_b = grad_y.sum(0) if need_b else None
        return grad_x, grad_w, grad_b


class _OneDNNEnsembleLinear(torch.autograd.Function):
    """y[i] = x[i] @ weight[i] + bias[i] for the n members, each (B, out), returned as a tuple:
    per-member tensors, so no layer stacks (copies) its members' activations.
    apply(weight (n, in, out), bias (n, 1, out), *xs): xs n tensors (B, in), or one shared."""

    @staticmethod
    def forward(ctx, weight: torch.Tensor, bias: torch.Tensor, *xs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        ctx.save_for_backward(weight, *xs)
        xs = xs * weight.shape[0] if len(xs) == 1 else xs
        return tuple(_onednn_mm(xi, wi.t(), bi[0]) for xi, wi, bi in zip(xs, weight, bias))

    @staticmethod
    def backward(ctx, *grad_ys: torch.Tensor):
        weight, *xs = ctx.saved_tensors
        need_w, need_b, *need_xs = ctx.needs_input_grad
        shared, n = len(xs) == 1, weight.shape[0]
        xs_n = xs * n if shared else xs
        grad_w = grad_b = None
        if need_w:  # (in, B) @ (B, out) per member
            grad_w = torch.stack([_onednn_mm(xi.t(), gi.t()) for xi, gi in zip(xs_n, grad_ys)])
        if need_b:
            grad_b = torch.stack([gi.sum(0, keepdim=True) for gi in grad_ys])
        grad_xs = [None] * len(xs)
        if any(need_xs):  # (B, out) @ (out, in) per member; a shared input sums its members' grads
            per = [_onednn_mm(gi, wi) for gi, wi in zip(grad_ys, weight)]
            grad_xs = [functools.reduce(torch.add, per)] if shared else per
        return grad_w, grad_b, *grad_xs


# An ensemble layer's activations ("members"): one (n, B, d) tensor on "torch", a tuple of n
# (B, d) tensors on "onednn".


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, backend: str) -> torch.Tensor:
    """nn.Linear's product for x (..., in), weight (out, in), bias (out,)."""
    if backend == "torch" or weight.dtype != torch.float32:  # oneDNN: float32 here
        return F.linear(x, weight, bias)
    lead = x.shape[:-1]
    return _OneDNNLinear.apply(x.reshape(-1, x.shape[-1]), weight, bias).reshape(*lead, weight.shape[0])


def ensemble_linear(x, weight: torch.Tensor, bias: torch.Tensor, backend: str):
    """n members at once: weight (n, in, out), bias (n, 1, out); x a shared (B, in) or the
    previous layer's members (n, B, in). Returns the members: (n, B, out) on "torch", as
    torch.baddbmm(bias, x, weight); a tuple of n (B, out) on "onednn"."""
    if backend == "torch" or weight.dtype != torch.float32:  # oneDNN: float32 here
        x = x.unsqueeze(0).expand(weight.shape[0], -1, -1) if x.dim() == 2 else x
        return torch.baddbmm(bias, x, weight)
    if isinstance(x, torch.Tensor):
        xs = (x,) if x.dim() == 2 else x.unbind(0)
    else:
        xs = tuple(x)
    return _OneDNNEnsembleLinear.apply(weight, bias, *xs)


def ensemble_map(fn, h):
    """fn applied to every member's activations (one call for a tensor, n for a tuple)."""
    return fn(h) if isinstance(h, torch.Tensor) else tuple(fn(x) for x in h)


def ensemble_stack(h) -> torch.Tensor:
    """The last layer's members (out = 1) as one (n, B) tensor."""
    return h.squeeze(-1) if isinstance(h, torch.Tensor) else torch.stack([x.squeeze(-1) for x in h])
