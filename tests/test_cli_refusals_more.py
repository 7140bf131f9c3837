"""The command lines as a new user meets them, beyond tests/test_cli_reliability.py (issue 41, item 5): output
paths that cannot be written (refused before any work, not lost at the end in a traceback), seeds and counts
out of range, files a tool would overwrite. Each refusal: exit 2, one `error:` line on stderr naming the flag
and what is allowed, no traceback, nothing written."""

from __future__ import annotations

import subprocess
import sys

import pytest
from scripts import ROOT

from test_cli_reliability import HEAVY, LIGHT_PROBE

UNWRITABLE = "/proc/vkgrl_no_such_dir/out"  # /proc takes no new file, not even root's


def refused(argv: list[str], message: str, tmp_path, light: bool = False) -> str:
    """Run `argv` (a script and its arguments, or -m module ...) and check it refuses in one line holding
    `message`; with `light`, also that nothing heavy was imported to say it. Returns the line."""
    if light:
        cmd = [sys.executable, "-c", LIGHT_PROBE.format(script=argv[0], argv=argv[1:], heavy=HEAVY)]
    else:
        cmd = [sys.executable, *argv]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    err = out.stderr.strip().splitlines()
    if light:
        assert out.stdout.strip().splitlines()[-1] == "EXIT 2 HEAVY []", out.stdout + out.stderr[-2000:]
    else:
        assert out.returncode == 2, out.stdout[-1000:] + out.stderr[-2000:]
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    assert [ln for ln in err if "error:" in ln] == [err[-1]], out.stderr[-2000:]  # one line, the last
    assert message in err[-1], err[-1]
    return err[-1]


@pytest.fixture
def a_file(tmp_path):
    path = tmp_path / "a_file"
    path.write_text("user data")
    return path


def _nothing_new(tmp_path, a_file):
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"] and a_file.read_text() == "user data"


OUTPUTS = [  # (argv with {out} where the output path goes, the flag)
    (["train/evaluate.py", "--device", "cpu", "--json", "{out}"], "--json"),
    (["train/evaluate.py", "--device", "cpu", "--video", "{out}"], "--video"),
    (["train/collect_demos.py", "--device", "cpu", "--out", "{out}"], "--out"),
    (["train/collect_images.py", "--device", "cpu", "--out", "{out}"], "--out"),
]


@pytest.mark.parametrize("argv, flag", OUTPUTS, ids=lambda v: v[0].removeprefix("train/") if isinstance(v, list) else v)
@pytest.mark.parametrize("where", ["unwritable", "under_a_file"])
def test_an_output_path_that_cannot_be_written_is_refused_before_any_work(argv, flag, where, tmp_path, a_file):
    """Before: the evaluation or the recording ran to its end, then a traceback (FileNotFoundError,
    NotADirectoryError) and the result was lost."""
    out = UNWRITABLE if where == "unwritable" else str(a_file / "x")
    expected = f"{flag} {out}: " + ("cannot write in /proc" if where == "unwritable" else f"{a_file} is a file, not a directory")
    refused([a.format(out=out) for a in argv], expected, tmp_path)
    _nothing_new(tmp_path, a_file)


@pytest.mark.parametrize("argv, message", [
    (["--run-dir", UNWRITABLE], f"--run-dir {UNWRITABLE}: cannot write in /proc"),
    (["--run-dir", "{a_file}/run"], "--run-dir {a_file}/run: {a_file} is a file, not a directory"),
    (["--run-dir", "{tmp}/run", "--cache-dir", "{a_file}"], "--cache-dir {a_file} is a file; give a directory"),
    (["--run-dir", "{tmp}/run", "--cache-dir", UNWRITABLE], f"--cache-dir {UNWRITABLE}: cannot write in /proc"),
    (["--run-dir", "{tmp}/run", "--seed", str(2**64)], f"--seed {2**64}: must be in [0, 2**32)"),
])
def test_run_py_refuses_a_run_or_cache_dir_it_cannot_write_before_any_heavy_import(argv, message, tmp_path, a_file):
    """Before: run.py built the env (and its prerequisites) and failed writing config.json with a traceback."""
    fill = {"tmp": tmp_path, "a_file": a_file}
    refused(["train/run.py", *[a.format(**fill) for a in argv]], message.format(**fill), tmp_path, light=True)
    _nothing_new(tmp_path, a_file)


@pytest.mark.parametrize("argv, message", [
    (["train/evaluate.py", "--device", "cpu", "--seed", "-1"], "--seed -1: must be in [0, 2**32)"),
    (["train/evaluate.py", "--device", "cpu", "--eval-seed", str(2**63)], f"--eval-seed {2**63}: must be in [0, 2**63)"),
    (["train/collect_demos.py", "--device", "cpu", "--out", "{tmp}/d.npz", "--seed", "-1"],
     "--seed -1: must be in [0, 2**32)"),
    (["train/collect_demos.py", "--device", "cpu", "--out", "{tmp}/d.npz", "--max-episodes", "0"],
     "argument --max-episodes: must be an integer >= 1, got '0'"),
    (["train/collect_images.py", "--device", "cpu", "--out", "{tmp}/i", "--seed", str(2**32)],
     f"--seed {2**32}: must be in [0, 2**32)"),
    (["train/collect_images.py", "--device", "cpu", "--out", "{tmp}/i", "--num-images", "40", "--num-envs", "1"],
     "CollectConfig.num_images=40 with num_envs=1 covers 1 episode; val_fraction=0.1 needs at least 2"),
])
def test_seeds_and_counts_out_of_range_are_refused(argv, message, tmp_path, a_file):
    """Before: a negative or too large seed was taken (run.py refused it, evaluate.py and the collections did
    not); --max-episodes 0 built the env and recorded nothing; 40 images of one world (one episode) were
    rendered, then a traceback from the train/validation split, and a half-written image set was left."""
    refused([a.format(tmp=tmp_path) for a in argv], message, tmp_path)
    _nothing_new(tmp_path, a_file)


GRID = ["--tasks", "PegInsert", "--envs", "factory", "--action-dims", "4", "--methods", "sac"]
DIR_OUTPUTS = [  # (argv with {out}; {tmp} an empty directory of runs), before any run is read or Ray started
    ["train/sweep.py", "--out", "{out}", *GRID, "--seeds", "0"],
    ["train/report.py", "{tmp}", "--out", "{out}"],
    ["train/plot_runs.py", "{tmp}", "--out", "{out}"],
]


@pytest.mark.parametrize("argv", DIR_OUTPUTS, ids=lambda v: v[0].removeprefix("train/"))
@pytest.mark.parametrize("where", ["unwritable", "under_a_file"])
def test_sweep_report_and_plot_runs_refuse_an_out_they_cannot_write(argv, where, tmp_path, a_file):
    """Before: sweep.py's mkdir, report.py's staging directory (after the runs were read) and plot_runs.py's
    figure (once drawn) ended in a traceback."""
    out = UNWRITABLE if where == "unwritable" else str(a_file / "x")
    expected = f"--out {out}: " + ("cannot write in /proc" if where == "unwritable" else f"{a_file} is a file, not a directory")
    refused([a.format(out=out, tmp=tmp_path) for a in argv], expected, tmp_path, light=True)
    _nothing_new(tmp_path, a_file)


def test_sweep_refuses_an_out_that_is_a_file_and_a_seed_run_py_refuses(tmp_path, a_file):
    """Before: `--out FILE` passed the checks and mkdir raised FileExistsError (a traceback); a seed >= 2**32
    started the sweep, and every trial of it failed in run.py."""
    refused(["train/sweep.py", "--out", str(a_file), *GRID, "--seeds", "0"], f"--out {a_file} is a file; give a "
            "directory", tmp_path, light=True)
    refused(["train/sweep.py", "--out", str(tmp_path / "s"), *GRID, "--seeds", "0", str(2**32)],
            f"grid: seeds must be integers in [0, 2**32) (run.py's --seed), got [0, {2**32}]", tmp_path, light=True)
    _nothing_new(tmp_path, a_file)


def test_train_vae_refuses_an_out_it_cannot_write_before_training(tmp_path, a_file):
    """Before: the model was built, then the run directory's mkdir raised (a traceback)."""
    import numpy as np

    from vkgrl_newton.vision.dataset import ImageSetWriter

    images = tmp_path / "a_file.images"  # (beside a_file; removed below)
    rng = np.random.default_rng(0)
    with ImageSetWriter(images, num_images=4, resolution=32, task="PegInsert", val_fraction=0.5) as w:
        w.add(rng.integers(0, 255, (4, 32, 32, 3), dtype=np.uint8), rng.normal(size=(4, 4)).astype(np.float32),
              np.array([0, 0, 1, 1]))
    for out, message in ((UNWRITABLE, f"--out {UNWRITABLE}: cannot write in /proc"),
                         (f"{a_file}/vae", f"--out {a_file}/vae: {a_file} is a file, not a directory")):
        refused(["train/train_vae.py", "--images", str(images), "--device", "cpu", "--epochs", "1", "--out", out],
                message, tmp_path)
    import shutil

    shutil.rmtree(images)
    _nothing_new(tmp_path, a_file)


TOOL_CASES = [  # (argv, what the line says); every tool's flags checked before it builds or times anything
    (["-m", "vkgrl_newton.tools.ceiling", "--json", "{a_file}"],
     "--json {a_file} exists; choose another path (results are never overwritten)"),
    (["-m", "vkgrl_newton.tools.ceiling", "--json", "{tmp}/c.json", "--episodes-per-world", "0"],
     "argument --episodes-per-world: must be an integer >= 1, got '0'"),
    (["-m", "vkgrl_newton.tools.ceiling", "--json", "{tmp}/c.json", "--num-envs", "0"],
     "argument --num-envs: must be an integer >= 1, got '0'"),
    (["-m", "vkgrl_newton.tools.ceiling", "--json", "{tmp}/c.json", "--seed", "-1"], "--seed -1: must be in [0, 2**32)"),
    (["-m", "vkgrl_newton.tools.ceiling", "--json", "{tmp}/c.json", "--perturb-kp-ulp", "-3"],
     "argument --perturb-kp-ulp: must be an integer >= 0, got '-3'"),
    (["-m", "vkgrl_newton.tools.ceiling", "--json", "{tmp}/c.json", "--oracle-lateral-noise-mm", "-0.5"],
     "argument --oracle-lateral-noise-mm: must be a finite number >= 0, got '-0.5'"),
    (["-m", "vkgrl_newton.tools.ceiling", "--json", UNWRITABLE], f"--json {UNWRITABLE}: cannot write in /proc"),
    (["-m", "vkgrl_newton.tools.bench_sac", "--steps", "0"], "argument --steps: must be an integer >= 1, got '0'"),
    (["-m", "vkgrl_newton.tools.bench_sac", "--repeats", "0"], "argument --repeats: must be an integer >= 1, got '0'"),
    (["-m", "vkgrl_newton.tools.bench_sac", "--hidden", "256", "0"], "argument --hidden: must be an integer >= 1, got '0'"),
    (["-m", "vkgrl_newton.tools.bench_sac", "--threads", "-1"], "argument --threads: must be an integer >= 0, got '-1'"),
    (["-m", "vkgrl_newton.tools.bench_sac", "--batch-size", "512", "--fill", "256"],
     "--batch-size 512: must be <= --fill 256"),
    (["-m", "vkgrl_newton.tools.bench_sac", "--json", UNWRITABLE], f"--json {UNWRITABLE}: cannot write in /proc"),
    (["-m", "vkgrl_newton.tools.bench_loop", "--json", UNWRITABLE], f"--json {UNWRITABLE}: cannot write in /proc"),
    (["-m", "vkgrl_newton.tools.bench_kernels", "--json", "{a_file}/k.json"],
     "--json {a_file}/k.json: {a_file} is a file, not a directory"),
    (["-m", "vkgrl_newton.tools.throughput", "--device", "cpu", "--json", UNWRITABLE],
     f"--json {UNWRITABLE}: cannot write in /proc"),
]


@pytest.mark.parametrize("argv, message", TOOL_CASES, ids=lambda v: "_".join(v[1:3]) if isinstance(v, list) else "")
def test_the_tools_refuse_counts_seeds_and_outputs_before_working(argv, message, tmp_path, a_file):
    """Before: ceiling overwrote an existing --json after its first controller, divided by zero after an
    evaluation of 0 episodes per world, took a negative seed or ulp count (as 0); bench_sac timed 0 gradient
    steps and reported 0 steps/s (--steps 0) or took the median of nothing (--repeats 0) after building its
    agents; a --json that cannot be written was a traceback once the benchmark had run."""
    fill = {"tmp": tmp_path, "a_file": a_file}
    refused([a.format(**fill) for a in argv], message.format(**fill), tmp_path)
    _nothing_new(tmp_path, a_file)


@pytest.mark.parametrize("argv, message", [
    (["--lam", "-1"], "argument --lam: must be a finite number > 0, got '-1'"),
    (["--lam-c", "nan"], "argument --lam-c: must be a finite number > 0, got 'nan'"),
    (["--beta", "-0.5"], "argument --beta: must be a finite number >= 0, got '-0.5'"),
    (["--seed", "-1"], "--seed -1: must be in [0, 2**32)"),
    (["--num-demos", "1"], "--num-demos 1: must be >= 2"),
])
def test_plot_kmp_refuses_kmp_parameters_before_drawing_demonstrations(argv, message, tmp_path, a_file):
    """Before: --lam -1 or --l 0 wrote the synthetic demonstrations to --out, then refused without naming the
    flag; --lam-c nan, after fitting, was a traceback; --seed -1 `expected non-negative integer`."""
    refused(["train/plot_kmp.py", "--synthetic", "PegInsert", "--out", str(tmp_path / "k"), *argv], message, tmp_path)
    _nothing_new(tmp_path, a_file)


@pytest.mark.parametrize("out, message", [
    ("{a_file}", "--out {a_file} is a file; give a directory"),
    (UNWRITABLE, f"--out {UNWRITABLE}: cannot write in /proc"),
])
def test_plot_kmp_refuses_an_out_it_cannot_write(out, message, tmp_path, a_file):
    """Before: a traceback (FileExistsError, FileNotFoundError) from the synthetic set's mkdir."""
    refused(["train/plot_kmp.py", "--synthetic", "PegInsert", "--out", out.format(a_file=a_file)],
            message.format(a_file=a_file), tmp_path)
    _nothing_new(tmp_path, a_file)


@pytest.mark.parametrize("env_id", ["VKGRL/PegInsert-Factory-4D-KGRL-v0", "VKGRL/PegInsert-Factory-4D-Vision-v0"])
def test_gymnasium_refuses_a_cache_dir_its_prerequisites_cannot_be_written_to(env_id, tmp_path, a_file):
    """Before: a NotADirectoryError traceback from the cache's mkdir (the KGRL and Vision ids make their
    demonstrations, tables, image set and VAE there)."""
    import gymnasium as gym

    import vkgrl_newton  # noqa: F401  (registers the ids)

    for cache_dir, message in ((a_file, f"cache_dir {a_file} is a file; give a directory"),
                               (UNWRITABLE, f"cache_dir {UNWRITABLE}: cannot write in /proc")):
        with pytest.raises(ValueError) as e:
            gym.make_vec(env_id, num_envs=1, device="cpu", cache_dir=cache_dir)
        assert message in str(e.value) and "\n" not in str(e.value)
    _nothing_new(tmp_path, a_file)


def test_plot_kmp_refuses_to_overwrite_its_plot(tmp_path):
    """Before: a second plot_kmp into the same --out replaced the first plot (perhaps of other KMP parameters)
    silently. Now the second is refused in one line and the first plot is kept byte for byte."""
    out = tmp_path / "k"
    first = subprocess.run([sys.executable, "train/plot_kmp.py", "--synthetic", "PegInsert", "--action-dim", "4",
                            "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr[-2000:]
    png = out / "kmp_PegInsert_4d.png"
    before = png.read_bytes()
    refused(["train/plot_kmp.py", "--synthetic", "PegInsert", "--action-dim", "4", "--lam", "2", "--out", str(out)],
            "kmp_PegInsert_4d.png exists; choose another --out", tmp_path)
    assert png.read_bytes() == before
