"""Training the denoising VAE on an image set (thesis 4.3.1, 5.6.2; curves of Figs. 6.7-6.9).

    train_vae("runs/images/PegInsert_r256", "runs/vae/PegInsert_r256", epochs=400)

or from the command line, `python train/train_vae.py --images DIR`. Read top to bottom:
`train_vae` sets the run up, trains epoch by epoch, then writes the figures and metrics.

Training (5.6.2, Table 5.5): Adam(lr = 1e-3), minibatches of 128 drawn without replacement from
the image set's TRAIN split in a fresh random order each epoch (the last batch of an epoch may
be smaller), 400 epochs. A batch is read from the memory-mapped images.npy at sorted indices
(the set does not fit in memory; sorted reads are sequential on disk) and converted to floats
on the fly. The encoder sees the augmented image (`vision.augment`, Table 5.5), the decoder is
trained to reproduce the CLEAN image; loss = `vae_loss` (eq. 4.48) with z sampled (eq. 4.44).

KL weight (`kl_weight`, 1 = eq. 4.48 as written, the thesis's setting) multiplies the KL term
of the training loss and of the validation loss. KL warm-up (`kl_warmup_epochs`, 0 = none, the
thesis's setting): the weight rises linearly from 0 to `kl_weight` over the first epochs.
Measured on the quick preset's PegInsert set (64 x 64, 4 096 images): with the thesis's
GroupNorm network and weight 1 the posterior collapsed (KL 0.002 nats, the decoder drew the mean
image, linear-probe R^2 ~ 0); a warm-up only delayed it. What the quick preset uses instead, and
why, is in prepare/vision.py.

Validation, after every epoch, on the set's VALIDATION split (whole episodes the training never
saw, `vision.dataset`): clean images, no augmentation, and z = mu instead of a sample, so the
validation loss is a deterministic function of the weights and comparable from epoch to epoch
(the reconstruction term is that of the mean latent, a little below the sampled one; the KL
term is the same expression as in training). It picks the best weights and is what Figs.
6.7-6.9 (b) show.

Randomness. Nothing uses torch's global RNG. Four generators are seeded from `seed` through
numpy's SeedSequence: the weight init, the batch order (on the CPU, so the batches are the same
on any device), the augmentation and latent noise (on the training device), and the 8 augmented
inputs of the reconstruction figure.

A run directory:

    checkpoints/last.pt  every epoch: weights, Adam state, epoch, and in "extra" the two
                         training generators' states, the loss history, the best epoch and the
                         timing, so that `resume=True` continues the same stream: on the CPU a
                         run resumed after epoch k ends with the same weights, bit for bit, as
                         one that never stopped, given the same number of torch threads (the
                         thread count changes the order of float sums); on CUDA, cuDNN's
                         convolution kernels are not bitwise deterministic, so the two agree
                         only to rounding
    vae.pt               the weights of the epoch with the lowest validation loss, without the
                         optimizer: the file the RL side loads (`load_vae`, `FrozenEncoder`); its
                         meta holds task, resolution, latent_dim and image_dir
    tb/                  tensorboard scalars vae/train/{loss,recon,kl,mse} and vae/val/{...},
                         x axis = epoch (1 = after the first epoch), and vae/perf/images_per_s
    loss_curves.png      KL, reconstruction and total loss per epoch, train and validation
                         (one run's version of thesis Figs. 6.7, 6.8, 6.9)
    reconstructions.png  8 fixed validation images: augmented input, clean image, and the
                         decoder's output from mu of that input, with the weights of vae.pt
    metrics.json         final and best losses, epochs, wall time, images/s, and a linear probe
                         of vae.pt's latent (below)

Linear probe (`vision.probe`): the encoder means of clean images of vae.pt, fitted on the
train split (at most PROBE_MAX_TRAIN images, evenly spaced) and scored on the whole validation
split against the privileged relative target pose x, y, z, cos(yaw), sin(yaw): R^2 per
component as r2_x, r2_y, r2_z, r2_cos_yaw, r2_sin_yaw (null where a component is constant on
the validation split and R^2 is undefined). Near-hole probe (`vision.probe.near_hole_probe`, in
metrics.json as probe_near_hole): on the frames of both splits where the held part is near the
hole, RMSE in mm per image axis of the fixed tip relative to the held part, from the latent
(affine and MLP) and from the privileged pixel measurements; null for an image set collected
without geometry (format 1).

A directory that is not empty is never trained into without `resume=True` (FileExistsError);
figures and metrics.json are the run's own files and are rewritten when a resumed run ends.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from .._io import atomic_write, atomic_write_text, check_meta
from .augment import augment
from .dataset import ImageSet
from .probe import PROBE_AXES, near_hole_mask, near_hole_probe, linear_probe
from .vae import DenoisingVAE, VAEConfig, load_vae, save_vae, to_float_images, vae_loss

__all__ = ["train_vae", "probe_vae", "describe_near_hole_probe", "LOSS_KEYS", "PROBE_TARGETS", "PROBE_MAX_TRAIN", "NUM_FIGURE_IMAGES"]

LOSS_KEYS = ("loss", "recon", "kl", "mse")  # vae_loss's parts, logged per epoch and split
PROBE_TARGETS = ("x", "y", "z", "cos_yaw", "sin_yaw")
PROBE_MAX_TRAIN = 20_000  # probe fit rows: plenty for a 16 -> 5 affine map, bounded encoder time
NUM_FIGURE_IMAGES = 8
CHECKPOINT = Path("checkpoints") / "last.pt"
BEST = "vae.pt"


def train_vae(image_dir, out_dir, *, epochs: int, batch_size: int = 128, lr: float = 1e-3, seed: int = 0,
              device: str | torch.device = "cpu", config: VAEConfig | None = None, resume: bool = False,
              progress: bool = True, log=print, kl_warmup_epochs: int = 0, kl_weight: float = 1.0) -> dict:
    """Train a denoising VAE on the image set in `image_dir`, writing the run to `out_dir`.

    `epochs` is the total, counted from the start of the run (a resumed run trains the rest).
    `config` defaults to VAEConfig at the set's resolution; given, its resolution must be the
    set's. With `resume=True` the run continues from out_dir/checkpoints/last.pt, which must
    belong to the same image set, config, batch size, lr and seed (ValueError naming the fields)
    and to the same device type. Returns what metrics.json holds.

    Every check runs before anything is written. A KeyboardInterrupt stops after the last
    finished epoch's checkpoint; `resume=True` continues from there.
    """
    # ------------------------------------------------------------------ arguments and the image set
    for name, v in (("epochs", epochs), ("batch_size", batch_size)):
        if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1):
            raise ValueError(f"train_vae: {name}={v!r}; allowed: an integer >= 1")
    if not (isinstance(lr, (int, float)) and math.isfinite(lr) and lr > 0):
        raise ValueError(f"train_vae: lr={lr!r}; allowed: a finite number > 0")
    if not (isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and seed >= 0):
        raise ValueError(f"train_vae: seed={seed!r}; allowed: an integer >= 0")
    if not (isinstance(kl_warmup_epochs, (int, np.integer)) and kl_warmup_epochs >= 0):
        raise ValueError(f"train_vae: kl_warmup_epochs={kl_warmup_epochs!r}; allowed: an integer >= 0")
    if not (isinstance(kl_weight, (int, float)) and not isinstance(kl_weight, bool) and math.isfinite(kl_weight)
            and kl_weight > 0):
        raise ValueError(f"train_vae: kl_weight={kl_weight!r}; allowed: a finite number > 0 (1 = eq. 4.48)")
    epochs, batch_size, seed, lr = int(epochs), int(batch_size), int(seed), float(lr)
    device = torch.device(device)
    images = ImageSet(image_dir)
    if config is None:
        config = VAEConfig(resolution=images.resolution)
    elif config.resolution != images.resolution:
        raise ValueError(f"train_vae: config.resolution={config.resolution} but image set {images.dir} has "
                         f"resolution {images.resolution}")
    train_idx, val_idx = images.train_idx, images.val_idx
    if len(train_idx) < 2 or len(val_idx) < 2:
        raise ValueError(f"image set {images.dir} has {len(train_idx)} training and {len(val_idx)} validation "
                         "images; training needs at least 2 of each (collect it with val_fraction > 0)")
    meta = {"task": images.task, "image_dir": str(images.dir.resolve()), "image_count": len(images),
            "num_train": len(train_idx), "num_val": len(val_idx), "batch_size": batch_size, "lr": lr, "seed": seed,
            "resolution": config.resolution, "latent_dim": config.latent_dim, "kl_warmup_epochs": int(kl_warmup_epochs),
            "kl_weight": float(kl_weight), "camera": images.meta.get("camera")}

    out = Path(out_dir)
    ckpt_path, best_path = out / CHECKPOINT, out / BEST
    payload = None
    if resume:
        if not ckpt_path.is_file():
            raise FileNotFoundError(f"cannot resume: {ckpt_path} does not exist (no run to continue in {out})")
        _, payload = load_vae(ckpt_path, map_location="cpu")  # a damaged file is a ValueError here
        _check_resume(payload, meta, config, device, epochs, ckpt_path)
    elif out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(f"output directory {out} is not empty; a run is never trained into without "
                              "resume=True (--resume): resume it or choose another directory")

    # ------------------------------------------------------------------ model, optimizer, generators
    s_init, s_order, s_noise, s_figure = (int(s) for s in np.random.SeedSequence(seed).generate_state(4))
    vae = DenoisingVAE(config, torch.Generator().manual_seed(s_init)).to(device)
    opt = torch.optim.Adam(vae.parameters(), lr=lr)
    order_gen = torch.Generator().manual_seed(s_order)  # batch order (CPU: indexes the memmap)
    noise_gen = torch.Generator(device).manual_seed(s_noise)  # augmentations and eps of eq. 4.44
    history: dict[str, list[float]] = {f"{split}/{k}": [] for split in ("train", "val") for k in LOSS_KEYS}
    best = {"epoch": 0, "loss": math.inf}
    timing = {"wall_s": 0.0, "train_s": 0.0, "train_images": 0}
    start_epoch = 0
    if payload is not None:
        vae.load_state_dict(payload["model"])
        opt.load_state_dict(payload["optimizer"])  # moves Adam's moments to the parameters' device
        extra = payload["extra"]
        order_gen.set_state(extra["order_rng"])
        noise_gen.set_state(extra["noise_rng"])
        history = {k: list(v) for k, v in extra["history"].items()}
        best, timing = dict(extra["best"]), dict(extra["timing"])
        start_epoch = int(payload["epoch"])
        log(f"resumed {out} after epoch {start_epoch} of {epochs}")
    out.mkdir(parents=True, exist_ok=True)

    def checkpoint(epoch: int) -> None:
        extra = {"order_rng": order_gen.get_state(), "noise_rng": noise_gen.get_state().cpu(),
                 "noise_device": device.type, "history": history, "best": best, "timing": timing,
                 "epochs": epochs}
        save_vae(ckpt_path, vae, config, meta, optimizer=opt, epoch=epoch, extra=extra)

    # ------------------------------------------------------------------ the epochs
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(str(out / "tb"), purge_step=start_epoch + 1 if payload is not None else None)
    bar = tqdm(total=epochs * len(train_idx), initial=start_epoch * len(train_idx), unit="img",
               disable=not progress, desc=f"VAE {images.task} r{config.resolution}")
    try:
        for epoch in range(start_epoch + 1, epochs + 1):
            # train: one pass over the train split in a fresh order
            t0 = time.perf_counter()
            vae.train()
            sums = torch.zeros(len(LOSS_KEYS), device=device)
            order = train_idx[torch.randperm(len(train_idx), generator=order_gen).numpy()]
            for start in range(0, len(order), batch_size):
                idx = np.sort(order[start:start + batch_size])
                clean = _read_batch(images.images, idx, device)
                recon, mu, logvar = vae(augment(clean, noise_gen), noise_gen)  # encoder input: augmented
                # KL warm-up: the weight rises linearly 0 -> kl_weight over the first kl_warmup_epochs
                ramp = min(1.0, (epoch - 1 + start / len(order)) / kl_warmup_epochs) if kl_warmup_epochs else 1.0
                beta = kl_weight * ramp
                parts = vae_loss(recon, clean, mu, logvar, kl_weight=beta)  # decoder target: the clean image
                opt.zero_grad(set_to_none=True)
                parts["loss"].backward()
                opt.step()
                sums += torch.stack([parts[k].detach() for k in LOSS_KEYS]) * len(idx)
                bar.update(len(idx))
            train = dict(zip(LOSS_KEYS, (sums / len(order)).tolist()))  # one sync per epoch
            t1 = time.perf_counter()
            # validate: clean images, z = mu (deterministic)
            val = _evaluate(vae, images.images, val_idx, batch_size, device, kl_weight)
            if not (math.isfinite(train["loss"]) and math.isfinite(val["loss"])):
                raise FloatingPointError(f"VAE loss is not finite in epoch {epoch} (train {train['loss']}, "
                                         f"validation {val['loss']}); the run in {out} stops at epoch "
                                         f"{epoch - 1}: train again with a lower learning rate")
            timing["train_s"] += t1 - t0
            timing["train_images"] += len(order)
            timing["wall_s"] += time.perf_counter() - t0

            for k in LOSS_KEYS:
                history[f"train/{k}"].append(train[k])
                history[f"val/{k}"].append(val[k])
                writer.add_scalar(f"vae/train/{k}", train[k], epoch)
                writer.add_scalar(f"vae/val/{k}", val[k], epoch)
            writer.add_scalar("vae/perf/images_per_s", len(order) / max(t1 - t0, 1e-9), epoch)
            if val["loss"] < best["loss"]:
                best = {"epoch": epoch, "loss": val["loss"]}
                save_vae(best_path, vae, config, meta, epoch=epoch)
            checkpoint(epoch)  # after vae.pt: a crash in between repeats this epoch identically
            bar.set_postfix({"epoch": epoch, "train": f"{train['loss']:.4g}", "val": f"{val['loss']:.4g}",
                             "best": best["epoch"]}, refresh=False)
    except KeyboardInterrupt:
        if ckpt_path.is_file():
            log(f"interrupted; {ckpt_path} holds the last finished epoch (resume=True / --resume continues)")
        raise
    finally:
        bar.close()
        writer.close()

    # ------------------------------------------------------------------ figures, probe, metrics
    best_vae, _ = load_vae(best_path, map_location=device)  # what the RL side will load
    figure_idx = val_idx[np.unique(np.linspace(0, len(val_idx) - 1, NUM_FIGURE_IMAGES).round().astype(int))]
    _save_png(out / "loss_curves.png", _plot_losses(history, best["epoch"], f"{images.task} r{config.resolution}",
                                                    kl_weight))
    _save_png(out / "reconstructions.png",
              _plot_reconstructions(best_vae, images.images, figure_idx, torch.Generator(device).manual_seed(s_figure),
                                    device, best["epoch"]))
    probe = _probe(best_vae, images, batch_size, device)
    probe_near = _probe_near_hole(best_vae, images, batch_size, device, seed)
    final = {split: {k: history[f"{split}/{k}"][-1] for k in LOSS_KEYS} for split in ("train", "val")}
    best_val = {k: history[f"val/{k}"][best["epoch"] - 1] for k in LOSS_KEYS}
    metrics = {
        "task": images.task, "resolution": config.resolution, "latent_dim": config.latent_dim,
        "image_dir": meta["image_dir"], "num_train": len(train_idx), "num_val": len(val_idx),
        "epochs": len(history["val/loss"]), "batch_size": batch_size, "lr": lr, "seed": seed, "device": str(device),
        "config": dataclasses.asdict(config),
        "final_train": final["train"], "final_val": final["val"], "best_epoch": best["epoch"], "best_val": best_val,
        "wall_s": timing["wall_s"], "train_s": timing["train_s"],
        "images_per_s": timing["train_images"] / max(timing["train_s"], 1e-9),  # training passes only
        "probe": probe, "probe_near_hole": probe_near,
        "files": {"vae": str(best_path), "checkpoint": str(ckpt_path), "loss_curves": str(out / "loss_curves.png"),
                  "reconstructions": str(out / "reconstructions.png"), "tensorboard": str(out / "tb")},
    }
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2) + "\n", overwrite=True)
    log(f"done: best validation loss {best['loss']:.5g} at epoch {best['epoch']} -> {best_path}; "
        "validation probe R^2 " + ", ".join(f"{k}={_fmt(probe['r2_' + k])}" for k in PROBE_TARGETS))
    log(describe_near_hole_probe(probe_near))
    return metrics


def probe_vae(vae_path, image_dir, batch_size: int = 128, device: str | torch.device = "cpu", seed: int = 0) -> dict:
    """Both probes of a trained VAE on an image set (its own or another of the same task and
    resolution): {"probe": the whole-range linear probe, "probe_near_hole": the near-hole probe}.

    `image_dir` may be a list of image sets: both probes are then fitted on the frames of all their
    training splits and scored on all their validation splits (episodes told apart per set). A
    probe's readout is fitted on finite data: measured on PegInsert's quick VAE, the near-hole MLP's
    x error on the same 695 held-out frames fell from ~0.6 mm fitted on one set's ~1 400 frames to
    0.49 on two sets' 2 865 and 0.46 on 4 231 (docs/log/benchmarks.md), so pooling sets the VAE never
    saw measures what the latent holds rather than the readout's sample size."""
    dirs = list(image_dir) if isinstance(image_dir, (list, tuple)) else [image_dir]
    if not dirs:
        raise ValueError("probe_vae: image_dir is an empty list; allowed: one image set or a list of them")
    sets = [ImageSet(d) for d in dirs]
    first = sets[0]
    vae, payload = load_vae(vae_path, expect={"task": first.task, "resolution": first.resolution},
                            map_location=device)
    trained_on = payload["meta"].get("camera")
    for images in sets:
        if (images.task, images.resolution) != (first.task, first.resolution):
            raise ValueError(f"probe_vae: image set {images.dir} is {images.task} at {images.resolution} px, "
                             f"{first.dir} is {first.task} at {first.resolution} px: pool sets of one task and resolution")
        shown = images.meta.get("camera")
        if shown != first.meta.get("camera"):
            raise ValueError(f"probe_vae: image sets {first.dir} and {images.dir} were taken with different cameras "
                             f"({first.meta.get('camera')} and {shown}): pool sets of one camera")
        if trained_on is not None and shown is not None and trained_on != shown:
            raise ValueError(f"VAE {vae_path} was trained on images of camera {trained_on}, the image set {images.dir} "
                             f"was taken with {shown}: probe it on images of its own camera")
    out = {"probe": _probe(vae, sets, batch_size, device),
           "probe_near_hole": _probe_near_hole(vae, sets, batch_size, device, seed)}
    if len(sets) > 1:
        out["image_sets"] = [str(images.dir) for images in sets]
    return out


def describe_near_hole_probe(p: dict | None) -> str:
    """One line of the near-hole probe for a log."""
    if p is None:
        return "near-hole probe: not measured (the image set has no geometry: collected before format 2)"
    if p.get("skipped"):
        return f"near-hole probe: skipped ({p['skipped']})"

    def xyz(key):
        d, se = p.get(key), p.get(key + "_se")
        if d is None:
            return "n/a"
        return " / ".join(f"{d[a]:.2f}" + (f"+-{se[a]:.2f}" if se else "") for a in PROBE_AXES)

    episodes = f" of {p['num_episodes']} episodes" if "num_episodes" in p else ""
    return (f"near-hole probe, RMSE mm x / y / z on {p['num_images']} held-out frames{episodes} (noise "
            f"{p['observation_noise_mm']:g} mm per axis): latent linear {xyz('latent_linear_rmse_mm')}, "
            f"latent MLP {xyz('latent_mlp_rmse_mm')}, pixel baseline {xyz('pixel_baseline_rmse_mm')}, "
            f"mean predictor {xyz('mean_predictor_rmse_mm')}")


# ----------------------------------------------------------------------------- helpers
def _check_resume(payload: dict, meta: dict, config: VAEConfig, device: torch.device, epochs: int, path: Path) -> None:
    """ValueError unless the checkpoint belongs to this run (the image set may have moved)."""
    if payload.get("extra") is None or payload.get("optimizer") is None or payload.get("epoch") is None:
        raise ValueError(f"cannot resume from {path}: it holds weights only, not a training checkpoint of train_vae")
    saved = {k: v for k, v in payload["meta"].items() if k != "image_dir"}
    saved.setdefault("kl_warmup_epochs", 0)  # written before these options existed
    saved.setdefault("kl_weight", 1.0)
    saved.setdefault("camera", None)
    check_meta(saved, {k: v for k, v in meta.items() if k != "image_dir"}, path)
    saved_config = {"group_norm": True, **payload["config"]}  # written before group_norm existed: it had GroupNorm
    if saved_config != dataclasses.asdict(config):
        check_meta({"config": saved_config}, {"config": dataclasses.asdict(config)}, path)
    if payload["extra"]["noise_device"] != device.type:
        raise ValueError(f"checkpoint {path} was trained on {payload['extra']['noise_device']}; resume it there "
                         f"(device={device.type!r} given): the noise generator's state is device-specific")
    if epochs < payload["epoch"]:
        raise ValueError(f"checkpoint {path} has trained {payload['epoch']} epochs already, more than epochs={epochs}")


def _read_batch(images: np.ndarray, idx: np.ndarray, device: torch.device) -> torch.Tensor:
    """uint8 rows `idx` (sorted) of the memmap -> float (n, 3, R, R) in [0, 1] on `device`
    (the uint8 batch is moved, a quarter of the bytes)."""
    return to_float_images(torch.from_numpy(images[idx]).to(device))


@torch.no_grad()
def _evaluate(vae: DenoisingVAE, images: np.ndarray, idx: np.ndarray, batch_size: int, device,
              kl_weight: float = 1.0) -> dict[str, float]:
    """Mean loss parts over `idx`: clean input, z = mu, no augmentation; `loss` weighs the KL by
    `kl_weight` (the objective trained after any warm-up)."""
    vae.eval()
    sums = torch.zeros(len(LOSS_KEYS), device=device)
    for start in range(0, len(idx), batch_size):
        clean = _read_batch(images, idx[start:start + batch_size], device)
        mu, logvar = vae.encode(clean)
        parts = vae_loss(vae.decode(mu), clean, mu, logvar, kl_weight=kl_weight)
        sums += torch.stack([parts[k] for k in LOSS_KEYS]) * clean.shape[0]
    return dict(zip(LOSS_KEYS, (sums / len(idx)).tolist()))


@torch.no_grad()
def _encode(vae: DenoisingVAE, images: np.ndarray, idx: np.ndarray, batch_size: int, device) -> np.ndarray:
    """Encoder means of the clean images `idx`: (n, d_z) float64."""
    vae.eval()
    return np.concatenate([vae.encode(_read_batch(images, idx[s:s + batch_size], device))[0].double().cpu().numpy()
                           for s in range(0, len(idx), batch_size)])


def _probe(vae: DenoisingVAE, sets: ImageSet | list[ImageSet], batch_size: int, device) -> dict:
    """Linear probe latent -> (x, y, z, cos yaw, sin yaw): fit on the train split(s), R^2 on the
    validation split(s) (several sets pooled)."""
    sets = [sets] if isinstance(sets, ImageSet) else sets
    cap = max(1, PROBE_MAX_TRAIN // len(sets))

    def targets(images: ImageSet, idx: np.ndarray) -> np.ndarray:
        s = images.state[idx].astype(np.float64)
        return np.column_stack([s[:, 0], s[:, 1], s[:, 2], np.cos(s[:, 3]), np.sin(s[:, 3])])

    zt, yt, zv, yv = [], [], [], []
    for images in sets:
        train_idx = images.train_idx
        if len(train_idx) > cap:
            train_idx = train_idx[np.linspace(0, len(train_idx) - 1, cap).round().astype(int)]
        zt.append(_encode(vae, images.images, train_idx, batch_size, device))
        yt.append(targets(images, train_idx))
        zv.append(_encode(vae, images.images, images.val_idx, batch_size, device))
        yv.append(targets(images, images.val_idx))
    zt, yt, zv, yv = (np.concatenate(a) for a in (zt, yt, zv, yv))
    fit = linear_probe(zt, yt, zv, yv)
    out: dict = {"num_fit": len(zt), "num_score": len(zv)}
    out.update({f"r2_{name}": _finite(r) for name, r in zip(PROBE_TARGETS, fit["r2"])})
    out.update({f"r2_train_{name}": _finite(r) for name, r in zip(PROBE_TARGETS, fit["r2_train"])})
    return out


def _probe_near_hole(vae: DenoisingVAE, sets: ImageSet | list[ImageSet], batch_size: int, device,
                     seed: int) -> dict | None:
    """The near-hole probe on every near-hole frame of the train (fit) and validation (score)
    splits, of one set or of several pooled (episode ids made distinct per set)."""
    sets = [sets] if isinstance(sets, ImageSet) else sets
    if not all(images.has_geometry for images in sets):
        return None
    cols: dict[str, list] = {k: [] for k in ("zt", "gt", "pt", "zv", "gv", "pv", "ev")}
    for k, images in enumerate(sets):
        near = near_hole_mask(images.geometry)
        tr, va = images.train_idx[near[images.train_idx]], images.val_idx[near[images.val_idx]]
        for key, idx in (("zt", tr), ("zv", va)):
            cols[key].append(_encode(vae, images.images, idx, batch_size, device) if len(idx)
                             else np.zeros((0, vae.config.latent_dim)))
        cols["gt"].append(images.geometry[tr])
        cols["gv"].append(images.geometry[va])
        cols["pt"].append(images.pixels[tr])
        cols["pv"].append(images.pixels[va])
        cols["ev"].append(np.column_stack([np.full(len(va), k), images.episode[va]]))  # (set, episode)
    c = {key: np.concatenate(v) for key, v in cols.items()}
    episodes = np.unique(c["ev"], axis=0, return_inverse=True)[1].reshape(-1)  # one id per (set, episode)
    return near_hole_probe(c["zt"], c["gt"], c["zv"], c["gv"], c["pt"], c["pv"], seed=seed, episodes_val=episodes)


def _finite(v: float) -> float | None:
    """JSON has no NaN: an undefined R^2 is null."""
    return float(v) if math.isfinite(v) else None


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def _plot_losses(history: dict[str, list[float]], best_epoch: int, title: str, kl_weight: float = 1.0):
    """Three panels as thesis Figs. 6.7 (KL), 6.8 (reconstruction), 6.9 (total): train and val per epoch."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    epochs = np.arange(1, len(history["val/loss"]) + 1)
    fig = Figure(figsize=(15, 3.8))
    axes = fig.subplots(1, 3)
    for ax, (key, name) in zip(axes, (("kl", "KL loss"), ("recon", "reconstruction loss"), ("loss", "total loss"))):
        train, val = np.asarray(history[f"train/{key}"]), np.asarray(history[f"val/{key}"])
        ax.plot(epochs, train, label="train (augmented input, sampled z)", marker="." if len(epochs) < 30 else None)
        ax.plot(epochs, val, label="validation (clean input, z = mu)", marker="." if len(epochs) < 30 else None)
        both = np.concatenate([train, val])
        if (both > 0).all() and both.max() / both.min() > 10:  # log-y where the curve spans decades
            ax.set_yscale("log")
        ax.axvline(best_epoch, color="0.6", ls=":", lw=1)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel("epoch")
        ax.set_ylabel(name)
        ax.set_title(name)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    objective = "eq. 4.48" if kl_weight == 1.0 else f"eq. 4.48 with the KL weighted {kl_weight:g}"
    fig.suptitle(f"VAE {title}: per-sample loss ({objective}), best validation epoch {best_epoch} (dotted)")
    fig.tight_layout()
    return fig


@torch.no_grad()
def _plot_reconstructions(vae: DenoisingVAE, images: np.ndarray, idx: np.ndarray, generator: torch.Generator,
                          device, best_epoch: int):
    """Rows: augmented input, clean image, decoder output from mu of the augmented input."""
    from matplotlib.figure import Figure

    vae.eval()
    clean = _read_batch(images, idx, device)
    noisy = augment(clean, generator)
    recon = vae.decode(vae.encode(noisy)[0])
    rows = [t.permute(0, 2, 3, 1).clamp(0, 1).cpu().numpy() for t in (noisy, clean, recon)]
    n, r = len(idx), clean.shape[-1]
    pad = max(1, r // 32)
    grid = np.ones((3 * r + 4 * pad, n * r + (n + 1) * pad, 3))
    for i, row in enumerate(rows):
        for j, img in enumerate(row):
            y, x = pad + i * (r + pad), pad + j * (r + pad)
            grid[y:y + r, x:x + r] = img
    fig = Figure(figsize=(1.6 * n + 1.6, 1.6 * 3 + 0.6))
    ax = fig.subplots()
    ax.imshow(grid, interpolation="nearest")
    ax.set_yticks([pad + i * (r + pad) + r / 2 for i in range(3)],
                  ["augmented input", "clean image", "reconstruction\nf(mu(input))"])
    ax.set_xticks([pad + j * (r + pad) + r / 2 for j in range(n)], [f"#{i}" for i in idx], fontsize=7)
    ax.tick_params(length=0)
    for s in ax.spines.values():
        s.set_visible(False)
    ax.set_title(f"validation images, weights of epoch {best_epoch} (vae.pt)")
    fig.tight_layout()
    return fig


def _save_png(path: Path, fig) -> None:
    """The run's own figure, written atomically (rewritten when a resumed run ends). Figures
    are made with matplotlib's Figure, which renders with Agg, not pyplot: no global backend or
    figure state is touched."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write(path, True, lambda f: f.write(buf.getvalue()), suffix=".png")
