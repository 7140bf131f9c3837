"""Damaged files, inconsistent demonstrations and the no-overwrite rules."""

import math

import numpy as np
import pytest
import torch

from vkgrl_newton.kmp import DemoSet, KMPTables, fit_prior, load_or_fit_prior, synthetic_demos
from vkgrl_newton.kmp.pose import unwrap_rotation_vectors
from vkgrl_newton.rotations import quat_exp, quat_log
from vkgrl_newton.kmp.tables import tables_path_for


@pytest.fixture(scope="module")
def peg_demos():
    return synthetic_demos("PegInsert", 6, action_dim=6, seed=0)


def truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_truncated_demo_file_is_a_value_error(peg_demos, tmp_path):
    path = peg_demos.save(tmp_path / "demos.npz")
    truncate(path)
    with pytest.raises(ValueError, match="not a readable demonstration file"):
        DemoSet.load(path)


def test_truncated_tables_cache_is_rebuilt(peg_demos, tmp_path):
    demo_path = peg_demos.save(tmp_path / "demos.npz")
    tables, tpath, rebuilt = load_or_fit_prior(demo_path, n_components=4)
    assert rebuilt
    truncate(tpath)
    with pytest.raises(ValueError, match="not a readable KMP tables file"):
        KMPTables.load(tpath)
    again, _, rebuilt = load_or_fit_prior(demo_path, n_components=4)
    assert rebuilt
    torch.testing.assert_close(again.gain, tables.gain, rtol=0, atol=0)


def test_foreign_file_at_cache_path_is_not_overwritten(peg_demos, tmp_path):
    demo_path = peg_demos.save(tmp_path / "demos.npz")
    foreign = tables_path_for(demo_path, 6)
    np.savez(foreign, something_else=np.arange(3))
    before = foreign.read_bytes()
    with pytest.raises(ValueError, match="not overwritten"):
        load_or_fit_prior(demo_path, n_components=4)
    assert foreign.read_bytes() == before


def test_tables_load_rejects_grid_mismatch_and_nan(peg_demos, tmp_path):
    tables = fit_prior(peg_demos, n_components=4)
    path = tables.save(tmp_path / "t.npz")
    data = dict(np.load(path))
    bad = dict(data, mean=data["mean"][:-1], gain=data["gain"][:-1])
    np.savez(tmp_path / "short.npz", **bad)
    with pytest.raises(ValueError, match="do not match dt"):
        KMPTables.load(tmp_path / "short.npz")
    nan_mean = data["mean"].copy()
    nan_mean[3, 2] = np.nan
    np.savez(tmp_path / "nan.npz", **dict(data, mean=nan_mean))
    with pytest.raises(ValueError, match="NaN"):
        KMPTables.load(tmp_path / "nan.npz")
    with pytest.raises(FileNotFoundError):
        KMPTables.load(tmp_path / "missing.npz")


def test_fit_prior_rejects_other_psi_ref_and_6d_from_4d(peg_demos):
    wrong = DemoSet(peg_demos.s, peg_demos.eta, peg_demos.demo_lengths, "PegInsert", math.radians(-40.0), 6)
    with pytest.raises(ValueError, match="psi_ref"):
        fit_prior(wrong, n_components=4)
    demos4 = synthetic_demos("PegInsert", 6, action_dim=4, seed=0)
    with pytest.raises(ValueError, match="6D tables need 6D demonstrations"):
        fit_prior(demos4, action_dim=6, n_components=4)
    assert fit_prior(demos4, n_components=4).action_dim == 4  # default: the demonstrations' own


def test_demo_validation_time_span_4d_and_wrap(peg_demos):
    s, eta, lengths = peg_demos.s.copy(), peg_demos.eta.copy(), peg_demos.demo_lengths
    with pytest.raises(ValueError, match="start at 0 and end at 1"):
        DemoSet(s * 0.9, eta, lengths, "PegInsert", 0.0, 6)
    with pytest.raises(ValueError, match="roll/pitch"):
        DemoSet(s, eta, lengths, "PegInsert", 0.0, 4)  # 6D data declared as 4D
    wrapped = eta.copy()
    wrapped[10:20, 5] += 2 * math.pi  # a jump the log map makes at pi
    with pytest.raises(ValueError, match="unwrap"):
        DemoSet(s, wrapped, lengths, "PegInsert", 0.0, 6)


def test_unwrap_recovers_a_turn_past_pi():
    """A rotation about a fixed axis sweeping 0 -> 330 degrees: log wraps at 180, unwrap restores it."""
    axis = torch.tensor([0.2, -0.3, 0.93], dtype=torch.float64)
    axis = axis / axis.norm()
    angles = torch.linspace(0.0, math.radians(330.0), 200, dtype=torch.float64)
    r_true = angles[:, None] * axis
    r_log = quat_log(quat_exp(r_true)).numpy()
    assert np.abs(np.diff(r_log, axis=0)).max() > 3.0  # the wrap is really there
    r_unwrapped = unwrap_rotation_vectors(r_log)
    np.testing.assert_allclose(r_unwrapped, r_true.numpy(), atol=1e-9)
    # the same rotations: exp of the unwrapped vectors equals exp of the wrapped ones up to sign
    q1, q2 = quat_exp(torch.as_tensor(r_unwrapped)), quat_exp(torch.as_tensor(r_log))
    dots = (q1 * q2).sum(dim=1).abs()
    torch.testing.assert_close(dots, torch.ones_like(dots), rtol=0, atol=1e-12)


def test_demo_save_never_overwrites(peg_demos, tmp_path):
    path = peg_demos.save(tmp_path / "demos.npz")
    before = path.read_bytes()
    with pytest.raises(FileExistsError):
        synthetic_demos("GearMesh", 2, seed=1).save(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demos.npz"]  # no temporary left behind


def test_clis_keep_warp_quiet_unless_verbose(tmp_path):
    """A CLI's own lines come first: no Warp banner, no per-module 'load ... (cached)' lines, no
    missing-driver warning; `--verbose` brings Warp's messages back."""
    import os
    import subprocess
    import sys

    def run(*extra):
        argv = [sys.executable, "-m", "vkgrl_newton.tools.bench_kernels", "--batch", "1", "--devices", "cpu", "--warmup", "1",
                "--repeats", "1", "--only", "kmp_horizon", "--json", str(tmp_path / f"b{len(extra)}.json"), *extra]
        out = subprocess.run(argv, capture_output=True, text=True, timeout=300,
                             env={**os.environ, "CUDA_VISIBLE_DEVICES": ""})
        assert out.returncode == 0, out.stderr
        return out.stdout + out.stderr

    quiet = run()
    assert "kmp_horizon" in quiet
    for noise in ("Warp 1.", "initialized", "Module ", "CUDA driver"):
        assert noise not in quiet, quiet
    assert "Warp 1." in run("--verbose")
