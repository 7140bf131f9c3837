"""Tests of the demonstration file format and the synthetic demonstrator (vkgrl_newton.kmp.demos)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vkgrl_newton.kmp.demos import DemoSet, synthetic_demos
from vkgrl_newton.tasks import TASKS

# Seated TCP height above the target frame at the end of each synthetic motion (m); NutThread
# threads 120 degrees at 2 mm per turn below its 4 mm start.
Z_END = {"PegInsert": 0.0074, "GearMesh": 0.002, "NutThread": 0.004 - 0.002 * 120.0 / 360.0}
STEPS = {"PegInsert": 150, "GearMesh": 150, "NutThread": 225}  # 10 s / 10 s / 15 s at 15 Hz


def small_set(**overrides):
    s = np.concatenate([np.linspace(0, 1, 5), np.linspace(0, 1, 4)])
    eta = np.random.default_rng(0).normal(size=(9, 6)) * 1e-3
    kw = dict(s=s, eta=eta, demo_lengths=np.array([5, 4], dtype=np.int64), task="PegInsert",
              psi_ref=0.0, action_dim=6, source="test")
    kw.update(overrides)
    return DemoSet(**kw)


# ---------------------------------------------------------------------------------------
# synthetic demonstrator
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("task", sorted(TASKS))
@pytest.mark.parametrize("action_dim", [4, 6])
def test_synthetic_shapes_and_contents(task, action_dim):
    num = 5
    d = synthetic_demos(task, num, action_dim=action_dim, seed=3)
    n = STEPS[task] + 1
    assert d.task == task and d.action_dim == action_dim and d.num_demos == num
    assert d.psi_ref == pytest.approx(TASKS[task].psi_ref)
    assert d.s.shape == (num * n,) and d.eta.shape == (num * n, 6)
    assert d.s.dtype == np.float64 and d.eta.dtype == np.float64
    np.testing.assert_array_equal(d.demo_lengths, np.full(num, n))
    assert np.all(np.isfinite(d.eta))
    for s, eta in d.split():
        assert s[0] == 0.0 and s[-1] == 1.0
        assert np.all(np.diff(s) > 0)
        np.testing.assert_allclose(np.diff(s), 1.0 / STEPS[task], rtol=1e-9)
        # rotation vectors are the shortest rotation
        assert np.all(np.linalg.norm(eta[:, 3:], axis=1) <= math.pi)
    if action_dim == 4:
        assert np.all(d.eta[:, 3:5] == 0.0)
    else:
        # 6D demos carry a small roll/pitch error (a few degrees), not zero
        assert np.abs(d.eta[:, 3:5]).max() > math.radians(0.3)
        assert np.abs(d.eta[:, 3:5]).max() < math.radians(6.0)


def test_synthetic_deterministic_for_seed():
    a = synthetic_demos("GearMesh", 4, action_dim=6, seed=11)
    b = synthetic_demos("GearMesh", 4, action_dim=6, seed=11)
    c = synthetic_demos("GearMesh", 4, action_dim=6, seed=12)
    np.testing.assert_array_equal(a.s, b.s)
    np.testing.assert_array_equal(a.eta, b.eta)
    assert not np.array_equal(a.eta, c.eta)


@pytest.mark.parametrize("task", sorted(TASKS))
def test_synthetic_final_pose_is_seated(task):
    d = synthetic_demos(task, 40, action_dim=6, seed=0)
    final = np.stack([eta[-1, :3] for _, eta in d.split()])
    seated = np.array([0.0, 0.0, Z_END[task]])
    # the 1 mm (std) target noise of eq. 5.23 plus 0.1 mm jitter: every demo within 5 mm per axis
    assert np.abs(final - seated).max() < 5e-3
    # on average the seated pose (40 demos: std of the mean ~0.16 mm)
    np.testing.assert_allclose(final.mean(axis=0), seated, atol=6e-4)
    xy_std = final[:, :2].std(axis=0)
    assert np.all(xy_std > 0.3e-3) and np.all(xy_std < 3e-3), xy_std
    # the start is the hand's initial height above the target (+- ee noise and target noise)
    start = np.stack([eta[0, :3] for _, eta in d.split()])
    assert np.abs(start[:, 2] - TASKS[task].hand_init_height).max() < TASKS[task].ee_pos_noise[2] + 5e-3


def test_synthetic_bad_arguments():
    with pytest.raises(ValueError, match="task"):
        synthetic_demos("NoSuchTask", 2)
    with pytest.raises(ValueError, match="num_demos"):
        synthetic_demos("PegInsert", 0)
    with pytest.raises(ValueError, match="action_dim"):
        synthetic_demos("PegInsert", 2, action_dim=5)


# ---------------------------------------------------------------------------------------
# DemoSet file format and validation
# ---------------------------------------------------------------------------------------
def test_save_load_round_trip_exact(tmp_path):
    d = synthetic_demos("NutThread", 3, action_dim=4, seed=5)
    path = d.save(tmp_path / "sub" / "demos.npz")
    assert path.exists()
    back = DemoSet.load(path)
    np.testing.assert_array_equal(back.s, d.s)
    np.testing.assert_array_equal(back.eta, d.eta)
    np.testing.assert_array_equal(back.demo_lengths, d.demo_lengths)
    assert back.demo_lengths.dtype == np.int64
    assert (back.task, back.psi_ref, back.action_dim, back.source) == (d.task, d.psi_ref, d.action_dim, d.source)
    # no temporary files are left behind
    assert sorted(p.name for p in path.parent.iterdir()) == ["demos.npz"]


def test_save_refuses_to_overwrite(tmp_path):
    path = tmp_path / "demos.npz"
    small_set().save(path)
    before = path.read_bytes()
    with pytest.raises(FileExistsError):
        small_set(source="other").save(path)
    assert path.read_bytes() == before


def test_empty_demo_set_raises():
    with pytest.raises(ValueError, match="empty"):
        DemoSet(s=np.zeros(0), eta=np.zeros((0, 6)), demo_lengths=np.zeros(0, dtype=np.int64),
                task="PegInsert", psi_ref=0.0, action_dim=6)


def test_s_outside_unit_interval_raises():
    s = np.concatenate([np.linspace(0, 1.01, 5), np.linspace(0, 1, 4)])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        small_set(s=s)
    s = np.concatenate([np.linspace(-0.01, 1, 5), np.linspace(0, 1, 4)])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        small_set(s=s)


def test_decreasing_time_raises():
    s = np.concatenate([np.linspace(0, 1, 5), np.array([0.0, 0.6, 0.5, 1.0])])
    with pytest.raises(ValueError, match="decreases inside demonstration 1"):
        small_set(s=s)
    # time restarting at 0 between demonstrations is fine
    small_set()


def test_other_validation():
    with pytest.raises(ValueError, match="sum"):
        small_set(demo_lengths=np.array([5, 5], dtype=np.int64))
    with pytest.raises(ValueError, match="eta"):
        small_set(eta=np.zeros((9, 4)))
    eta = np.zeros((9, 6))
    eta[3, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        small_set(eta=eta)
    with pytest.raises(ValueError, match="action_dim"):
        small_set(action_dim=5)


def test_load_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        DemoSet.load(tmp_path / "nope.npz")


def test_load_missing_keys(tmp_path):
    path = tmp_path / "partial.npz"
    np.savez(path, s=np.linspace(0, 1, 5), eta=np.zeros((5, 6)))
    with pytest.raises(ValueError, match="missing keys"):
        DemoSet.load(path)


def test_load_not_npz(tmp_path):
    path = tmp_path / "garbage.npz"
    path.write_bytes(b"this is not a zip file")
    with pytest.raises(ValueError):
        DemoSet.load(path)
