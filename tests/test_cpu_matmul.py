"""The SAC networks' CPU matmul library: "auto" chosen once per machine and kept (agents/matmul_backend.py),
both libraries within float32's error bound of the exact products, and the choice a run records and keeps."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from vkgrl_newton.agents import matmul_backend as mb
from vkgrl_newton.agents.dense import ensemble_linear, linear, onednn_available
from vkgrl_newton.agents.sac_config import MATMUL_BACKENDS, make_sac_config

TINY = make_sac_config("quick", hidden_dims=(16, 16), batch_size=8)
U = 2.0 ** -24  # float32's unit roundoff


def _fake_timer(monkeypatch, seconds: dict):
    calls = []

    def fake(cfg, obs_dim, action_dim, **kw):
        calls.append((obs_dim, action_dim))
        return dict(seconds)

    monkeypatch.setattr(mb, "time_backends", fake)
    monkeypatch.setattr(mb, "onednn_available", lambda: True)
    return calls


def test_auto_is_timed_once_per_machine_and_shapes_then_read_back(tmp_path, monkeypatch):
    calls = _fake_timer(monkeypatch, {"onednn": 2e-3, "torch": 1e-3})
    path = tmp_path / "cpu_matmul.json"
    assert mb.choose_cpu_matmul(TINY, 8, 4, "cpu", path) == "torch"  # the faster one
    assert len(calls) == 1
    kept = json.loads(path.read_text())["choices"]
    assert list(kept) == [mb.choice_key(TINY, 8, 4)] and kept[mb.choice_key(TINY, 8, 4)]["backend"] == "torch"
    from vkgrl_newton.runtime import cpu_model

    assert cpu_model() in mb.choice_key(TINY, 8, 4) and torch.__version__ in mb.choice_key(TINY, 8, 4)
    # the second call (any later run on this machine) reads the kept winner, even if a timing now would differ
    calls2 = _fake_timer(monkeypatch, {"onednn": 1e-3, "torch": 2e-3})
    assert mb.choose_cpu_matmul(TINY, 8, 4, "cpu", path) == "torch" and calls2 == []
    # other shapes are another key: timed once, kept beside the first
    assert mb.choose_cpu_matmul(TINY, 11, 4, "cpu", path) == "onednn" and calls2 == [(11, 4)]
    assert len(json.loads(path.read_text())["choices"]) == 2
    # a concrete library is what it says, without timing
    assert mb.choose_cpu_matmul(dataclasses.replace(TINY, cpu_matmul="onednn"), 3, 2, "cpu", path) == "onednn"
    assert calls2 == [(11, 4)]


def test_auto_is_torch_without_timing_where_onednn_is_missing_or_on_cuda(tmp_path, monkeypatch):
    calls = _fake_timer(monkeypatch, {"onednn": 1e-3, "torch": 2e-3})
    monkeypatch.setattr(mb, "onednn_available", lambda: False)
    path = tmp_path / "cpu_matmul.json"
    assert mb.choose_cpu_matmul(TINY, 8, 4, "cpu", path) == "torch"
    monkeypatch.setattr(mb, "onednn_available", lambda: True)
    assert mb.choose_cpu_matmul(TINY, 8, 4, "cuda:0", path) == "torch"  # cuBLAS either way
    assert calls == [] and not path.exists()


@pytest.mark.parametrize("damage", [b"", b"{not json", b'{"format": 99, "choices": {}}', b"[1, 2]",
                                    b'{"format": 1, "choices": {"k": {"backend": "mkl"}}}'])
def test_a_damaged_choice_file_is_measured_again_and_rewritten_whole(tmp_path, monkeypatch, damage):
    calls = _fake_timer(monkeypatch, {"onednn": 1e-3, "torch": 2e-3})
    path = tmp_path / "cpu_matmul.json"
    path.write_bytes(damage)
    assert mb.choose_cpu_matmul(TINY, 8, 4, "cpu", path) == "onednn" and len(calls) == 1
    data = json.loads(path.read_text())
    assert data["format"] == 1 and data["choices"][mb.choice_key(TINY, 8, 4)]["backend"] == "onednn"


def test_a_real_timing_is_kept_and_a_sac_built_with_auto_runs_the_kept_library(tmp_path, monkeypatch):
    from vkgrl_newton.agents.sac import SAC

    monkeypatch.setenv("VKGRL_NEWTON_CACHE_DIR", str(tmp_path))
    seconds = mb.time_backends(TINY, 5, 3, rounds=2, min_call_s=0.005)
    assert set(seconds) == set(MATMUL_BACKENDS) and all(0 < s < 10 for s in seconds.values())
    agent = SAC(5, 3, TINY, "cpu", seed=0)
    kept = json.loads((tmp_path / mb.CHOICE_FILE).read_text())["choices"] if onednn_available() else None
    want = kept[mb.choice_key(TINY, 5, 3)]["backend"] if kept else "torch"
    assert agent.cpu_matmul == agent.critic.matmul == want


def _gamma(k: int) -> float:
    """Higham's gamma_k = k u / (1 - k u): |fl(sum of k products) - exact| <= gamma_k sum |products|,
    for any summation order and with or without FMA (float32 inputs, float32 accumulation)."""
    return k * U / (1 - k * U)


def _check_bound(got: torch.Tensor, exact: torch.Tensor, abs_terms: torch.Tensor, k: int, what: str) -> None:
    err = (got.double() - exact).abs()
    bound = _gamma(k) * abs_terms
    worst = (err / bound.clamp_min(1e-300)).max().item()
    assert bool((err <= bound).all()), f"{what}: error exceeds gamma_{k} bound by x{worst:.2f}"
    assert worst > 0 or bool((err == 0).all())  # (a non-trivial comparison: the products were rounded)


@pytest.mark.parametrize("backend", MATMUL_BACKENDS)
def test_both_libraries_are_within_float32s_error_bound_of_the_exact_products(backend):
    """linear and ensemble_linear, forward and every gradient, at the thesis network's widths, against
    the exact products of the same float32 numbers (float64 holds a product of two float32 exactly and
    sums these few terms with error far below the float32 bound). A library computing in a lower
    precision (bf16, tf32) would break the bound."""
    if backend == "onednn" and not onednn_available():
        pytest.skip("this torch has no oneDNN linear")
    g = torch.Generator().manual_seed(0)
    B, K, N, n = 256, 512, 256, 2
    x = torch.randn(B, K, generator=g).requires_grad_(True)
    w = (torch.randn(N, K, generator=g) / K ** 0.5).requires_grad_(True)
    b = torch.randn(N, generator=g).requires_grad_(True)
    gy = torch.randn(B, N, generator=g)
    y = linear(x, w, b, backend)
    y.backward(gy)
    x64, w64, b64, gy64 = (t.detach().double() for t in (x, w, b, gy))
    _check_bound(y, x64 @ w64.T + b64, x64.abs() @ w64.abs().T + b64.abs(), K + 1, "linear forward")
    _check_bound(x.grad, gy64 @ w64, gy64.abs() @ w64.abs(), N, "linear d/dx")
    _check_bound(w.grad, gy64.T @ x64, gy64.abs().T @ x64.abs(), B, "linear d/dw")
    _check_bound(b.grad, gy64.sum(0), gy64.abs().sum(0), B, "linear d/db")

    we = (torch.randn(n, K, N, generator=g) / K ** 0.5).requires_grad_(True)
    be = torch.randn(n, 1, N, generator=g).requires_grad_(True)
    xs = torch.randn(B, K, generator=g).requires_grad_(True)  # one input shared by the members
    gys = torch.randn(n, B, N, generator=g)
    ys = ensemble_linear(xs, we, be, backend)
    ys = ys if isinstance(ys, torch.Tensor) else torch.stack(ys)
    ys.backward(gys)
    we64, be64, xs64, gys64 = (t.detach().double() for t in (we, be, xs, gys))
    _check_bound(ys, xs64 @ we64 + be64, xs64.abs() @ we64.abs() + be64.abs(), K + 1, "ensemble forward")
    _check_bound(we.grad, xs64.T @ gys64, xs64.abs().T @ gys64.abs(), B, "ensemble d/dw")
    # the shared input's gradient sums the members' products: n * N terms at most
    _check_bound(xs.grad, (gys64 @ we64.transpose(1, 2)).sum(0), (gys64.abs() @ we64.abs().transpose(1, 2)).sum(0),
                 n * N, "ensemble d/dx (shared)")


# --- the run records the library that ran, keeps it on --resume, refuses a change -----------------

def _sac_checkpoint(run_dir, cpu_matmul: str, drop_field: bool = False) -> None:
    from vkgrl_newton.agents.checkpoint import CHECKPOINT_FORMAT, save_checkpoint
    from vkgrl_newton.agents.sac_config import SAC_PRESETS
    from vkgrl_newton.run.config import RunConfig

    meta = RunConfig(task="PegInsert", method="sac", num_envs=2, preset="quick",
                     sac=dataclasses.replace(SAC_PRESETS["quick"], cpu_matmul=cpu_matmul)).meta()
    if drop_field:  # a run from before the field existed
        del meta["sac"]["cpu_matmul"]
    save_checkpoint(run_dir / "checkpoints" / "last.pt",
                    {"format": CHECKPOINT_FORMAT, "meta": meta, "counters": {"transitions": 16}, "agent": {}, "rng": {},
                     "plan": {"total_steps": 32, "checkpoint_every": 16, "eval_episodes": 0, "eval_seed": 1}})


def _resolve(argv):
    from vkgrl_newton.run.config import build_parser
    from vkgrl_newton.run.resolve import resolve

    return resolve(build_parser(), argv)


def test_a_fresh_run_records_a_concrete_library_chosen_in_its_cache_dir(tmp_path):
    cfg = _resolve(["--method", "sac", "--device", "cpu", "--run-dir", str(tmp_path / "run"),
                    "--cache-dir", str(tmp_path / "cache"), "--sac", "hidden_dims=16,16", "--sac", "batch_size=8"]).config
    assert cfg.sac.cpu_matmul in MATMUL_BACKENDS and cfg.meta()["sac"]["cpu_matmul"] == cfg.sac.cpu_matmul
    if onednn_available():  # timed and kept in the run's cache directory
        kept = json.loads((tmp_path / "cache" / mb.CHOICE_FILE).read_text())["choices"]
        assert [c["backend"] for c in kept.values()] == [cfg.sac.cpu_matmul]
    given = _resolve(["--method", "sac", "--device", "cpu", "--run-dir", str(tmp_path / "run2"),
                      "--cpu-matmul", "torch"]).config
    assert given.sac.cpu_matmul == "torch"


@pytest.mark.parametrize("argv, message", [
    (["--method", "ppo", "--cpu-matmul", "torch"], "--cpu-matmul is for the SAC methods"),
    (["--method", "sac", "--cpu-matmul", "torch", "--sac", "cpu_matmul=onednn"],
     "--cpu-matmul torch and --sac cpu_matmul=onednn disagree"),
])
def test_cpu_matmul_options_that_cannot_both_hold_are_refused(argv, message, tmp_path):
    from vkgrl_newton.run.config import ConfigError

    with pytest.raises(ConfigError, match=message):
        _resolve([*argv, "--device", "cpu", "--run-dir", str(tmp_path / "run")])


def test_a_resumed_run_keeps_its_library_and_refuses_another(tmp_path):
    from vkgrl_newton.run.config import ConfigError

    run_dir = tmp_path / "run"
    _sac_checkpoint(run_dir, "torch")
    for extra in ([], ["--cpu-matmul", "auto"], ["--cpu-matmul", "torch"]):
        cfg = _resolve(["--run-dir", str(run_dir), "--resume", "--device", "cpu", *extra]).config
        assert cfg.sac.cpu_matmul == "torch"
    with pytest.raises(ConfigError, match="ran on torch; --cpu-matmul onednn would change its float32 results"):
        _resolve(["--run-dir", str(run_dir), "--resume", "--device", "cpu", "--cpu-matmul", "onednn"])
    old = tmp_path / "old"
    _sac_checkpoint(old, "torch", drop_field=True)  # before the field: torch's matmul, and it resumes as such
    assert _resolve(["--run-dir", str(old), "--resume", "--device", "cpu"]).config.sac.cpu_matmul == "torch"


def test_the_choice_is_made_and_kept_for_the_threads_the_run_will_use(tmp_path, monkeypatch):
    seen = []

    def fake(cfg, obs_dim, action_dim, **kw):
        seen.append(torch.get_num_threads())
        return {"onednn": 1e-3, "torch": 2e-3}

    monkeypatch.setattr(mb, "time_backends", fake)
    monkeypatch.setattr(mb, "onednn_available", lambda: True)
    before = torch.get_num_threads()
    path = tmp_path / "cpu_matmul.json"
    mb.choose_cpu_matmul(TINY, 8, 4, "cpu", path, threads=1)
    assert seen == [1] and torch.get_num_threads() == before  # timed on 1 thread, the caller's count restored
    torch.set_num_threads(1)
    try:
        assert mb.choice_key(TINY, 8, 4) in json.loads(path.read_text())["choices"]  # kept under 1 thread's key
    finally:
        torch.set_num_threads(before)


def test_evaluate_refuses_cpu_matmul_without_a_checkpoint(capsys):
    from scripts import load_script

    with pytest.raises(SystemExit) as exc:
        load_script("evaluate").main(["--cpu-matmul", "torch", "--device", "cpu"])
    assert exc.value.code == 2
    assert "--cpu-matmul chooses a SAC checkpoint's matmul library: give --checkpoint" in capsys.readouterr().err
