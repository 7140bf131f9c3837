"""What the vision methods need before they train, produced on first use and cached per task.

    encoder, info = load_or_make_encoder("PegInsert", VISION_PRESETS["quick"], "runs/cache", "cpu")

1. the image set (`prepare.images`): cache/<task>/images_v<demonstrator version>_r<R>_n<N>_seed<S>_<key>/
   (<key>: a hash of every collection setting and the camera, `collect.collection_key`), collected into a temporary sibling directory and renamed when complete, so an interrupted
   collection leaves no half set under the final name (a stop removes the temporary directory at
   once; a stale one, of a killed run, is removed and redone by the next);
2. the VAE (`vision.train`): cache/<task>/vae_v<version>_r<R>_n<N>_e<E>[...]_seed<S>_<key>/vae.pt (the
   image set's key: a VAE of other images is never taken for this one); a VAE run that was
   interrupted after its first epoch (checkpoints/last.pt but no metrics.json) is resumed, one
   stopped inside its first epoch removed at once (or, killed, by the next run) and restarted;
3. the frozen encoder (`FrozenEncoder`) of that vae.pt, checked against task and resolution.
Steps 1 and 2 each run under their cache entry's lock (`vkgrl_newton.cache`): runs that start
together on an empty cache collect and train once, the others wait and reuse.

Presets: `thesis` as Tables 5.5-5.6 (256 x 256, 130,000 images, 400 epochs, batch 128, eq. 4.48
as written, GroupNorm, Table 5.6's cameras: a GPU job); `quick`, small enough for a 2-core CPU
(64 x 64, 4,096 images, 10 epochs of batch 32, ~5 min), with changes measured on PegInsert's quick
image sets (docs/log/benchmarks.md), without which the VAE never leaves the mean-image plateau on this
budget or does not see the hole well enough:
- no GroupNorm (`VAEConfig.group_norm=False`): with it, a plain autoencoder could not even fit
  64 images in 400 full-batch steps (encoder means equal for all images); without it, it leaves
  the plateau in ~150;
- the KL term weighted 0.01 (`kl_weight`, a beta-VAE): eq. 4.48 sums the squared error over the
  pixels, so at 64 px it is 16x smaller against the same KL than at 256 px; measured at 64 px:
  weight 1 diverged, 1/16 kept ~17 nats and a probe R^2 of ~0.2 / 0.7 on x / y, 0.01 ~35 nats
  and ~0.77 / 0.77;
- batch 32 (4x the gradient steps per image) and 10 epochs: the linear probe of the latent peaked
  at ~9 epochs and fell after (x / y R^2 0.73 / 0.57 at 17 epochs while the reconstruction kept
  improving), so the epoch count is an early stop chosen on the validation episodes' probe;
- the "contact" cameras (sim.camera.CONTACT_CAMERAS): PegInsert's Table 5.6 camera re-aimed at the
  peg's tip with a 48 mm lens, ~1 mm per pixel where the parts meet instead of ~2 (the near-hole
  probe: the latent locates the hole to 0.51 / 0.18 mm on x / y against 0.85 / 0.28 with Table
  5.6's reading, on the same states); GearMesh's looks from beside the hand under the held gear's
  rim at the shaft it must go onto, which Table 5.6's camera (down the gripper axis, onto the
  gear) does not see; NutThread's is Table 5.6's;
- collection rounds of 60 control steps (4 s) instead of whole episodes and 20 % of the episodes
  held out: ~200 episodes in the set instead of ~100, ~30 held-out episodes near the hole for the
  near-hole probe instead of ~7 (one episode's error moved the RMSE by 0.1 mm).
A user's own VAE (`vae_path`) skips 1 and 2.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from ..cache import entry_lock
from ..signals import phase
from ..vision.train import train_vae
from ..vision.vae import FrozenEncoder, VAEConfig, load_vae
from .images import CollectConfig, collect_images, collection_key, default_image_dir

__all__ = ["VisionPreset", "VISION_PRESETS", "load_or_make_encoder", "default_vae_dir", "untrained_preset_latent",
           "load_or_make_probe", "default_probe_path", "PROBE_FITS"]


@dataclass(frozen=True)
class VisionPreset:
    resolution: int
    num_images: int
    vae_epochs: int
    vae_batch_size: int = 128  # Table 5.5
    kl_weight: float = 1.0  # eq. 4.48 as written
    group_norm: bool = True  # 5.6.1
    seed: int = 0
    # the image set's camera (sim.camera.CAMERA_SETS: "table5.6" as the thesis, "contact" aimed at
    # where the parts meet) and sampling; the split and the collection rounds (the collector's defaults)
    camera: str = "table5.6"
    samples_per_pixel: int = 1
    val_fraction: float = 0.1
    episode_steps: int | None = None  # control steps per collection round (None: whole episodes)

    def vae_config(self) -> VAEConfig:
        return VAEConfig(resolution=self.resolution, group_norm=self.group_norm)

    def collect_config(self, task: str, num_envs: int = 16, device: str = "cpu") -> CollectConfig:
        """The image set's collection (16 worlds whatever the run's world count: the set does not
        depend on it)."""
        from ..sim.camera import CAMERA_SETS

        if self.camera not in CAMERA_SETS:
            raise ValueError(f"VisionPreset.camera={self.camera!r}; allowed: {sorted(CAMERA_SETS)}")
        spec = CAMERA_SETS[self.camera][task]
        return CollectConfig(task=task, num_images=self.num_images, resolution=self.resolution, num_envs=num_envs,
                             seed=self.seed, device=device, focal_length=spec.focal_length,
                             camera_rpy_deg=spec.rpy_deg, camera_pos_hand=spec.pos_hand,
                             samples_per_pixel=self.samples_per_pixel,
                             val_fraction=self.val_fraction, episode_steps=self.episode_steps)


VISION_PRESETS = {
    "thesis": VisionPreset(resolution=256, num_images=130_000, vae_epochs=400),
    "quick": VisionPreset(resolution=64, num_images=4_096, vae_epochs=10, vae_batch_size=32, kl_weight=0.01,
                          group_norm=False, camera="contact", val_fraction=0.2, episode_steps=60),
}


def default_vae_dir(cache_dir, task: str, preset: VisionPreset, num_envs: int = 16) -> Path:
    """cache/<task>/vae_v<D>_r<R>_n<N>_e<E>[_b<B>][_kl<w>][_nonorm]_seed<S>_<image key>: the VAE settings
    that differ from the thesis's are in the name, then the image set's key, so a VAE trained with
    other settings or on other images is never taken for it."""
    from ..envs.scripted import DEMONSTRATOR_VERSION  # the image set's key (images.default_image_dir)

    name = f"vae_v{DEMONSTRATOR_VERSION}_r{preset.resolution}_n{preset.num_images}_e{preset.vae_epochs}"
    if preset.vae_batch_size != 128:
        name += f"_b{preset.vae_batch_size}"
    if preset.kl_weight != 1.0:
        name += f"_kl{preset.kl_weight:g}"
    if not preset.group_norm:
        name += "_nonorm"
    return Path(cache_dir) / task / f"{name}_seed{preset.seed}_{collection_key(preset.collect_config(task, num_envs))}"


def load_or_make_encoder(task: str, preset: VisionPreset, cache_dir, device: str, vae_path=None,
                         num_envs: int = 16, log=print, progress: bool = True) -> tuple[FrozenEncoder, dict]:
    """The frozen encoder for `task` and what it came from ({"vae": path, "resolution", "latent_dim"})."""
    if vae_path is not None:
        vae, payload = load_vae(vae_path, expect={"task": task}, map_location=device)
    else:
        collect_config = preset.collect_config(task, num_envs, device)
        image_dir = default_image_dir(cache_dir, collect_config)
        with entry_lock(image_dir, log=log, what=f"the {task} image set"):
            if not (image_dir / "meta.json").is_file():
                if image_dir.exists():
                    raise FileExistsError(f"{image_dir} exists but is not a complete image set (no meta.json); "
                                          "it is not ours to delete: move it away and run again")
                tmp = image_dir.with_name(image_dir.name + ".collecting")
                if tmp.exists():  # our own interrupted collection (the lock says no run is at it now)
                    shutil.rmtree(tmp)
                log(f"collecting {preset.num_images} task-camera images ({preset.resolution} px) -> {image_dir}")
                try:
                    with phase(f"preparing the vision prerequisites: collecting the {task} image set",
                               "the unfinished set is removed"):
                        collect_images(collect_config, tmp, progress=progress, log=log)
                except BaseException:  # a stop or an error: removed now, under the lock, not left for the next run
                    shutil.rmtree(tmp, ignore_errors=True)
                    raise
                tmp.rename(image_dir)
        vae_dir = default_vae_dir(cache_dir, task, preset, num_envs)
        vae_path = vae_dir / "vae.pt"
        with entry_lock(vae_dir, log=log, what=f"the {task} VAE"):
            if not (vae_dir / "metrics.json").is_file():
                resume = (vae_dir / "checkpoints" / "last.pt").is_file()
                if vae_dir.exists() and not resume:  # ours, stopped inside its first epoch: start over
                    shutil.rmtree(vae_dir)
                log(f"{'resuming' if resume else 'training'} the denoising VAE ({preset.vae_epochs} epochs) -> {vae_dir}")
                checkpoint = vae_dir / "checkpoints" / "last.pt"
                try:
                    with phase(f"preparing the vision prerequisites: training the {task} VAE",
                               lambda: f"its last finished epoch is kept in {checkpoint}: the next run resumes it"
                               if checkpoint.is_file() else "stopped in its first epoch: nothing is kept"):
                        train_vae(image_dir, vae_dir, epochs=preset.vae_epochs, batch_size=preset.vae_batch_size,
                                  kl_weight=preset.kl_weight, config=preset.vae_config(), seed=preset.seed,
                                  device=device, resume=resume, progress=progress, log=log)
                except BaseException:  # stopped inside its first epoch: nothing to resume, removed now
                    if not checkpoint.is_file():
                        shutil.rmtree(vae_dir, ignore_errors=True)
                    raise
        vae, payload = load_vae(vae_path, expect={"task": task, "resolution": preset.resolution}, map_location=device)
        log(f"VAE loaded: {vae_path}")
    encoder = FrozenEncoder(vae, camera=payload["meta"].get("camera"))
    return encoder, {"vae": str(vae_path), "resolution": encoder.config.resolution,
                     "latent_dim": encoder.latent_dim}


# --vision-probe-fit: what the near-hole probe is fitted on. images: the VAE's image set's near-hole frames;
# closed_loop: those and the camera controller's own frames (prepare.closed_loop)
PROBE_FITS = ("images", "closed_loop")


def default_probe_path(cache_dir, task: str, preset: VisionPreset, num_envs: int = 16, fit: str = "images") -> Path:
    """cache/<task>/<the VAE's entry>/near_hole_probe_mlp[_closed_loop]_seed<S>.npz: the probe belongs to that VAE and
    its images."""
    if fit not in PROBE_FITS:
        raise ValueError(f"probe fit {fit!r}; allowed: {', '.join(PROBE_FITS)}")
    tag = "_closed_loop" if fit == "closed_loop" else ""
    return default_vae_dir(cache_dir, task, preset, num_envs) / f"near_hole_probe_mlp{tag}_seed{preset.seed}.npz"


_PROBE_ARRAYS = ("x_mean", "x_scale", "y_mean", "y_scale", "num_fit", "held_out_rmse_mm", "held_out_frames",
                 "num_layers")


def load_or_make_probe(task: str, preset: VisionPreset, cache_dir, encoder: FrozenEncoder, num_envs: int = 16,
                       log=print, path=None, fit: str = "images", progress: bool = True):
    """The near-hole probe of the preset's VAE (--vision-probe-obs; tools/ceiling.py's camera estimate): an MLP
    (vision.probe.NearHoleRegressor) from the frozen encoder's latent to the fixed tip minus the held part in the
    image's frame, fitted on every near-hole frame of the VAE's own image set with the set's privileged geometry,
    as a pose estimator is trained in simulation. Made on first use under its cache entry's lock (seconds) and
    written atomically; returns (vision.probe.ProbeMLP on the CPU, its path, {"num_fit", "held_out_rmse_mm",
    "held_out_frames"}: the same model fitted on the set's training episodes and scored on its validation ones,
    image axes x, y, z). `path`: a probe file to load as it is (a run's recorded one), never fitted.

    fit "closed_loop" (--vision-probe-fit): fitted on the image set's frames and the camera controller's own
    (prepare.closed_loop: that controller steering by this VAE's image-set probe, made first if missing, on 128
    episodes of their own: ~5 min once per VAE); its held-out score is on the controller's frames instead: the
    same model fitted on the image set's training episodes and the first CLOSED_LOOP_ROUNDS - 2 rounds, scored on
    the near-hole frames of the last two rounds' episodes, with the image-set probe's score on those frames beside
    it ("image_probe_rmse_mm")."""
    import numpy as np

    from .._io import load_npz
    from ..vision.probe import ProbeMLP

    given = path is not None
    path = Path(path) if given else default_probe_path(cache_dir, task, preset, num_envs, fit)
    base = None
    if fit == "closed_loop" and not given and not path.is_file():  # (its own lock: taken before this entry's)
        base = load_or_make_probe(task, preset, cache_dir, encoder, num_envs, log, progress=progress)[0]
    with entry_lock(path, log=log, what=f"the {task} near-hole probe"):
        if not path.is_file() and not given:
            z, g, train = _image_set_latents(task, preset, cache_dir, encoder, num_envs)
            log(f"fitting the near-hole probe of the {task} VAE ({fit}) -> {path}")
            if fit == "closed_loop":
                _fit_closed_loop_probe(path, task, preset, cache_dir, encoder, base, z, g, train, num_envs, log,
                                       progress)
            else:
                _fit_image_probe(path, preset, z, g, train)
    data = load_npz(path, "near-hole probe", _PROBE_ARRAYS)
    k = int(data["num_layers"])
    try:
        probe = ProbeMLP({"x_mean": data["x_mean"], "x_scale": data["x_scale"], "y_mean": data["y_mean"],
                          "y_scale": data["y_scale"], "weights": [data[f"w{i}"] for i in range(k)],
                          "biases": [data[f"b{i}"] for i in range(k)]})
    except (KeyError, ValueError, RuntimeError, TypeError) as e:
        raise ValueError(f"{path}: not a near-hole probe ({type(e).__name__}: {e}); delete it to fit it again") from None
    if probe.latent_dim != encoder.latent_dim:
        raise ValueError(f"{path}: a probe of a {probe.latent_dim}-d latent, the VAE's is {encoder.latent_dim}-d")
    record = {"num_fit": int(data["num_fit"]), "held_out_frames": int(data["held_out_frames"]),
              "held_out_rmse_mm": dict(zip("xyz", map(float, data["held_out_rmse_mm"])))}
    if "image_probe_rmse_mm" in data:  # a closed-loop probe: the image-set probe on the same held-out frames
        record["image_probe_rmse_mm"] = dict(zip("xyz", map(float, data["image_probe_rmse_mm"])))
        record["closed_loop_episodes"] = int(data["closed_loop_episodes"])
    return probe, path, record


def _image_set_latents(task: str, preset: VisionPreset, cache_dir, encoder: FrozenEncoder, num_envs: int):
    """The VAE's image set as the probe sees it: latents (n, d_z) float64 (the encoder's mean, as the policy gets
    them), geometry (n, 13) float64, and the training split (n,) bool."""
    import numpy as np

    from ..vision.dataset import ImageSet

    images = ImageSet(default_image_dir(cache_dir, preset.collect_config(task, num_envs)),
                      resolution=preset.resolution, task=task)
    if not images.has_geometry:
        raise ValueError(f"{images.dir}: the image set has no geometry (format 1): the probe cannot be fitted")
    z = np.concatenate([encoder(np.asarray(images.images[i:i + 256])).double().cpu().numpy()
                        for i in range(0, len(images), 256)])
    return z, images.geometry.astype(np.float64), images.split == 0


def _probe_errors(reg, z, g):
    """(m, 3) errors, image axes, of the fitted regressor on the near-hole rows of (z, g) (m of them)."""
    from ..vision.probe import near_hole_mask, relative_in_image

    near = near_hole_mask(g)
    return reg(z[near]) - relative_in_image(g[near])


def _save_probe(path, reg, err, **extra) -> None:
    import numpy as np

    from .._io import atomic_savez

    state = reg.state()
    arrays = {k: state[k] for k in ("x_mean", "x_scale", "y_mean", "y_scale")}
    arrays.update({f"w{i}": w for i, w in enumerate(state["weights"])})
    arrays.update({f"b{i}": b for i, b in enumerate(state["biases"])})
    atomic_savez(path, False, num_layers=np.array(len(state["weights"])), num_fit=np.array(state["num_fit"]),
                 held_out_rmse_mm=1e3 * np.sqrt((err ** 2).mean(axis=0)), held_out_frames=np.array(len(err)),
                 **extra, **arrays)


def _fit_image_probe(path, preset: VisionPreset, z, g, train) -> None:
    from ..vision.probe import NearHoleRegressor

    err = _probe_errors(NearHoleRegressor(z[train], g[train], seed=preset.seed), z[~train], g[~train])
    _save_probe(path, NearHoleRegressor(z, g, seed=preset.seed), err)


def _fit_closed_loop_probe(path, task: str, preset: VisionPreset, cache_dir, encoder, base, z, g, train,
                           num_envs: int, log, progress: bool) -> None:
    import numpy as np

    from ..vision.probe import NearHoleRegressor
    from .closed_loop import CLOSED_LOOP_ROUNDS, CLOSED_LOOP_SEED, collect_closed_loop_frames

    if base is None:  # (the closed-loop file existed at our first check and was removed before this lock)
        base = load_or_make_probe(task, preset, cache_dir, encoder, num_envs, log, progress=progress)[0]
    with phase(f"preparing the vision prerequisites: the {task} camera controller's frames for the probe",
               "nothing is written: the next run collects them again"):
        frames = collect_closed_loop_frames(task, encoder, base, cache_dir, num_envs, CLOSED_LOOP_ROUNDS,
                                            CLOSED_LOOP_SEED, log=log, progress=progress)
    zc, gc, late = frames["z"], frames["geometry"], frames["round"] >= CLOSED_LOOP_ROUNDS - 2
    held_out = NearHoleRegressor(np.concatenate([z[train], zc[~late]]), np.concatenate([g[train], gc[~late]]),
                                 seed=preset.seed)
    err = _probe_errors(held_out, zc[late], gc[late])
    import torch

    # (ProbeMLP, float64; on the encoder's device: the collection's CameraLatent moved it there in place)
    image_err = _probe_errors(lambda x: base(torch.as_tensor(x, device=base.x_mean.device)).cpu().numpy(), zc[late],
                              gc[late])
    _save_probe(path, NearHoleRegressor(np.concatenate([z, zc]), np.concatenate([g, gc]), seed=preset.seed), err,
                image_probe_rmse_mm=1e3 * np.sqrt((image_err ** 2).mean(axis=0)),
                closed_loop_episodes=np.array(len(frames["success"])),
                closed_loop_seed=np.array(CLOSED_LOOP_SEED),
                closed_loop_success=np.array(float(frames["success"].mean())))


def untrained_preset_latent(env, preset: str):
    """A CameraLatent of a vision preset's camera with an untrained encoder of the thesis's shape:
    what the benchmarks time (untrained weights cost the same as trained ones)."""
    import dataclasses

    from ..envs.camera_latent import CameraLatent
    from ..vision.vae import DenoisingVAE, FrozenEncoder, VAEConfig
    from .images import collect_camera_spec

    p = VISION_PRESETS[preset]
    camera = dataclasses.asdict(collect_camera_spec(p.collect_config(env.cfg.task)))
    return CameraLatent(env, FrozenEncoder(DenoisingVAE(VAEConfig(resolution=p.resolution)), camera=camera))
