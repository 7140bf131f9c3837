"""Tests of the VAE training loop (vkgrl_newton.vision.train) and its CLI (train/train_vae.py) on a
tiny synthetic image set: 96 images of 32 x 32, a coloured square on a dark background whose
position is a linear function of the state's x, y (size from z, colour from yaw), 12 episodes
of 8 frames, a quarter of the episodes for validation. Tiny widths and batch 16 keep each
training run well under a second of compute."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scripts import load_script
import torch

from vkgrl_newton.vision import FrozenEncoder, ImageSet, ImageSetWriter, VAEConfig, load_vae, train_vae
from vkgrl_newton.vision.train import LOSS_KEYS, PROBE_TARGETS

TASK, RES, N, EPISODES = "PegInsert", 32, 96, 12
CHANNELS = (8, 16, 16, 32, 32)
CONFIG = VAEConfig(resolution=RES, channels=CHANNELS)
TRAIN = dict(batch_size=16, seed=0, config=CONFIG, progress=False, log=lambda *a: None)
OUTPUTS = ("checkpoints/last.pt", "vae.pt", "loss_curves.png", "reconstructions.png", "metrics.json")

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def synthetic_set(directory: Path) -> Path:
    rng = np.random.default_rng(0)
    state = np.column_stack([rng.uniform(-1, 1, (N, 2)), rng.uniform(0, 1, N), rng.uniform(-3, 3, N)])
    state = state.astype(np.float32)  # x, y, z, yaw
    images = np.full((N, RES, RES, 3), 30, np.uint8)
    pixels = np.full((N, 12), np.nan, np.float32)
    for i, (x, y, z, yaw) in enumerate(state):
        half = int(3 + 2 * z)
        cx, cy = int(round(16 + 9 * x)), int(round(16 + 9 * y))  # linear in x, y
        images[i, max(cy - half, 0):cy + half + 1, max(cx - half, 0):cx + half + 1] = (
            int(128 + 120 * np.cos(yaw)), 200, int(128 + 120 * np.sin(yaw)))
        pixels[i, :3] = cx + 0.5, cy + 0.5, (2 * half + 1) ** 2  # the square's centre and area
        pixels[i, 3:6] = 0.0, 0.0, 0.2
        pixels[i, 6:] = 16.0, 30.0, 20.0, 0.0, 0.01, 0.1  # a held part that does not move in the image
    # every frame near the hole: the fixed tip 5 mm x (x, y, z) from the held part, identity camera
    held = np.tile([0.5, 0.0, 0.2], (N, 1))
    geometry = np.column_stack([held, held + 0.005 * state[:, :3], np.zeros((N, 3)), np.tile([0, 0, 0, 1.0], (N, 1))])
    with ImageSetWriter(directory, N, RES, TASK, val_fraction=0.25, seed=0) as writer:
        writer.add(images, state, np.repeat(np.arange(EPISODES), N // EPISODES), geometry.astype(np.float32), pixels)
    return directory


@pytest.fixture(scope="module")
def image_dir(tmp_path_factory) -> Path:
    return synthetic_set(tmp_path_factory.mktemp("imageset") / "set")


@pytest.fixture(scope="module")
def straight(torch_one_thread, image_dir, tmp_path_factory) -> tuple[Path, dict]:
    """A 3-epoch run that never stopped: (run directory, returned metrics)."""
    out = tmp_path_factory.mktemp("vae") / "straight"
    return out, train_vae(image_dir, out, epochs=3, **TRAIN)


def load_cli():
    return load_script("train_vae")


@pytest.fixture(scope="module")
def cli():
    return load_cli()


# ----------------------------------------------------------------------------- a run and its files
def test_run_writes_every_output_and_validation_loss_falls(straight, image_dir):
    out, metrics = straight
    for name in OUTPUTS:
        assert (out / name).is_file(), name
    assert list((out / "tb").glob("events.out.tfevents.*"))
    assert json.loads((out / "metrics.json").read_text()) == json.loads(json.dumps(metrics))

    _, payload = load_vae(out / "checkpoints" / "last.pt")
    assert payload["epoch"] == 3 and payload["optimizer"] is not None
    history = payload["extra"]["history"]
    assert set(history) == {f"{s}/{k}" for s in ("train", "val") for k in LOSS_KEYS}
    assert all(len(v) == 3 for v in history.values())
    assert history["val/loss"][-1] < history["val/loss"][0]
    assert metrics["epochs"] == 3 and metrics["final_val"] == {k: history[f"val/{k}"][-1] for k in LOSS_KEYS}
    best = int(np.argmin(history["val/loss"])) + 1
    assert metrics["best_epoch"] == best and metrics["best_val"]["loss"] == min(history["val/loss"])
    for split in ("final_train", "final_val"):  # loss = recon + kl (eq. 4.48)
        assert metrics[split]["loss"] == pytest.approx(metrics[split]["recon"] + metrics[split]["kl"], rel=1e-5)
    assert metrics["wall_s"] > 0 and metrics["images_per_s"] > 0
    assert metrics["num_train"] + metrics["num_val"] == N and metrics["image_dir"] == str(image_dir.resolve())
    probe = metrics["probe"]
    assert {f"r2_{t}" for t in PROBE_TARGETS} <= set(probe)
    assert all(isinstance(probe[f"r2_{t}"], float) and probe[f"r2_{t}"] <= 1 for t in PROBE_TARGETS)
    assert probe["num_fit"] == metrics["num_train"] and probe["num_score"] == metrics["num_val"]
    near = metrics["probe_near_hole"]  # every frame is near the hole: all validation frames scored
    assert near["num_images"] == metrics["num_val"] and near["num_fit"] == metrics["num_train"]
    assert near["observation_noise_mm"] == 1.0 and near["pixel_baseline_num_images"] == metrics["num_val"]
    for key in ("latent_linear_rmse_mm", "latent_mlp_rmse_mm", "pixel_baseline_rmse_mm", "mean_predictor_rmse_mm"):
        assert set(near[key]) == {"x", "y", "z"} and all(v >= 0 for v in near[key].values()), key
    # the square's centre is x, y up to rounding to the pixel (0.5 px of 9 px per 5 mm: <= 0.28 mm)
    for axis in "xy":
        assert near["pixel_baseline_linear_rmse_mm"][axis] < 0.28 < near["mean_predictor_rmse_mm"][axis]


def test_tensorboard_scalars_per_epoch(straight):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out, _ = straight
    acc = EventAccumulator(str(out / "tb"), size_guidance={"scalars": 0})
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {f"vae/{s}/{k}" for s in ("train", "val") for k in LOSS_KEYS} <= tags
    _, payload = load_vae(out / "checkpoints" / "last.pt")
    events = acc.Scalars("vae/val/loss")
    assert [e.step for e in events] == [1, 2, 3]  # x axis = epoch
    np.testing.assert_allclose([e.value for e in events], payload["extra"]["history"]["val/loss"], rtol=1e-6)


def test_best_weights_load_for_the_rl_side(straight, image_dir):
    out, metrics = straight
    vae, payload = load_vae(out / "vae.pt", expect={"task": TASK, "resolution": RES})
    assert payload["meta"]["latent_dim"] == 16 and payload["meta"]["image_dir"] == str(image_dir.resolve())
    assert payload["epoch"] == metrics["best_epoch"] and payload["optimizer"] is None
    images = ImageSet(image_dir)
    enc = FrozenEncoder(vae)
    mu = enc(images.images[images.val_idx])  # uint8 (N, R, R, 3), camera layout
    assert mu.shape == (len(images.val_idx), 16) and torch.isfinite(mu).all()
    if metrics["best_epoch"] == 3:  # the best is the last epoch: same weights as last.pt
        last, _ = load_vae(out / "checkpoints" / "last.pt")
        for a, b in zip(vae.state_dict().values(), last.state_dict().values()):
            assert torch.equal(a, b)


def test_only_the_training_encoder_input_is_augmented(image_dir, tmp_path, monkeypatch):
    """A marked augmentation (+1: every pixel > 1) must reach the encoder in training (and the
    figure's input row) only; every loss target and every validation / probe input is clean."""
    from vkgrl_newton.vision import train as train_module
    from vkgrl_newton.vision.vae import DenoisingVAE

    encoded, targets = [], []
    real_encode, real_loss = DenoisingVAE.encode, train_module.vae_loss

    def encode(self, x):
        encoded.append(bool(x.min() >= 1.0) if x.max() > 1.0 else False)
        return real_encode(self, x)

    def loss(recon, target, mu, logvar, kl_weight=1.0):
        targets.append(float(target.max()))
        return real_loss(recon, target, mu, logvar, kl_weight=kl_weight)

    monkeypatch.setattr(train_module, "augment", lambda images, generator: images + 1.0)
    monkeypatch.setattr(train_module, "vae_loss", loss)
    monkeypatch.setattr(DenoisingVAE, "encode", encode)
    train_vae(image_dir, tmp_path / "marked", epochs=1, **TRAIN)
    images = ImageSet(image_dir)
    batches = -(-len(images.train_idx) // 16)  # training batches of the one epoch
    val_batches = -(-len(images.val_idx) // 16)
    assert len(targets) == batches + val_batches and max(targets) <= 1.0
    # order: training batches (augmented), validation (clean), figure (augmented), probe (clean),
    # near-hole probe (clean; every frame of this set is near the hole)
    assert encoded == ([True] * batches + [False] * val_batches + [True] + [False] * (batches + val_batches)
                       + [False] * (batches + val_batches))


# ----------------------------------------------------------------------------- resume
def test_resume_continues_the_same_run_bitwise(straight, image_dir, tmp_path):
    """On the CPU every op here is deterministic and all randomness comes from the restored
    generators, so 2 epochs + resume to 3 give the very weights of a straight 3-epoch run."""
    out = tmp_path / "resumed"
    first = train_vae(image_dir, out, epochs=2, **TRAIN)
    assert first["epochs"] == 2
    messages = []
    metrics = train_vae(image_dir, out, epochs=3, resume=True, **{**TRAIN, "log": messages.append})
    assert any("resumed" in m and "epoch 2" in m for m in messages)
    _, resumed = load_vae(out / "checkpoints" / "last.pt")
    _, reference = load_vae(straight[0] / "checkpoints" / "last.pt")
    assert resumed["epoch"] == 3 == metrics["epochs"]
    assert resumed["model"].keys() == reference["model"].keys()
    for name, tensor in reference["model"].items():
        assert torch.equal(resumed["model"][name], tensor), name
    for a, b in zip(resumed["optimizer"]["state"].values(), reference["optimizer"]["state"].values()):
        assert all(torch.equal(a[k], b[k]) for k in ("step", "exp_avg", "exp_avg_sq"))
    assert torch.equal(resumed["extra"]["order_rng"], reference["extra"]["order_rng"])
    assert torch.equal(resumed["extra"]["noise_rng"], reference["extra"]["noise_rng"])
    assert resumed["extra"]["history"] == reference["extra"]["history"]
    assert metrics["final_val"] == straight[1]["final_val"] and metrics["probe"] == straight[1]["probe"]


def test_resume_a_checkpoint_written_before_the_new_options(image_dir, tmp_path):
    """A run checkpointed before group_norm / kl_weight existed (no such keys) resumes as what it
    was: GroupNorm on, KL weight 1; asking it for no GroupNorm is refused, naming the field."""
    import shutil

    from vkgrl_newton._io import load_checkpoint, save_checkpoint

    out = tmp_path / "old"
    train_vae(image_dir, out, epochs=1, **TRAIN)
    path = out / "checkpoints" / "last.pt"
    payload = load_checkpoint(path, required=())
    del payload["config"]["group_norm"]
    del payload["meta"]["kl_weight"]
    payload.pop("format")
    save_checkpoint(path, payload)
    shutil.copytree(out, tmp_path / "old2")
    metrics = train_vae(image_dir, out, epochs=2, resume=True, **TRAIN)
    assert metrics["epochs"] == 2 and metrics["config"]["group_norm"] is True
    no_norm = VAEConfig(resolution=RES, channels=CHANNELS, group_norm=False)
    with pytest.raises(ValueError, match="group_norm"):
        train_vae(image_dir, tmp_path / "old2", epochs=2, resume=True, **{**TRAIN, "config": no_norm})


def test_resume_refuses_another_run(image_dir, tmp_path, straight):
    with pytest.raises(FileNotFoundError, match="last.pt"):
        train_vae(image_dir, tmp_path / "nothing", epochs=3, resume=True, **TRAIN)
    with pytest.raises(ValueError, match="lr"):
        train_vae(image_dir, straight[0], epochs=3, resume=True, **{**TRAIN, "lr": 5e-4})
    with pytest.raises(ValueError, match="trained 3 epochs already"):
        train_vae(image_dir, straight[0], epochs=2, resume=True, **TRAIN)


def test_non_empty_out_dir_without_resume_is_an_error(image_dir, tmp_path):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match=str(out)):
        train_vae(image_dir, out, epochs=1, **TRAIN)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]  # nothing written


# ----------------------------------------------------------------------------- CLI
def test_cli_trains_and_resumes(cli, image_dir, tmp_path, capsys):
    out = tmp_path / "cli"
    common = ["--images", str(image_dir), "--out", str(out), "--device", "cpu", "--no-progress"]
    assert cli.main([*common, "--epochs", "1", "--batch-size", "16", "--channels", "8,16,16,32,32"]) == 0
    assert all((out / name).is_file() for name in OUTPUTS)
    # resume takes batch size, channels, lr and seed from the run; --epochs raises the total
    assert cli.main([*common, "--resume", "--epochs", "2"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["epochs"] == 2 and metrics["batch_size"] == 16 and tuple(metrics["config"]["channels"]) == CHANNELS
    with pytest.raises(SystemExit) as exc:
        cli.main([*common, "--resume", "--batch-size", "32"])
    assert exc.value.code == 2 and "--batch-size 32" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        cli.main([*common, "--resume", "--no-group-norm"])
    assert exc.value.code == 2 and "--no-group-norm" in capsys.readouterr().err
    # the quick preset's settings through the CLI
    out2 = tmp_path / "cli_quick"
    assert cli.main(["--images", str(image_dir), "--out", str(out2), "--device", "cpu", "--no-progress", "--epochs",
                     "1", "--batch-size", "16", "--channels", "8,16,16,32,32", "--kl-weight", "0.01",
                     "--no-group-norm"]) == 0
    metrics = json.loads((out2 / "metrics.json").read_text())
    assert metrics["config"]["group_norm"] is False
    from vkgrl_newton.vision.vae import load_vae

    _, payload = load_vae(out2 / "vae.pt")
    assert payload["meta"]["kl_weight"] == 0.01


@pytest.mark.parametrize("argv,flag", [
    (["--epochs", "0"], "--epochs"),
    (["--epochs", "ten"], "--epochs"),
    (["--batch-size", "0"], "--batch-size"),
    (["--lr", "-1e-3"], "--lr"),
    (["--seed", "-1"], "--seed"),
    (["--channels", "8,16,16"], "--channels"),
    (["--channels", "8,16,16,32,30"], "--channels"),  # not a multiple of 8: VAEConfig says so
    (["--device", "tpu:9"], "--device"),
    (["--images", "MISSING"], "--images"),
    (["--resume"], "--resume"),  # needs --out
])
def test_cli_bad_flags_are_argparse_errors(cli, image_dir, tmp_path, argv, flag, capsys):
    images = [] if "--images" in argv else ["--images", str(image_dir)]
    argv = [a.replace("MISSING", str(tmp_path / "no_such_set")) for a in argv]
    with pytest.raises(SystemExit) as exc:
        cli.main([*images, "--out", str(tmp_path / "o"), "--no-progress", *argv]
                 if flag != "--resume" else [*images, "--no-progress", *argv])
    assert exc.value.code == 2
    assert flag in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_cli_images_is_required_and_out_is_never_reused(cli, image_dir, straight, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--epochs", "1"])
    assert exc.value.code == 2 and "--images" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        cli.main(["--images", str(image_dir), "--out", str(straight[0]), "--epochs", "1", "--device", "cpu"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "--out" in err and str(straight[0]) in err


@pytest.mark.parametrize("value", [0.0, -0.5, float("nan"), float("inf"), True])
def test_kl_weight_must_be_a_positive_finite_number(image_dir, tmp_path, value):
    with pytest.raises(ValueError, match="kl_weight"):
        train_vae(image_dir, tmp_path / "run", epochs=1, kl_weight=value)
    assert not (tmp_path / "run").exists()


def test_kl_weight_scales_the_trained_kl_and_is_part_of_the_run(image_dir, tmp_path, monkeypatch):
    """The weight reaches vae_loss in every training batch, and a resume with another weight is refused."""
    import vkgrl_newton.vision.train as vt

    seen = []
    real = vt.vae_loss

    def spy(*args, kl_weight=1.0, **kwargs):
        seen.append(kl_weight)
        return real(*args, kl_weight=kl_weight, **kwargs)

    monkeypatch.setattr(vt, "vae_loss", spy)
    out = tmp_path / "klw"
    metrics = train_vae(image_dir, out, epochs=1, kl_weight=0.25, **TRAIN)
    assert seen and all(w == 0.25 for w in seen)
    monkeypatch.setattr(vt, "vae_loss", real)
    with pytest.raises(ValueError, match="kl_weight"):
        train_vae(image_dir, out, epochs=2, resume=True, kl_weight=1.0, **TRAIN)
    assert metrics["epochs"] == 1


def test_kl_warmup_epochs_must_be_a_nonnegative_int(image_dir, tmp_path):
    with pytest.raises(ValueError, match="kl_warmup_epochs=-1.*>= 0"):
        train_vae(image_dir, tmp_path / "run", epochs=1, kl_warmup_epochs=-1)
    assert not (tmp_path / "run").exists()  # checked before anything is written


def test_cli_probe_only_reproduces_the_runs_probes_and_writes_nothing(cli, image_dir, straight, capsys):
    out, metrics = straight
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    assert cli.main(["--images", str(image_dir), "--probe-only", str(out / "vae.pt"), "--device", "cpu",
                     "--batch-size", str(TRAIN["batch_size"])]) == 0
    captured = capsys.readouterr()
    probes = json.loads(captured.out)
    assert "near-hole probe, RMSE mm" in captured.err
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    # the same weights, frames and encoder batches as the run's own probe, in one process on one
    # machine: the same float32 latents, the same float64 fits, so the same numbers (to float64
    # rounding of the JSON round trip: none, floats print exactly)
    assert probes["probe"] == json.loads(json.dumps(metrics["probe"]))
    assert probes["probe_near_hole"] == json.loads(json.dumps(metrics["probe_near_hole"]))
    with pytest.raises(SystemExit):
        cli.main(["--images", str(image_dir), "--probe-only", str(out / "missing.pt")])
    assert "--probe-only" in capsys.readouterr().err


def test_probe_vae_refuses_images_of_another_camera(image_dir, straight, tmp_path):
    import shutil

    from vkgrl_newton.vision.train import probe_vae

    out, _ = straight
    other = tmp_path / "other_camera"
    shutil.copytree(image_dir, other)
    meta = json.loads((other / "meta.json").read_text())
    (other / "meta.json").write_text(json.dumps({**meta, "camera": {"focal_length": 48.0}}))
    vae, payload = load_vae(out / "vae.pt")
    from vkgrl_newton.vision.vae import save_vae

    save_vae(tmp_path / "vae.pt", vae, vae.config, {**payload["meta"], "camera": {"focal_length": 24.0}})
    with pytest.raises(ValueError, match="probe it on images of its own camera"):
        probe_vae(tmp_path / "vae.pt", other)
    with pytest.raises(ValueError, match="pool sets of one camera"):  # the synthetic set records none
        probe_vae(out / "vae.pt", [image_dir, other])


def test_probe_vae_pools_image_sets(image_dir, straight, tmp_path, cli, capsys):
    """Several image sets are pooled: fitted on all training splits, scored on all validation
    splits, the episodes of each set counted apart (a copy has the same episode ids). Reference:
    a set pooled with its own copy is every row twice, which leaves a least-squares fit (ridge
    scaled by the row count, as both probes do) and the mean predictor unchanged, so their errors
    equal the set's own to float64 rounding, with twice the frames and episodes."""
    import shutil

    from vkgrl_newton.vision.train import probe_vae

    out, _ = straight
    copy = tmp_path / "copy"
    shutil.copytree(image_dir, copy)
    one = probe_vae(out / "vae.pt", image_dir, batch_size=16)
    two = probe_vae(out / "vae.pt", [image_dir, copy], batch_size=16)
    assert two["image_sets"] == [str(ImageSet(image_dir).dir), str(ImageSet(copy).dir)]
    a, b = one["probe_near_hole"], two["probe_near_hole"]
    assert (b["num_fit"], b["num_images"], b["num_episodes"]) == (2 * a["num_fit"], 2 * a["num_images"],
                                                                   2 * a["num_episodes"])
    # Tolerance. Both sides see bit-identical float32 latents (the same images in the same encoder
    # batches), so only float64 summation order differs: ~1.1e-16 per rounding. The affine maps are
    # ridge fits on standardized inputs, whose normal equations have condition <= (d + r) / r: the
    # near-hole ridge r = 1e-6 with d <= 16 inputs gives <= 1.6e7; the whole-range probe's r = 1e-3 on
    # latents of order one (unit prior, KL weight 1 here) gives ~1e4, so the fits and their RMSE / R^2 move by < ~2e-9 relative; rel 1e-7 keeps a 50x
    # margin, and abs 1e-9 covers an R^2 or RMSE that is itself ~0.
    for key in ("latent_linear_rmse_mm", "mean_predictor_rmse_mm", "pixel_baseline_linear_rmse_mm"):
        for axis in ("x", "y", "z"):
            assert b[key][axis] == pytest.approx(a[key][axis], rel=1e-7, abs=1e-9), (key, axis)
    assert (two["probe"]["num_fit"], two["probe"]["num_score"]) == (2 * one["probe"]["num_fit"],
                                                                     2 * one["probe"]["num_score"])
    for name in PROBE_TARGETS:  # the same derivation as above (ridge 1e-3)
        assert two["probe"][f"r2_{name}"] == pytest.approx(one["probe"][f"r2_{name}"], rel=1e-7, abs=1e-9)
    # the CLI takes several sets only to probe
    assert cli.main(["--images", str(image_dir), str(copy), "--probe-only", str(out / "vae.pt"), "--device",
                     "cpu", "--batch-size", "16"]) == 0
    assert json.loads(capsys.readouterr().out)["probe_near_hole"]["num_images"] == b["num_images"]
    with pytest.raises(SystemExit):
        cli.main(["--images", str(image_dir), str(copy), "--out", str(tmp_path / "run"), "--device", "cpu"])
    assert "several only with --probe-only" in capsys.readouterr().err
