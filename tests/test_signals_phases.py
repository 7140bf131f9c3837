"""Issue 41: a real signal at each phase of train/run.py and of gymnasium.make on an empty cache
(recording the prior's demonstrations, fitting its tables, collecting the image set, training the
VAE, training, the final evaluation, the prior's evaluation) ends in one line on stderr naming the
phase and what it kept, exit 130 / 143 / 129 and no traceback; what was finished stays; no cache entry
is left half-written (no temporary file, every file there loads) or locked; the next run reuses,
resumes or remakes it.

The runs are tests/phase_driver.py: train/run.py (its own __main__) made small, held at the phase
until the signal comes (the test waits for the driver's marker file, never a fixed time). Where the
next run would repeat minutes of simulation (recording 16 scripted demonstrations), it is the same
cache call in this process with the recorder replaced by synthetic demonstrations: the same entry,
path and lock.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from scripts import ROOT

DRIVER = Path(__file__).with_name("phase_driver.py")
TINY_VISION = "32,64,2"  # 32 px, 64 images (one round of 16 worlds), 2 VAE epochs (phase_driver.tiny_vision_preset)
SMALL = ["--num-envs", "2", "--device", "cpu", "--cpu-matmul", "torch", "--eval-episodes", "1", "--sac",
         "learning_starts=2", "--sac", "batch_size=2", "--sac", "hidden_dims=16,16"]  # (progress bars on: a user's)
ENTER_LIMIT_S = 900  # a cold Warp kernel cache compiles every kernel first (minutes under load)
EXIT_LIMIT_S = 300


class Driver:
    """One tests/phase_driver.py process, its stdout and stderr in files (no pipe to fill)."""

    def __init__(self, tmp_path: Path, hold: str, mode: str, *args: str, vision: str | None = None):
        n = len(list(tmp_path.glob("driver*.err")))
        self.marker = tmp_path / f"driver{n}.entered"
        self.out_path, self.err_path = tmp_path / f"driver{n}.out", tmp_path / f"driver{n}.err"
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "CUDA_VISIBLE_DEVICES": ""}
        env.pop("VKGRL_TEST_VISION", None)
        if vision:
            env["VKGRL_TEST_VISION"] = vision
        self.t0 = time.monotonic()
        with open(self.out_path, "w") as out, open(self.err_path, "w") as err:
            self.proc = subprocess.Popen([sys.executable, str(DRIVER), str(self.marker), hold, mode, *args], cwd=ROOT,
                                         env=env, stdout=out, stderr=err)

    @property
    def err(self) -> str:
        return self.err_path.read_text()

    @property
    def out(self) -> str:
        return self.out_path.read_text()

    def stop_when(self, entered, sig: int, what: str) -> int:
        """Send `sig` once entered() holds (the process still alive), wait for the exit; its code."""
        try:
            deadline = time.monotonic() + ENTER_LIMIT_S
            while not entered():
                assert self.proc.poll() is None, f"exited {self.proc.returncode} before {what}:\n{self.err[-3000:]}"
                assert time.monotonic() < deadline, f"no {what} within {ENTER_LIMIT_S} s:\n{self.err[-3000:]}"
                time.sleep(0.1)
            t_in = time.monotonic() - self.t0
            self.proc.send_signal(sig)
            rc = self.proc.wait(timeout=EXIT_LIMIT_S)
            print(f"{what}: signalled at {t_in:.1f} s, exited at {time.monotonic() - self.t0:.1f} s")  # (-s shows it)
            return rc
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()

    def stop_in_phase(self, sig: int, what: str) -> int:
        return self.stop_when(self.marker.exists, sig, what)

    def finish(self) -> int:
        try:
            return self.proc.wait(timeout=EXIT_LIMIT_S * 3)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()


def assert_one_line(driver: Driver, rc: int, sig: int, *needles: str) -> str:
    """Exit 128 + sig (130 for SIGINT), no traceback, and the last line of stderr says it all."""
    err = driver.err
    assert rc == 128 + sig, (rc, err[-3000:])
    assert "Traceback" not in err and "Exception ignored" not in err, err[-3000:]
    last = [ln for ln in err.splitlines() if ln.strip()][-1]
    for needle in needles:
        assert needle in last, (needle, last)
    return last


def assert_cache_whole(*dirs: Path) -> None:
    """No temporary file or directory is left, every lock is free, every entry there loads."""
    from filelock import FileLock

    from vkgrl_newton.agents.checkpoint import load_checkpoint
    from vkgrl_newton.kmp.demos import DemoSet
    from vkgrl_newton.kmp.tables import KMPTables
    from vkgrl_newton.vision.dataset import ImageSet
    from vkgrl_newton.vision.vae import load_vae

    for d in dirs:
        if not d.exists():
            continue
        for path in d.rglob("*"):
            assert ".tmp" not in path.name and not path.name.endswith(".collecting"), f"left behind: {path}"
            if path.suffix == ".lock":
                lock = FileLock(str(path))
                lock.acquire(timeout=0)  # filelock's Timeout if a process still held it
                lock.release()
            elif path.suffix == ".npz":
                (KMPTables if ".kmp" in path.name else DemoSet).load(path)
            elif path.is_dir() and path.name.startswith("images_"):
                ImageSet(path)
            elif path.suffix == ".pt":  # a VAE's or a run's checkpoint
                load_vae(path) if any(p.name.startswith("vae_") for p in path.parents) else load_checkpoint(path)
            elif path.suffix == ".json" and path.parent.name == "evaluations":
                json.loads(path.read_text())


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def synthetic_demos_file(path: Path) -> Path:
    from vkgrl_newton.kmp.demos import synthetic_demos

    synthetic_demos("PegInsert", 4, action_dim=6, seed=1).save(path)
    return path


def remake_prior_in_process(cache: Path, num_demos: int, monkeypatch) -> None:
    """The next run's preparation of the same cache entry (its path, its lock), the recorder replaced by
    synthetic demonstrations and the fit by nothing (seconds; test_sighup_while_run_py_fits_the_prior fits):
    it must neither wait on a lock nor find a half file, and records the entry anew."""
    from vkgrl_newton.kmp.demos import synthetic_demos
    from vkgrl_newton.prepare import prior

    recorded = []

    def record(task, path, num_demos, *args):
        recorded.append(path)
        synthetic_demos(task, num_demos, action_dim=6, seed=1).save(path)

    monkeypatch.setattr(prior, "_record_scripted", record)
    monkeypatch.setattr(prior, "load_or_fit_prior", lambda path, **kw: (None, path, True))
    lines: list[str] = []
    _, path = prior.load_or_make_prior("PegInsert", 4, cache, num_demos=num_demos, log=lines.append)
    assert recorded == [path] == [prior.demos_path_for(cache, "PegInsert", num_demos, 0)], (recorded, path)
    assert not any("waiting for another run" in ln for ln in lines), lines
    assert_cache_whole(cache)


@pytest.mark.slow
def test_sigterm_while_run_py_records_the_demonstrations(tmp_path, monkeypatch):
    cache, run_dir = tmp_path / "cache", tmp_path / "run"
    d = Driver(tmp_path, "record", "run", "--method", "kgrl", "--num-demos", "2", "--cache-dir", str(cache),
               "--run-dir", str(run_dir), *SMALL)
    rc = d.stop_in_phase(signal.SIGTERM, "the demonstrator's episodes")
    assert_one_line(d, rc, signal.SIGTERM, "train/run.py: stopped by SIGTERM while preparing the KMP prior: recording "
                    "its 2 PegInsert demonstrations (none is kept", "run again to continue")
    assert not run_dir.exists()  # nothing of the run before its prerequisites
    assert not list(cache.rglob("*.npz"))
    assert_cache_whole(cache)
    remake_prior_in_process(cache, 2, monkeypatch)


@pytest.mark.slow
def test_sighup_while_run_py_fits_the_prior(tmp_path):
    from vkgrl_newton.kmp.prior import load_or_fit_prior
    from vkgrl_newton.kmp.tables import tables_path_for

    demos = synthetic_demos_file(tmp_path / "demos" / "mine.npz")
    before = sha(demos)
    cache, run_dir = tmp_path / "cache", tmp_path / "run"
    d = Driver(tmp_path, "fit", "run", "--method", "kgrl", "--demos", str(demos), "--cache-dir", str(cache),
               "--run-dir", str(run_dir), *SMALL)
    rc = d.stop_in_phase(signal.SIGHUP, "the fit")
    assert_one_line(d, rc, signal.SIGHUP, "stopped by SIGHUP while preparing the KMP prior: fitting its tables "
                    "(the demonstrations mine.npz are kept")
    assert sha(demos) == before  # the user's file, as it was
    tables_path = tables_path_for(demos, 4, "gmr")
    assert not tables_path.exists() and not run_dir.exists()
    assert_cache_whole(demos.parent, cache)
    tables, path, rebuilt = load_or_fit_prior(demos, action_dim=4)  # the next run fits them
    assert path == tables_path and rebuilt
    assert_cache_whole(demos.parent)


@pytest.mark.slow
def test_sigterm_while_collecting_the_image_set_then_sigint_while_training_the_vae(tmp_path):
    """Two phases of one cache: the collection (SIGTERM) and, in the next run, the VAE (Ctrl-C); the
    run after that resumes the VAE from its first epoch."""
    from phase_driver import tiny_vision_preset

    from vkgrl_newton.prepare.images import default_image_dir
    from vkgrl_newton.prepare.vision import default_vae_dir, load_or_make_encoder
    from vkgrl_newton.vision.dataset import ImageSet
    from vkgrl_newton.vision.vae import load_vae

    cache, run_dir = tmp_path / "cache", tmp_path / "run"
    argv = ["--method", "vision_sac", "--cache-dir", str(cache), "--run-dir", str(run_dir), *SMALL]
    preset = tiny_vision_preset(TINY_VISION)
    image_dir = default_image_dir(cache, preset.collect_config("PegInsert"))
    vae_dir = default_vae_dir(cache, "PegInsert", preset)

    d = Driver(tmp_path, "collect", "run", *argv, vision=TINY_VISION)
    rc = d.stop_in_phase(signal.SIGTERM, "frames written")
    assert_one_line(d, rc, signal.SIGTERM, "stopped by SIGTERM while preparing the vision prerequisites: collecting "
                    "the PegInsert image set (the unfinished set is removed)")
    assert not image_dir.exists() and not image_dir.with_name(image_dir.name + ".collecting").exists()
    assert not vae_dir.exists() and not run_dir.exists()
    assert_cache_whole(cache)

    d = Driver(tmp_path, "vae", "run", *argv, vision=TINY_VISION)  # collects anew, then the VAE: Ctrl-C
    rc = d.stop_in_phase(signal.SIGINT, "the VAE's second epoch")
    assert_one_line(d, rc, signal.SIGINT, "interrupted while preparing the vision prerequisites: training the "
                    f"PegInsert VAE (its last finished epoch is kept in {vae_dir / 'checkpoints' / 'last.pt'}")
    assert len(ImageSet(image_dir)) == 64  # the finished set stays
    _, payload = load_vae(vae_dir / "checkpoints" / "last.pt")
    assert payload["epoch"] == 1 and not (vae_dir / "metrics.json").exists() and not run_dir.exists()
    assert_cache_whole(cache)

    lines: list[str] = []  # the next run: the set reused, the VAE resumed at epoch 1 and finished
    load_or_make_encoder("PegInsert", preset, cache, "cpu", log=lines.append, progress=False)
    assert not any(ln.startswith("collecting") for ln in lines), lines
    assert any(f"resumed {vae_dir} after epoch 1 of 2" in ln for ln in lines), lines
    assert json.loads((vae_dir / "metrics.json").read_text())["epochs"] == 2
    assert_cache_whole(cache)


@pytest.mark.slow
def test_sigterm_before_the_first_checkpoint_removes_what_the_run_wrote(tmp_path):
    """Between config.json (and tb/) and the loop's first checkpoint: a directory holding them and no
    checkpoint would be refused by the next run and by --resume alike, so the stopped run removes them."""
    run_dir = tmp_path / "run"
    d = Driver(tmp_path, "start", "run", "--method", "sac", "--run-dir", str(run_dir), "--total-steps", "100000",
               "--cache-dir", str(tmp_path / "cache"), *SMALL)
    rc = d.stop_in_phase(signal.SIGTERM, "the loop's start")
    assert_one_line(d, rc, signal.SIGTERM, "train/run.py: stopped by SIGTERM; stopped before its first checkpoint: "
                    "what it wrote is removed; run again to start it")
    assert not run_dir.exists()


@pytest.mark.slow
def test_sigterm_while_training_then_in_the_final_and_the_priors_evaluation(tmp_path):
    """One kgrl run stopped in each later phase in turn, each next run resuming it: training (the
    checkpoint at the loop's start), the final evaluation, the prior's evaluation (cached in
    --cache-dir/evaluations), then the run finishes."""
    from vkgrl_newton.agents.checkpoint import load_checkpoint

    demos = synthetic_demos_file(tmp_path / "demos" / "mine.npz")
    cache, run_dir = tmp_path / "cache", tmp_path / "run"
    ckpt = run_dir / "checkpoints" / "last.pt"
    common = ["--run-dir", str(run_dir), "--cache-dir", str(cache), *SMALL]

    d = Driver(tmp_path, "none", "run", "--method", "kgrl", "--demos", str(demos), "--total-steps", "100000",
               "--checkpoint-every", "100000", *common)
    rc = d.stop_when(ckpt.exists, signal.SIGTERM, "the loop's first checkpoint")  # (written whole: renamed in)
    last = assert_one_line(d, rc, signal.SIGTERM, "train/run.py: stopped by SIGTERM", "(--resume continues)")
    at = load_checkpoint(ckpt)["counters"]["transitions"]
    # in the loop (or, a few bytecodes after that first checkpoint, just before it: the checkpoint is kept)
    assert f"; checkpoint at {at} transitions in {ckpt}" in last or f"the checkpoint {ckpt} is kept" in last, last
    assert (run_dir / "config.json").is_file() and not (run_dir / "metrics.json").exists()
    assert_cache_whole(demos.parent, cache, run_dir)

    d = Driver(tmp_path, "final_eval", "run", "--resume", "--total-steps", str(at + 4), *common)
    rc = d.stop_in_phase(signal.SIGTERM, "the final evaluation")
    assert_one_line(d, rc, signal.SIGTERM, "stopped by SIGTERM during the final evaluation; the trained checkpoint "
                    f"{ckpt} is kept (--resume evaluates)")
    assert load_checkpoint(ckpt)["counters"]["transitions"] == at + 4  # trained to the end, kept
    assert not (run_dir / "metrics.json").exists()
    assert_cache_whole(demos.parent, cache, run_dir)

    d = Driver(tmp_path, "prior_eval", "run", "--resume", *common)
    rc = d.stop_in_phase(signal.SIGTERM, "the prior's evaluation")
    assert_one_line(d, rc, signal.SIGTERM, "during the final evaluation while computing the prior's evaluation (none "
                    "of it is cached", "(--resume evaluates)")
    assert not list((cache / "evaluations").glob("*.json")) and not (run_dir / "metrics.json").exists()
    assert_cache_whole(demos.parent, cache, run_dir)

    d = Driver(tmp_path, "none", "run", "--resume", *common)
    assert d.finish() == 0, d.err[-3000:]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["training"]["transitions"] == at + 4 and "prior_eval" in metrics
    assert len(list((cache / "evaluations").glob("*.json"))) == 1  # the prior's evaluation, made and cached
    assert_cache_whole(demos.parent, cache, run_dir)


@pytest.mark.slow
def test_sigterm_while_gymnasium_make_records_the_prior(tmp_path, monkeypatch):
    """A user's script without handlers of its own: gymnasium.make_vec of a KGRL id on an empty cache."""
    cache = tmp_path / "cache"
    d = Driver(tmp_path, "record", "gym", "VKGRL/PegInsert-Factory-4D-KGRL-v0", str(cache))
    rc = d.stop_in_phase(signal.SIGTERM, "the demonstrator's episodes")
    assert_one_line(d, rc, signal.SIGTERM, "vkgrl_newton: stopped by SIGTERM while preparing the KMP prior: "
                    "recording its 16 PegInsert demonstrations (none is kept", "the env was not made")
    assert "made" not in d.out
    assert not list(cache.rglob("*.npz"))
    assert_cache_whole(cache)
    remake_prior_in_process(cache, 16, monkeypatch)
