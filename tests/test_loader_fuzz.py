"""Issue 41: every loader of a file a user hands over, fuzzed with hypothesis.

One loader per kind of file: a training checkpoint (agents.checkpoint.load_checkpoint), a VAE
(vision.vae.load_vae), demonstrations (kmp.demos.DemoSet.load), KMP tables (kmp.tables.KMPTables.load),
an image set (vision.dataset.ImageSet), a sweep's grid JSON (train/sweep.py load_grid) and a sweep's
run directory (vkgrl_newton.sweep: trial.json, metrics.json, curves.jsonl). Each is fed random bytes,
truncations of a valid file at every length class, bytes flipped inside, and the valid file's content
with keys removed, values of other types, dtypes and shapes, NaN and inf inside arrays and a foreign
format version. The property: the loader returns a valid object or raises ValueError, the project's one
error type (the CLIs turn it into `prog: error: <line>` and exit 2), whose message is one line naming
the file. Anything else (KeyError, RuntimeError, a pickle or zip error, MemoryError...) fails here.

The seed files are small and synthetic, written with the project's own writers: no training, no Warp.
Bounded and derandomized, so that CI is deterministic and the file runs in well under a minute.
"""

from __future__ import annotations

import copy
import io
import itertools
import json
import math
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scripts import ROOT, load_script

from vkgrl_newton._io import save_checkpoint
from vkgrl_newton.agents.checkpoint import load_checkpoint
from vkgrl_newton.kmp.demos import DemoSet, synthetic_demos
from vkgrl_newton.kmp.gmr import GMM
from vkgrl_newton.kmp.tables import KMPTables
from vkgrl_newton.sweep import read_trial_state, run_transitions, trial_status
from vkgrl_newton.vision.dataset import ImageSet, ImageSetWriter
from vkgrl_newton.vision.vae import DenoisingVAE, VAEConfig, load_vae, save_vae

# torch warns about the pickle protocol a damaged file claims before it refuses it
pytestmark = pytest.mark.filterwarnings("ignore:Detected pickle protocol:UserWarning")
FUZZ = settings(max_examples=100, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
_names = itertools.count()


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


def _fresh(work: Path, suffix: str) -> Path:
    return work / f"f{next(_names)}{suffix}"


def refused_or_valid(load, path: Path, valid=lambda obj: None):
    """The property: `load(path)` returns an object `valid` accepts, or raises ValueError in one line naming path."""
    try:
        obj = load(path)
    except ValueError as e:
        message = str(e)
        assert "\n" not in message, message
        assert str(path) in message, message
        return None
    valid(obj)
    return obj


# ----------------------------------------------------------------------------- damage, as strategies
def truncation(n: int):
    """A length to cut a file of n bytes to: tiny, around headers, anywhere, the last bytes."""
    return st.one_of(st.integers(0, min(64, n - 1)), st.integers(0, min(1024, n - 1)), st.integers(0, n - 1),
                     st.integers(max(0, n - 64), n - 1))


@st.composite
def damaged_bytes(draw, seed: bytes) -> bytes:
    """Random bytes, the seed file cut short, or the seed file with some bytes changed."""
    kind = draw(st.sampled_from(("random", "truncated", "flipped")))
    if kind == "random":
        return draw(st.binary(max_size=4096))
    if kind == "truncated":
        return seed[: draw(truncation(len(seed)))]
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, 8))):
        data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
    return bytes(data)


DTYPES = st.sampled_from([np.float64, np.float32, np.int64, np.int8, np.uint8, np.bool_, np.complex64, "U3"])
SHAPES = hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=5)


def random_array():
    return DTYPES.flatmap(lambda dt: hnp.arrays(dt, SHAPES))


def with_non_finite(a: np.ndarray, draw) -> np.ndarray:
    """`a` as float with NaN, inf or -inf at some entries."""
    a = np.array(a, dtype=np.float64)
    if a.size:
        flat = a.reshape(-1)
        for _ in range(draw(st.integers(1, 3))):
            flat[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    return a


@st.composite
def mutated_arrays(draw, seed: dict) -> dict:
    """The seed's named arrays with keys removed, replaced by other dtypes and shapes, reshaped, given NaN
    or inf, or a foreign format_version."""
    arrays = dict(seed)
    for _ in range(draw(st.integers(1, 3))):
        key = draw(st.sampled_from(sorted(seed)))
        op = draw(st.sampled_from(("drop", "replace", "reshape", "non_finite", "dtype", "version")))
        if op == "drop":
            arrays.pop(key, None)
        elif op == "replace":
            arrays[key] = draw(random_array())
        elif op == "reshape" and key in arrays:
            arrays[key] = np.asarray(arrays[key]).reshape(-1)[: draw(st.integers(0, 3))]
        elif op == "non_finite" and key in arrays and np.asarray(arrays[key]).dtype.kind in "iuf":
            arrays[key] = with_non_finite(arrays[key], draw)
        elif op == "dtype" and key in arrays:
            try:
                arrays[key] = np.asarray(arrays[key]).astype(draw(DTYPES))
            except (ValueError, OverflowError):  # a dtype these values cannot take: the example keeps the array
                pass
        elif op == "version":
            arrays["format_version"] = np.int64(draw(st.integers(-3, 2**40)))
    return arrays


def npz_bytes(arrays: dict) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def read_npz(data: bytes) -> dict:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def huge_header_npz(arrays: dict, key: str) -> bytes:
    """The archive with `key`'s .npy header claiming a shape of terabytes over its few bytes of data."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for k, v in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asarray(v))
            raw = member.getvalue()
            if k == key:
                head = io.BytesIO()
                np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False,
                                                             "shape": (2**20, 2**20)})
                raw = head.getvalue() + b"\0" * 64
            zf.writestr(k + ".npy", raw)
    return buf.getvalue()


JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
                    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
                    max_leaves=12)


@st.composite
def mutated_json(draw, seed: dict) -> dict:
    """The seed object with keys removed or their values (or their list items) replaced by any JSON."""
    obj = copy.deepcopy(seed)
    for _ in range(draw(st.integers(1, 3))):
        key = draw(st.sampled_from(sorted(seed)))
        op = draw(st.sampled_from(("drop", "replace", "item")))
        if op == "drop":
            obj.pop(key, None)
        elif op == "replace" or not isinstance(obj.get(key), list) or not obj[key]:
            obj[key] = draw(JSON)
        else:
            obj[key][draw(st.integers(0, len(obj[key]) - 1))] = draw(JSON)
    return obj


@st.composite
def json_file(draw, seed: dict) -> bytes:
    """A damaged JSON file: bytes, any JSON value, the seed mutated, or with bare NaN (not JSON)."""
    kind = draw(st.sampled_from(("bytes", "json", "mutated", "nan")))
    text = json.dumps(seed)
    if kind == "bytes":
        return draw(damaged_bytes(text.encode()))
    if kind == "json":
        return json.dumps(draw(JSON)).encode()
    if kind == "mutated":
        return json.dumps(draw(mutated_json(seed))).encode()
    return json.dumps({**seed, draw(st.sampled_from(sorted(seed))): math.nan}).encode()


# ----------------------------------------------------------------------------- checkpoints
TORCH_VALUES = st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70), st.floats(), st.text(max_size=6),
                         st.lists(st.integers(), max_size=3),
                         random_array().filter(lambda a: a.dtype.kind != "U").map(torch.from_numpy))


def _tensor_with_non_finite(t: torch.Tensor, draw) -> torch.Tensor:
    return torch.from_numpy(with_non_finite(t.numpy(), draw)).to(t.dtype if t.is_floating_point() else torch.float64)


@st.composite
def mutated_payload(draw, seed: dict) -> dict:
    """The checkpoint's payload with a (nested) key removed, its value replaced by another type or tensor
    shape, NaN or inf inside a tensor, or a foreign format number."""
    payload = copy.deepcopy(seed)
    for _ in range(draw(st.integers(1, 3))):
        path, node = [], payload  # walk down a few levels of dicts
        while isinstance(node, dict) and node and draw(st.booleans()):
            key = draw(st.sampled_from(sorted(node)))
            path.append(key)
            if not isinstance(node[key], dict):
                break
            node = node[key]
        if not path:
            path = [draw(st.sampled_from(sorted(payload)))]
        parent = payload
        for k in path[:-1]:
            parent = parent[k]
        key = path[-1]
        op = draw(st.sampled_from(("drop", "replace", "non_finite", "format")))
        if op == "drop":
            parent.pop(key, None)
        elif op == "replace":
            parent[key] = draw(TORCH_VALUES)
        elif op == "non_finite":
            tensors = [(d, k) for d, k in _tensor_slots(payload) if d[k].numel()]
            if tensors:
                d, k = draw(st.sampled_from(tensors))
                d[k] = _tensor_with_non_finite(d[k], draw)
        else:
            payload["format"] = draw(st.one_of(st.integers(-3, 2**40), st.just(torch.ones(3, dtype=torch.int64)),
                                               st.just(True), st.text(max_size=3)))
    return payload


def _tensor_slots(obj):
    """(dict, key) of every tensor inside nested dicts, in a fixed order."""
    if isinstance(obj, dict):
        for k in sorted(obj, key=str):
            if isinstance(obj[k], torch.Tensor):
                yield obj, k
            else:
                yield from _tensor_slots(obj[k])


def torch_bytes(payload: dict) -> bytes:
    buf = io.BytesIO()
    torch.save(payload, buf)
    return buf.getvalue()


def training_payload() -> dict:
    """A training checkpoint's payload as run.py writes it (format included), with a small agent."""
    g = torch.Generator().manual_seed(0)
    return {"format": 1,
            "meta": {"task": "PegInsert", "method": "sac", "env": "factory", "action_dim": 4, "seed": 0,
                     "num_envs": 2, "preset": "quick", "time_obs": True, "obs_dim": 5, "sac": {"lr": 3e-4}},
            "counters": {"transitions": 8, "env_steps": 4, "episodes": 0, "wall_s": 1.5},
            "agent": {"actor": {"0.weight": torch.randn(4, 5, generator=g), "0.bias": torch.zeros(4)},
                      "log_alpha": torch.zeros(()), "actor_optim": {"state": {}, "param_groups": [{"lr": 3e-4}]},
                      # replay data is what the env gave, not weights: NaN there is no damage
                      "buffer": {"capacity": 4, "ptr": 2, "size": 2, "obs": torch.full((2, 5), math.nan)}},
            "rng": {"torch": torch.get_rng_state()}, "plan": {"total_steps": 16}}


@pytest.fixture(scope="module")
def training_seed():
    payload = training_payload()
    return payload, torch_bytes(payload)


def _valid_training(payload):
    assert isinstance(payload["meta"], dict) and isinstance(payload["counters"], dict)
    assert payload["meta"]["task"] == "PegInsert" or isinstance(payload["meta"]["task"], str)


def test_the_seed_training_checkpoint_loads_and_its_replay_nan_is_no_damage(work, training_seed):
    path = _fresh(work, ".pt")
    path.write_bytes(training_seed[1])
    assert load_checkpoint(path)["counters"]["transitions"] == 8


@FUZZ
@given(data=st.data())
def test_training_checkpoint_bytes(work, training_seed, data):
    path = _fresh(work, ".pt")
    path.write_bytes(data.draw(damaged_bytes(training_seed[1])))
    refused_or_valid(load_checkpoint, path, _valid_training)


@FUZZ
@given(data=st.data())
def test_training_checkpoint_content(work, training_seed, data):
    path = _fresh(work, ".pt")
    path.write_bytes(torch_bytes(data.draw(mutated_payload(training_seed[0]))))
    refused_or_valid(load_checkpoint, path, _valid_training)


def test_nan_in_a_checkpoints_weights_is_refused_naming_the_entry(work, training_seed):
    payload = copy.deepcopy(training_seed[0])
    payload["agent"]["actor"]["0.weight"][1, 2] = math.inf
    path = _fresh(work, ".pt")
    path.write_bytes(torch_bytes(payload))
    with pytest.raises(ValueError, match=r"agent\.actor\.0\.weight holds NaN or inf"):
        load_checkpoint(path)


TINY_VAE = VAEConfig(resolution=32, latent_dim=2, channels=(8, 8, 8, 8, 8), groups=8)


@pytest.fixture(scope="module")
def vae_seed(work):
    vae = DenoisingVAE(TINY_VAE, torch.Generator().manual_seed(0))
    opt = torch.optim.Adam(vae.parameters())
    extra = {"order_rng": torch.Generator().get_state(), "noise_rng": torch.Generator().get_state(),
             "noise_device": "cpu", "history": {"train/loss": [1.0]}, "best": {"epoch": 1, "loss": 1.0},
             "timing": {"wall_s": 1.0}, "epochs": 2}
    path = save_vae(work / "vae_seed.pt", vae, TINY_VAE, {"task": "PegInsert", "batch_size": 4, "lr": 1e-3, "seed": 0},
                    optimizer=opt, epoch=1, extra=extra)
    data = path.read_bytes()
    return torch.load(io.BytesIO(data), weights_only=True), data


def _valid_vae(result):
    vae, payload = result
    assert all(bool(torch.isfinite(p).all()) for p in vae.parameters())
    assert isinstance(payload["meta"], dict)


def _load_vae(path):
    return load_vae(path, expect={"task": "PegInsert"})


def test_the_seed_vae_loads(work, vae_seed):
    path = _fresh(work, ".pt")
    path.write_bytes(vae_seed[1])
    _valid_vae(_load_vae(path))


@FUZZ
@given(data=st.data())
def test_vae_bytes(work, vae_seed, data):
    path = _fresh(work, ".pt")
    path.write_bytes(data.draw(damaged_bytes(vae_seed[1])))
    refused_or_valid(_load_vae, path, _valid_vae)


@FUZZ
@given(data=st.data())
def test_vae_content(work, vae_seed, data):
    path = _fresh(work, ".pt")
    path.write_bytes(torch_bytes(data.draw(mutated_payload(vae_seed[0]))))
    refused_or_valid(_load_vae, path, _valid_vae)


def test_a_vae_config_asking_for_terabytes_is_refused_before_any_allocation(work, vae_seed):
    payload = copy.deepcopy(vae_seed[0])
    payload["config"]["channels"] = [2**20] * 5  # its weights would be ~10^13 floats
    path = _fresh(work, ".pt")
    path.write_bytes(torch_bytes(payload))
    with pytest.raises(ValueError, match="config or weights do not fit.*of another shape than the config's"):
        _load_vae(path)


# ----------------------------------------------------------------------------- npz files
@pytest.fixture(scope="module")
def demos_seed(work):
    path = synthetic_demos("PegInsert", num_demos=2, action_dim=4, seed=0).save(work / "demos_seed.npz")
    data = path.read_bytes()
    return read_npz(data), data


@FUZZ
@given(data=st.data())
def test_demonstrations_bytes(work, demos_seed, data):
    path = _fresh(work, ".npz")
    path.write_bytes(data.draw(damaged_bytes(demos_seed[1])))
    refused_or_valid(DemoSet.load, path, _valid_demos)


@FUZZ
@given(data=st.data())
def test_demonstrations_content(work, demos_seed, data):
    path = _fresh(work, ".npz")
    path.write_bytes(npz_bytes(data.draw(mutated_arrays(demos_seed[0]))))
    refused_or_valid(DemoSet.load, path, _valid_demos)


def _valid_demos(d):
    assert isinstance(d, DemoSet) and np.isfinite(d.eta).all() and math.isfinite(d.psi_ref)


@pytest.mark.parametrize("key, value, message", [("psi_ref", np.float64(math.nan), "psi_ref must be one finite number"),
                                                 ("format_version", np.int64(2), "format_version 2"),
                                                 ("task", np.str_("Juggling"), "task must be one of"),
                                                 ("demo_lengths", np.array([151.0, 151.0]), "not whole numbers")])
def test_a_demonstration_file_with_a_bad_field_is_refused(work, demos_seed, key, value, message):
    path = _fresh(work, ".npz")
    path.write_bytes(npz_bytes({**demos_seed[0], key: value}))
    with pytest.raises(ValueError, match=message):
        DemoSet.load(path)


@pytest.fixture(scope="module")
def tables_seed(work):
    g = torch.Generator().manual_seed(0)
    cov = torch.eye(7, dtype=torch.float64).repeat(2, 1, 1)
    tables = KMPTables(mean=torch.randn(11, 6, generator=g, dtype=torch.float64),
                       gain=torch.randn(11, 6, 6, generator=g, dtype=torch.float64), dt=0.1, horizon=2, lam=1.0,
                       beta=1.0, l=1.0, action_dim=6,
                       gmm=GMM(torch.full((2,), 0.5, dtype=torch.float64), torch.zeros(2, 7, dtype=torch.float64), cov),
                       source_sha256="ab", fit_seed=0)
    data = tables.save(work / "tables_seed.npz").read_bytes()
    return read_npz(data), data


def _valid_tables(t):
    assert bool(torch.isfinite(t.mean).all() and torch.isfinite(t.gain).all())
    assert t.mean.shape[0] == t.n_steps + 1 and t.action_dim in (4, 6) and t.horizon >= 0


@FUZZ
@given(data=st.data())
def test_kmp_tables_bytes(work, tables_seed, data):
    path = _fresh(work, ".npz")
    path.write_bytes(data.draw(damaged_bytes(tables_seed[1])))
    refused_or_valid(KMPTables.load, path, _valid_tables)


@FUZZ
@given(data=st.data())
def test_kmp_tables_content(work, tables_seed, data):
    path = _fresh(work, ".npz")
    path.write_bytes(npz_bytes(data.draw(mutated_arrays(tables_seed[0]))))
    refused_or_valid(KMPTables.load, path, _valid_tables)


@pytest.mark.parametrize("which", ["demos", "tables"])
def test_an_npz_header_claiming_terabytes_is_refused_without_allocating(work, demos_seed, tables_seed, which):
    arrays, load = (demos_seed[0], DemoSet.load) if which == "demos" else (tables_seed[0], KMPTables.load)
    path = _fresh(work, ".npz")
    path.write_bytes(huge_header_npz(arrays, "eta" if which == "demos" else "mean"))
    with pytest.raises(ValueError, match="declares"):
        load(path)


# ----------------------------------------------------------------------------- image sets
@pytest.fixture(scope="module")
def imageset_seed(work):
    d = work / "images_seed"
    rng = np.random.default_rng(0)
    with ImageSetWriter(d, num_images=4, resolution=32, task="PegInsert", val_fraction=0.5) as w:
        w.add(rng.integers(0, 255, (4, 32, 32, 3), dtype=np.uint8), rng.normal(size=(4, 4)).astype(np.float32),
              np.array([0, 0, 1, 1]))
    return d


IMAGESET_PARTS = ("meta.json", "images.npy", "state.npy", "episode.npy", "split.npy", "geometry.npy", "pixels.npy")


@st.composite
def damaged_npy(draw, seed: np.ndarray) -> bytes:
    kind = draw(st.sampled_from(("bytes", "array", "non_finite", "npz")))
    buf = io.BytesIO()
    if kind == "bytes":
        np.save(buf, seed)
        return draw(damaged_bytes(buf.getvalue()))
    if kind == "npz":  # an archive where one array belongs
        return npz_bytes({"a": seed})
    with np.errstate(invalid="ignore"):  # (NaN cast to an integer dtype: whatever it becomes)
        np.save(buf, draw(random_array()) if kind == "array" else with_non_finite(seed, draw).astype(seed.dtype))
    return buf.getvalue()


@FUZZ
@given(data=st.data())
def test_image_set_files(work, imageset_seed, data):
    d = _fresh(work, "")
    shutil.copytree(imageset_seed, d)
    part = data.draw(st.sampled_from(IMAGESET_PARTS))
    if part == "meta.json":
        damaged = data.draw(json_file(json.loads((imageset_seed / part).read_text())))
    else:
        damaged = data.draw(damaged_npy(np.load(imageset_seed / part)))
    (d / part).write_bytes(damaged)
    refused_or_valid(ImageSet, d, _valid_image_set)


def _valid_image_set(s):
    assert np.isfinite(s.state).all() and len(s) == s.images.shape[0] == s.split.shape[0]


# ----------------------------------------------------------------------------- sweeps: grid JSON, run directories
GRID = {"tasks": ["PegInsert"], "envs": ["factory"], "action_dims": [4, 6], "methods": ["sac", "kgrl"],
        "seeds": [0, 1], "method_args": {"kgrl": ["--kgrl-recipe", "base"]}, "variants": {"a": ["--label-x"]}}


@pytest.fixture(scope="module")
def sweep_py():
    return load_script("sweep")


def test_the_seed_grid_loads(work, sweep_py):
    path = _fresh(work, ".json")
    path.write_text(json.dumps(GRID))
    assert sweep_py.load_grid(path)["methods"] == ["sac", "kgrl"]


@FUZZ
@given(data=st.data())
def test_grid_json(work, sweep_py, data):
    path = _fresh(work, ".json")
    path.write_bytes(data.draw(json_file(GRID)))
    refused_or_valid(sweep_py.load_grid, path, lambda g: sweep_py.trials_of(g, work))


TRIAL = {"state": "running", "attempts": 1, "host": "elsewhere", "pid": 12345, "submitted_unix": 1.0}
METRICS = {"success_rate": 0.5, "training": {"transitions": 64, "first_transition_unix": 2.0}}


@FUZZ
@given(data=st.data())
def test_a_sweeps_run_directory(work, data):
    """trial.json, metrics.json and curves.jsonl of a trial, as --status and the driver read them."""
    run_dir = _fresh(work, "")
    run_dir.mkdir()
    part = data.draw(st.sampled_from(("trial.json", "metrics.json", "curves.jsonl")))
    if part == "curves.jsonl":
        lines = [json.dumps({"transitions": 8 * i, "success_rate": 0.1}) for i in range(3)]
        if data.draw(st.booleans()):
            lines[data.draw(st.integers(0, 2))] = json.dumps(data.draw(JSON))
        damaged = ("\n".join(lines) + "\n").encode()
        damaged = data.draw(st.sampled_from((damaged, damaged[: data.draw(truncation(len(damaged)))])))
    else:
        damaged = data.draw(json_file(TRIAL if part == "trial.json" else METRICS))
    (run_dir / part).write_bytes(damaged)
    trial = {"name": "t", "run_dir": str(run_dir)}
    # the file named is the one damaged (run_dir alone would name every file in it)
    loader = {"trial.json": lambda p: read_trial_state(p.parent), "metrics.json": run_transitions,
              "curves.jsonl": lambda p: trial_status(trial)}[part]
    refused_or_valid(loader, run_dir / part)
    if part != "metrics.json":  # (with metrics.json the trial is done: the state is not read)
        refused_or_valid(lambda p: trial_status(trial), run_dir / part)


# ----------------------------------------------------------------------------- the CLIs: one line, exit 2
def _cli(*argv):
    return subprocess.run([sys.executable, *map(str, argv)], cwd=ROOT, capture_output=True, text=True, timeout=300)


def _one_line_refusal(out, *needles):
    assert out.returncode == 2, (out.returncode, out.stderr[-2000:])
    assert "Traceback" not in out.stderr, out.stderr[-2000:]
    last = out.stderr.strip().splitlines()[-1]
    for n in needles:
        assert str(n) in last, last


def test_the_command_lines_refuse_damaged_files_in_one_line(work, imageset_seed):
    """The CLI paths no other test covers: a grid, a run's curves, demonstrations to plot, an image set."""
    grid = _fresh(work, ".json")
    grid.write_text('{"tasks": ["PegInsert"], "envs": "factory"')  # cut short
    _one_line_refusal(_cli("train/sweep.py", "--out", _fresh(work, ""), "--grid", grid), "--grid", grid,
                      "not a readable grid file")
    run = _fresh(work, "")
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"method": "sac", "seed": 0}))  # no task, env or action_dim
    _one_line_refusal(_cli("train/plot_runs.py", run, "--out", _fresh(work, ".png")), run / "config.json",
                      "is damaged")
    (run / "config.json").write_text(json.dumps({"method": "sac", "seed": 0, "task": "PegInsert", "env": "factory",
                                                 "action_dim": 4}))
    (run / "curves.jsonl").write_text('{"transitions": 8}\n[1, 2]\n{"transitions": 16}\n')
    _one_line_refusal(_cli("train/plot_runs.py", run, "--out", _fresh(work, ".png")), run / "curves.jsonl",
                      "is damaged")
    demos = _fresh(work, ".npz")
    demos.write_bytes(npz_bytes({"s": np.zeros(3), "eta": np.zeros((3, 6)), "demo_lengths": np.array([3]),
                                 "task": np.str_("PegInsert"), "psi_ref": np.float64(math.nan),
                                 "action_dim": np.int64(4)}))
    _one_line_refusal(_cli("train/plot_kmp.py", "--demos", demos, "--out", _fresh(work, "")), demos,
                      "psi_ref must be one finite number")
    images = _fresh(work, "")
    shutil.copytree(imageset_seed, images)
    (images / "state.npy").write_bytes((imageset_seed / "state.npy").read_bytes()[:100])  # truncated
    _one_line_refusal(_cli("train/train_vae.py", "--images", images, "--out", _fresh(work, ""), "--device", "cpu"),
                      "--images", images, "state.npy")
