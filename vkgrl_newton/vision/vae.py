"""The denoising variational autoencoder of Vision-KGRL (thesis 4.3.1, eqs. 4.37-4.48; 5.6).

Read top to bottom: config, network, loss, the frozen encoder the policy uses, checkpoints.

Images. The network works on float tensors (N, 3, R, R) with values in [0, 1], R = the square
camera resolution (256 in the thesis, Table 5.6); the camera and the image set hold uint8
(N, H, W, 3), which `to_float_images` converts. Denoising (eq. 4.39): the encoder sees an
augmented image (`vision.augment`), the decoder is trained to reproduce the clean one.

Network (5.6.1, Fig. 5.2). Encoder: 5 x [Conv2d(k=4, s=2, p=1) -> LeakyReLU -> GroupNorm(8)],
in that order as the thesis writes it, then flatten and two linear heads for mu and log sigma^2
(d_z = 16). Decoder, the mirror: linear -> (C5, R/32, R/32) -> 4 x [ConvTranspose2d(k=4, s=2,
p=1) -> LeakyReLU -> GroupNorm(8)] -> ConvTranspose2d(k=4, s=2, p=1) to 3 channels -> sigmoid.
The thesis gives neither the channel widths nor the Leaky ReLU slope: (32, 64, 128, 256, 256) and
0.2 are our choice. `VAEConfig.group_norm=False` drops the GroupNorm layers (the CPU `quick`
preset's setting, prepare/vision.py says why).

Loss (eq. 4.48, with sigma_o^2 of eq. 4.42 absorbed into the unit weight of the squared error):
    L = 1/N sum_t [ ||o_t - f(z_t)||^2 + 1/2 sum_j (mu_tj^2 + sigma_tj^2 - log sigma_tj^2 - 1) ]
with z_t = mu + sigma * eps (eq. 4.44) and ||.||^2 summed over all 3 R^2 pixel values.

Policy side (eq. 4.49, 5.6.1): the latent is the encoder mean mu of the clean image, with the
encoder frozen (`FrozenEncoder`).

Checkpoint (`save_vae` / `load_vae`, written by `_io.save_checkpoint`):
    format      _io.CHECKPOINT_FORMAT
    kind        "denoising_vae"
    vae_format  VAE_FORMAT
    config      dataclasses.asdict(VAEConfig)
    meta        what the VAE is (task, image set, ...), plus resolution and latent_dim
    model       DenoisingVAE.state_dict()
    optimizer   the optimizer's state_dict or None
    epoch       int or None
    extra       a dict the trainer keeps with the weights (RNG states, loss history, ...) or None
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .._io import check_finite, load_checkpoint, one_line, save_checkpoint, short_repr

__all__ = [
    "VAEConfig",
    "DenoisingVAE",
    "FrozenEncoder",
    "to_float_images",
    "kl_divergence",
    "vae_loss",
    "save_vae",
    "load_vae",
    "VAE_KIND",
    "VAE_FORMAT",
]

VAE_KIND = "denoising_vae"
VAE_FORMAT = 1
NUM_LAYERS = 5  # conv layers of the encoder and transposed conv layers of the decoder (5.6.1)
_RESOLUTIONS = tuple(2**k for k in range(5, 10))  # 32 .. 512: R / 2^5 >= 1
VAE_RESOLUTIONS = _RESOLUTIONS  # public: the image sizes a VAE (and so an image set for one) can have


# ----------------------------------------------------------------------------- config
@dataclass(frozen=True)
class VAEConfig:
    resolution: int = 256  # square RGB images R x R (Table 5.6)
    latent_dim: int = 16  # d_z (5.6)
    # Output channels of the 5 encoder convs (the decoder mirrors them). Our choice: the thesis
    # gives 5 layers "as the number of feature channels increases" but no widths.
    channels: tuple[int, ...] = (32, 64, 128, 256, 256)
    leaky_slope: float = 0.2  # our choice; the thesis says Leaky ReLU without a slope
    groups: int = 8  # GroupNorm groups (5.6.1); every width must be divisible by it
    # GroupNorm after every hidden layer as 5.6.1 (True), or none (False): measured on the quick
    # preset's 64 px PegInsert images, the normalized net stays on the mean-image plateau (encoder
    # means nearly equal for every image) for thousands of steps, the unnormalized one leaves it
    # within ~150; the CPU preset uses False (prepare.vision)
    group_norm: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "channels", tuple(self.channels))  # a list from JSON or a checkpoint
        if not _is_int(self.resolution) or self.resolution not in _RESOLUTIONS:
            raise ValueError(f"VAEConfig.resolution={self.resolution!r}; allowed: a power of two in "
                             f"[32, 512] ({', '.join(map(str, _RESOLUTIONS))})")
        if not _is_int(self.latent_dim) or self.latent_dim < 1:
            raise ValueError(f"VAEConfig.latent_dim={self.latent_dim!r}; allowed: an integer >= 1")
        if not _is_int(self.groups) or self.groups < 1:
            raise ValueError(f"VAEConfig.groups={self.groups!r}; allowed: an integer >= 1")
        if len(self.channels) != NUM_LAYERS or not all(_is_int(c) and c >= 1 for c in self.channels):
            raise ValueError(f"VAEConfig.channels={self.channels!r}; allowed: {NUM_LAYERS} positive integers")
        bad = [c for c in self.channels if c % self.groups]
        if bad:
            raise ValueError(f"VAEConfig.channels={self.channels!r}: {bad} not divisible by "
                             f"VAEConfig.groups={self.groups}; allowed: multiples of {self.groups}")
        if not isinstance(self.group_norm, (bool, np.bool_)):
            raise ValueError(f"VAEConfig.group_norm={self.group_norm!r}; allowed: True or False")
        if not (isinstance(self.leaky_slope, (int, float)) and 0.0 <= self.leaky_slope < 1.0):
            raise ValueError(f"VAEConfig.leaky_slope={self.leaky_slope!r}; allowed: a number in [0, 1)")

    @property
    def bottleneck(self) -> int:
        """Side of the last encoder feature map: R / 2^5."""
        return self.resolution >> NUM_LAYERS


def _is_int(v: object) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


# ----------------------------------------------------------------------------- network
def to_float_images(images: torch.Tensor | np.ndarray) -> torch.Tensor:
    """uint8 (N, H, W, 3) -> float32 (N, 3, H, W) in [0, 1], contiguous, on the input's device."""
    if isinstance(images, np.ndarray):
        images = torch.from_numpy(np.require(images, requirements=["C", "W"]))  # a read-only memmap is copied
    if images.dtype != torch.uint8 or images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"to_float_images expects uint8 images (N, H, W, 3), got {images.dtype} "
                         f"{tuple(images.shape)}")
    return images.permute(0, 3, 1, 2).to(torch.float32).div_(255.0).contiguous()


def _block(conv: nn.Module, out_channels: int, cfg: VAEConfig) -> list[nn.Module]:
    norm = [nn.GroupNorm(cfg.groups, out_channels)] if cfg.group_norm else []
    return [conv, nn.LeakyReLU(cfg.leaky_slope), *norm]


class DenoisingVAE(nn.Module):
    """Encoder q(z | o~) = N(mu, diag(sigma^2)) (eq. 4.41) and decoder f(z) (eq. 4.42)."""

    def __init__(self, config: VAEConfig | None = None, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.config = cfg = config if config is not None else VAEConfig()
        c, s = cfg.channels, cfg.bottleneck
        enc: list[nn.Module] = []
        for c_in, c_out in zip((3, *c[:-1]), c):
            enc += _block(nn.Conv2d(c_in, c_out, 4, 2, 1), c_out, cfg)
        self.encoder = nn.Sequential(*enc, nn.Flatten())  # (N, 3, R, R) -> (N, C5 * s * s)
        flat = c[-1] * s * s
        self.fc_mu = nn.Linear(flat, cfg.latent_dim)
        self.fc_logvar = nn.Linear(flat, cfg.latent_dim)
        dec: list[nn.Module] = [nn.Linear(cfg.latent_dim, flat), nn.Unflatten(1, (c[-1], s, s))]
        rev = c[::-1]  # C5 .. C1
        for c_in, c_out in zip(rev[:-1], rev[1:]):
            dec += _block(nn.ConvTranspose2d(c_in, c_out, 4, 2, 1), c_out, cfg)
        dec += [nn.ConvTranspose2d(rev[-1], 3, 4, 2, 1), nn.Sigmoid()]
        self.decoder = nn.Sequential(*dec)  # (N, d_z) -> (N, 3, R, R)
        # torch's default init, U(+-1/sqrt(fan_in)) for weights and biases, drawn from our own
        # generator (GroupNorm keeps its ones and zeros).
        gen = generator if generator is not None else torch.Generator().manual_seed(0)
        with torch.no_grad():
            for m in self.modules():
                if isinstance(m, (nn.Linear, nn.Conv2d, nn.ConvTranspose2d)):
                    bound = 1.0 / math.sqrt(nn.init._calculate_fan_in_and_fan_out(m.weight)[0])
                    nn.init.uniform_(m.weight, -bound, bound, generator=gen)
                    nn.init.uniform_(m.bias, -bound, bound, generator=gen)

    def _check_images(self, x: torch.Tensor) -> None:
        r = self.config.resolution
        if x.ndim != 4 or tuple(x.shape[1:]) != (3, r, r) or not x.is_floating_point():
            raise ValueError(f"DenoisingVAE expects float images (N, 3, {r}, {r}) in [0, 1], got "
                             f"{x.dtype} {tuple(x.shape)}")

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Float images (N, 3, R, R) in [0, 1] -> mu (N, d_z), log sigma^2 (N, d_z)."""
        self._check_images(x)
        h = self.encoder(x)
        return self.fc_mu(h), self.fc_logvar(h)

    @staticmethod
    def reparameterize(mu: torch.Tensor, logvar: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """z = mu + sigma * eps, eps ~ N(0, I) from `generator` (eq. 4.44); (N, d_z)."""
        eps = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
        return mu + torch.exp(0.5 * logvar) * eps

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latents (N, d_z) -> reconstructed images (N, 3, R, R) in (0, 1)."""
        return self.decoder(z)

    def forward(self, x_aug: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
        """Augmented images (N, 3, R, R) -> (reconstruction (N, 3, R, R), mu, logvar (N, d_z)).
        The reconstruction is compared with the CLEAN image (`vae_loss`)."""
        mu, logvar = self.encode(x_aug)
        return self.decode(self.reparameterize(mu, logvar, generator)), mu, logvar


# ----------------------------------------------------------------------------- loss
def kl_divergence(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL(N(mu, diag(exp(logvar))) || N(0, I)) per sample (eq. 4.47): (N, d_z) -> (N,)."""
    return 0.5 * (mu.square() + logvar.exp() - logvar - 1.0).sum(-1)


def vae_loss(recon: torch.Tensor, target: torch.Tensor, mu: torch.Tensor, logvar: torch.Tensor,
             kl_weight: float = 1.0) -> dict[str, torch.Tensor]:
    """The objective of eq. 4.48 and its parts, for a batch of N samples.

    recon, target: (N, ...) (the decoder output and the CLEAN image); mu, logvar: (N, d_z).
    Returns `loss` (scalar, with its graph), and detached scalars for logs: `recon` (batch mean
    of the squared error summed over pixels), `kl` (batch mean of eq. 4.47) and `mse` (the mean
    squared error per pixel value, readable across resolutions).
    """
    if recon.shape != target.shape:
        raise ValueError(f"vae_loss: recon {tuple(recon.shape)} and target {tuple(target.shape)} differ")
    sq = (recon - target).square()
    recon_sum = sq.flatten(1).sum(1)  # (N,)
    kl = kl_divergence(mu, logvar)  # (N,)
    loss = (recon_sum + kl_weight * kl).mean()  # kl_weight 1: eq. 4.48 (< 1 only in a KL warm-up)
    return {"loss": loss, "recon": recon_sum.mean().detach(), "kl": kl.mean().detach(), "mse": sq.mean().detach()}


# ----------------------------------------------------------------------------- frozen encoder
class FrozenEncoder(nn.Module):
    """The policy's vision feature: mu of a trained VAE's encoder (eq. 4.49), weights frozen.

    Holds a copy of the encoder and the mu head, so that training the VAE further (or anything
    else) cannot move it. Always in eval mode: `train()` is a no-op, so a policy that switches
    its modules to training leaves this one as it is. `camera`: the camera its images came from
    (sim.camera.CameraSpec's fields, from the image set through the VAE's meta); None for a VAE
    written before it was recorded, which saw Table 5.6's camera at its resolution.
    """

    def __init__(self, vae: DenoisingVAE, camera: dict | None = None) -> None:
        super().__init__()
        self.config = vae.config
        self.camera = None if camera is None else dict(camera)
        self.encoder = copy.deepcopy(vae.encoder)
        self.fc_mu = copy.deepcopy(vae.fc_mu)
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> FrozenEncoder:
        return super().train(False)

    @property
    def latent_dim(self) -> int:
        return self.config.latent_dim

    @torch.no_grad()
    def forward(self, images: torch.Tensor | np.ndarray) -> torch.Tensor:
        """uint8 (N, R, R, 3) (camera layout) or float (N, 3, R, R) in [0, 1] -> mu (N, d_z),
        on the encoder's device."""
        r = self.config.resolution
        device = self.fc_mu.weight.device
        if isinstance(images, np.ndarray):
            x = to_float_images(images).to(device)
        elif images.dtype == torch.uint8:
            x = to_float_images(images.to(device))  # move the 4x smaller uint8 image
        elif images.is_floating_point() and images.ndim == 4 and images.shape[1] == 3:
            x = images.to(device=device, dtype=torch.float32)
        else:
            raise ValueError(f"FrozenEncoder expects uint8 (N, H, W, 3) or float (N, 3, H, W) images, got "
                             f"{images.dtype} {tuple(images.shape)}")
        if tuple(x.shape[-2:]) != (r, r):
            raise ValueError(f"FrozenEncoder: expected images of {r} x {r} (the VAE's resolution), got "
                             f"{x.shape[-2]} x {x.shape[-1]}")
        return self.fc_mu(self.encoder(x))


# ----------------------------------------------------------------------------- checkpoints
_VAE_KEYS = ("kind", "vae_format", "config", "meta", "model")
_VAE_KINDS = {"config": dict, "meta": dict, "model": dict, "optimizer": (dict, type(None)), "epoch": (int, type(None)),
              "extra": (dict, type(None))}
# a train_vae checkpoint (extra not None): what vision.train and train/train_vae.py read back on --resume
_TRAINING_EXTRA = {"order_rng": torch.Tensor, "noise_rng": torch.Tensor, "noise_device": str, "history": dict,
                   "best": dict, "timing": dict, "epochs": int}
_TRAINING_META = ("batch_size", "lr", "seed")


def _train_command(task: object = None) -> str:
    t = task if task is not None else "T"
    return (f"`python train/collect_images.py --task {t} --out DIR` then `python train/train_vae.py --images DIR` "
            f"(train/run.py --method vision_kgrl --task {t} does both itself)")


def save_vae(path, vae: DenoisingVAE, config: VAEConfig, meta: dict, optimizer: torch.optim.Optimizer | None = None,
             epoch: int | None = None, extra: dict | None = None) -> Path:
    """Write the VAE (and optionally its optimizer, epoch and `extra`) atomically to `path`.

    `meta` says what the VAE is (task, image set, ...); resolution and latent_dim are added from
    `config`, and a `meta` that states other values is a ValueError.
    """
    if config != vae.config:
        raise ValueError(f"save_vae: config {config} is not the VAE's {vae.config}")
    meta = dict(meta)
    try:  # what torch.load(weights_only=True) reads back; a Path or numpy scalar would fail only then
        json.dumps(meta)
    except TypeError as e:
        raise ValueError(f"save_vae: meta must hold only str, numbers, bools, None, lists and dicts ({e})") from None
    for name in ("resolution", "latent_dim"):
        if name in meta and meta[name] != getattr(config, name):
            raise ValueError(f"save_vae: meta[{name!r}]={meta[name]!r} but config.{name}={getattr(config, name)!r}")
        meta[name] = getattr(config, name)
    return save_checkpoint(path, {
        "kind": VAE_KIND, "vae_format": VAE_FORMAT, "config": dataclasses.asdict(config), "meta": meta,
        "model": vae.state_dict(), "optimizer": None if optimizer is None else optimizer.state_dict(),
        "epoch": None if epoch is None else int(epoch), "extra": extra,
    })


def _check_training_state(payload: dict, path) -> None:
    """A train_vae checkpoint (one with `extra`) holds what a resume reads, of the right types."""
    extra = payload.get("extra")
    if extra is None:
        return  # weights only
    if payload.get("optimizer") is None or type(payload.get("epoch")) is not int or payload["epoch"] < 0:
        raise ValueError(f"VAE checkpoint {path} is damaged: a training checkpoint without its optimizer or epoch")
    for key, kind in _TRAINING_EXTRA.items():
        if not isinstance(extra.get(key), kind):
            raise ValueError(f"VAE checkpoint {path} is damaged: extra {key!r} is {short_repr(extra.get(key))}, "
                             f"not a {kind.__name__}")
    missing = [k for k in _TRAINING_META if k not in payload["meta"]]
    if missing:
        raise ValueError(f"VAE checkpoint {path} is damaged: its meta has no {missing}")


def load_vae(path, expect: dict | None = None, map_location: str | torch.device = "cpu"
             ) -> tuple[DenoisingVAE, dict]:
    """Read a VAE written by `save_vae`: (the VAE in eval mode on `map_location`, the whole payload).

    FileNotFoundError (saying how to train one) if `path` is missing; ValueError if it is damaged,
    not a VAE checkpoint, or its meta differs from `expect` (e.g. {"task": "PegInsert",
    "resolution": 256, "latent_dim": 16}) in any field.
    """
    path = Path(path)
    task = (expect or {}).get("task")
    if not path.is_file():
        raise FileNotFoundError(f"VAE checkpoint {path} does not exist; train one with {_train_command(task)}")
    payload = load_checkpoint(path, map_location=map_location, required=_VAE_KEYS,
                              hint=f"retrain the VAE with {_train_command(task)}", kinds=_VAE_KINDS)
    if (not isinstance(payload["kind"], str) or payload["kind"] != VAE_KIND or type(payload["vae_format"]) is not int
            or payload["vae_format"] != VAE_FORMAT):
        raise ValueError(f"checkpoint {path} is a {short_repr(payload['kind'])} of format "
                         f"{short_repr(payload['vae_format'])}; this code reads {VAE_KIND!r} of format {VAE_FORMAT}")
    meta = payload["meta"]
    for name, want in (expect or {}).items():
        if name not in meta:
            raise ValueError(f"VAE checkpoint {path}: expected {name}={want!r}, the checkpoint does not store {name}")
        if not isinstance(meta[name], type(want)) or meta[name] != want:  # (a tensor's != is no bool)
            raise ValueError(f"VAE checkpoint {path}: {name} mismatch, expected {want!r}, checkpoint has "
                             f"{short_repr(meta[name])}")
    _check_training_state(payload, path)
    try:
        config = VAEConfig(**payload["config"])
        with torch.device("meta"):  # the shapes the config implies, allocating nothing: a damaged config
            shapes = {k: v.shape for k, v in DenoisingVAE(config).state_dict().items()}  # may ask for terabytes
        got = {k: getattr(v, "shape", None) for k, v in payload["model"].items()}
        if got != shapes:
            wrong = sorted(k for k in set(got) | set(shapes) if got.get(k) != shapes.get(k))
            raise ValueError(f"{len(wrong)} weights missing, extra or of another shape than the config's "
                             f"(first: {wrong[0]})")
        check_finite(payload["model"], path, "model")
        vae = DenoisingVAE(config)
        vae.load_state_dict(payload["model"])
    except (TypeError, ValueError, RuntimeError) as e:
        if str(e).startswith(f"{path}: "):  # check_finite's own line
            raise
        raise ValueError(one_line(f"VAE checkpoint {path}: config or weights do not fit ({type(e).__name__}: {e})",
                                  400)) from None
    return vae.to(map_location).eval(), payload
