"""Runs started together on an empty cache prepare each entry once (vkgrl_newton.cache): two real
processes, each a 'run' (tests/cache_worker.py) whose expensive step is a logged stand-in."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

WORKER = Path(__file__).with_name("cache_worker.py")


def _two_runs_at_once(kind: str, tmp_path: Path):
    calls = tmp_path / "calls.log"
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    procs = [subprocess.Popen([sys.executable, str(WORKER), kind, str(tmp_path / "cache"), str(calls)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=240)[0] for p in procs]
    for p, out in zip(procs, outs):
        assert p.returncode == 0, out
    results = [next(ln for ln in out.splitlines() if ln.startswith("RESULT")) for out in outs]
    return calls.read_text().split(), results, outs


def test_two_kgrl_runs_record_the_demonstrations_once(tmp_path):
    calls, results, outs = _two_runs_at_once("prior", tmp_path)
    assert calls == ["record"], calls
    assert results[0] == results[1]  # same demonstrations, same tables
    assert sum("waiting for another run" in out for out in outs) == 1, outs
    demos = Path(results[0].split()[1])
    assert demos.exists() and demos.with_name(demos.stem + ".kmp4d.npz").exists()
    assert "_v" in demos.name  # keyed by the demonstrator's version


def test_two_vision_runs_collect_and_train_once(tmp_path):
    calls, results, outs = _two_runs_at_once("vision", tmp_path)
    assert sorted(calls) == ["collect", "train"], calls
    assert results[0] == results[1]
    assert sum("waiting for another run" in out for out in outs) >= 1, outs


def test_a_changed_demonstrator_version_names_new_cache_entries(monkeypatch, tmp_path):
    from vkgrl_newton.prepare.prior import demos_path_for
    from vkgrl_newton.envs import scripted
    from vkgrl_newton.prepare.images import default_image_dir
    from vkgrl_newton.prepare.vision import VISION_PRESETS, default_vae_dir

    def names():
        return (demos_path_for(tmp_path, "PegInsert", 16, 0),
                default_image_dir(tmp_path, VISION_PRESETS["quick"].collect_config("PegInsert")),
                default_vae_dir(tmp_path, "PegInsert", VISION_PRESETS["quick"]))

    old = names()
    monkeypatch.setattr(scripted, "DEMONSTRATOR_VERSION", scripted.DEMONSTRATOR_VERSION + 1)
    new = names()
    assert all(a != b for a, b in zip(old, new)), (old, new)


def test_a_changed_file_is_named_with_both_hashes(tmp_path):
    from vkgrl_newton.cache import check_unchanged, file_sha256

    f = tmp_path / "demos.npz"
    f.write_bytes(b"one")
    recorded = file_sha256(f)
    check_unchanged(f, recorded, "demos")  # unchanged: no error
    f.write_bytes(b"two")
    with pytest.raises(ValueError) as exc:
        check_unchanged(f, recorded, "demos")
    assert recorded in str(exc.value) and file_sha256(f) in str(exc.value)
    f.unlink()
    with pytest.raises(FileNotFoundError):
        check_unchanged(f, recorded, "demos")


def test_a_runs_near_hole_probe_is_checked_like_its_vae(tmp_path):
    """--vision-probe-obs runs record their probe by sha256: check_run_files refuses a changed or missing one, and
    without_file_records leaves the probe's records out of the fields a resume compares."""
    from vkgrl_newton.cache import check_run_files, file_sha256
    from vkgrl_newton.run.resolve import without_file_records

    probe = tmp_path / "near_hole_probe_mlp_seed0.npz"
    probe.write_bytes(b"weights")
    meta = {"vision": {"vae": "v.pt", "latent_dim": 16, "probe": str(probe), "probe_sha256": file_sha256(probe)}}
    check_run_files(meta, probe=probe)  # unchanged
    check_run_files({"vision": {"vae": "v.pt"}}, probe=probe)  # a run without a probe record: nothing to check
    probe.write_bytes(b"other weights")
    with pytest.raises(ValueError, match="the near-hole probe .* has changed"):
        check_run_files(meta, probe=probe)
    probe.unlink()
    with pytest.raises(FileNotFoundError, match="the near-hole probe"):
        check_run_files(meta, probe=probe)
    assert without_file_records(meta)["vision"] == {"vae": "v.pt", "latent_dim": 16}


def test_a_probe_run_records_its_probe_and_a_damaged_probe_is_one_line(tmp_path):
    """run_meta_with_files records the probe the run read (path and sha256) beside its VAE's; a damaged probe file
    given to load_or_make_probe is a ValueError naming it, never fitted over."""
    from types import SimpleNamespace

    from vkgrl_newton.cache import file_sha256
    from vkgrl_newton.agents.sac_config import SACConfig
    from vkgrl_newton.prepare.vision import VISION_PRESETS, load_or_make_probe
    from vkgrl_newton.run.config import RunConfig
    from vkgrl_newton.run.train import run_meta_with_files

    vae, probe = tmp_path / "vae.pt", tmp_path / "near_hole_probe_mlp_seed0.npz"
    vae.write_bytes(b"vae")
    probe.write_bytes(b"not an npz")
    cfg = RunConfig(method="vision_kgrl", vae=vae, vision_probe_obs=True, probe=probe, cache_dir=tmp_path,
                    sac=SACConfig())
    meta = run_meta_with_files(cfg, SimpleNamespace(action_path=None, encoder=object()))
    assert meta["vision_probe_obs"] and meta["vision"]["probe"] == str(probe)
    assert meta["vision"]["probe_sha256"] == file_sha256(probe) and meta["vision"]["vae_sha256"] == file_sha256(vae)
    plain = run_meta_with_files(RunConfig(method="vision_kgrl", vae=vae, cache_dir=tmp_path, sac=SACConfig()),
                                SimpleNamespace(action_path=None, encoder=object()))
    assert "probe" not in plain["vision"] and "vision_probe_obs" not in plain
    with pytest.raises(ValueError, match="near_hole_probe_mlp_seed0.npz"):
        load_or_make_probe("PegInsert", VISION_PRESETS["quick"], tmp_path, encoder=None, path=probe, log=lambda *a: None)
    assert probe.read_bytes() == b"not an npz"  # a given file is never refitted or replaced
