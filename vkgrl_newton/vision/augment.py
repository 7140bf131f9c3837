"""The denoising corruption p_aug(o~ | o) of eq. 4.39: the augmentations of thesis Table 5.5.

Each image of a batch, independently:
    horizontal flip      with p = 0.5
    brightness shift     with p = 0.3, by b ~ U(-15, 15) on the 0..255 scale (b / 255 on our
                         [0, 1] floats), the same b on every pixel and channel, then clamped to [0, 1]
    Gaussian blur        with p = 0.3, sigma ~ U(0, 0.7): a separable, normalized 5-tap kernel
                         (radius 2, enough for sigma <= 0.7: a third tap would carry < 1e-4 of the weight),
                         reflect padding so that a constant image stays constant

applied in that order (the table's; flip commutes with the other two). Images are float
tensors (N, 3, H, W) in [0, 1]. Randomness comes only from the caller's generator, on the
images' device, and all N draws of every parameter are taken whether or not they are used, so
the stream advances by the same amount for every batch of N.

`augment` = `draw_params` + `apply_params`; the two halves are public so that tests and
figures can see what was done to which image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F

__all__ = ["AugmentConfig", "AugmentParams", "augment", "draw_params", "apply_params", "gaussian_kernel1d",
           "gaussian_blur"]


@dataclass(frozen=True)
class AugmentConfig:
    flip_p: float = 0.5
    brightness_p: float = 0.3
    brightness_range: tuple[float, float] = (-15.0, 15.0)  # on the 0..255 scale
    blur_p: float = 0.3
    blur_sigma_range: tuple[float, float] = (0.0, 0.7)  # pixels
    blur_kernel_size: int = 5

    def __post_init__(self) -> None:
        for name in ("brightness_range", "blur_sigma_range"):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        for name in ("flip_p", "brightness_p", "blur_p"):
            p = getattr(self, name)
            if not (isinstance(p, (int, float)) and 0.0 <= p <= 1.0):
                raise ValueError(f"AugmentConfig.{name}={p!r}; allowed: a probability in [0, 1]")
        lo, hi = self.brightness_range
        if not -255.0 <= lo <= hi <= 255.0:
            raise ValueError(f"AugmentConfig.brightness_range={self.brightness_range!r}; allowed: (lo, hi) "
                             "with -255 <= lo <= hi <= 255")
        lo, hi = self.blur_sigma_range
        if not 0.0 <= lo <= hi:
            raise ValueError(f"AugmentConfig.blur_sigma_range={self.blur_sigma_range!r}; allowed: (lo, hi) "
                             "with 0 <= lo <= hi")
        k = self.blur_kernel_size
        if not (isinstance(k, int) and k >= 1 and k % 2 == 1):
            raise ValueError(f"AugmentConfig.blur_kernel_size={k!r}; allowed: an odd integer >= 1")


class AugmentParams(NamedTuple):
    flip: torch.Tensor  # (N,) bool
    shift: torch.Tensor  # (N,) brightness shift on the [0, 1] scale; 0 where not shifted
    blur: torch.Tensor  # (N,) bool
    sigma: torch.Tensor  # (N,) blur sigma in pixels (drawn for all, used where blur)


def draw_params(n: int, generator: torch.Generator, config: AugmentConfig | None = None,
                device: torch.device | str | None = None) -> AugmentParams:
    """The random choices for n images; `generator` lives on `device` (default: the generator's)."""
    cfg = config if config is not None else AugmentConfig()
    device = generator.device if device is None else torch.device(device)
    u = torch.rand((5, n), generator=generator, device=device)  # one draw, a fixed stream layout
    (b_lo, b_hi), (s_lo, s_hi) = cfg.brightness_range, cfg.blur_sigma_range
    shifted = u[1] < cfg.brightness_p
    shift = torch.where(shifted, (b_lo + (b_hi - b_lo) * u[2]) / 255.0, torch.zeros_like(u[2]))
    return AugmentParams(flip=u[0] < cfg.flip_p, shift=shift, blur=u[3] < cfg.blur_p,
                         sigma=s_lo + (s_hi - s_lo) * u[4])


def gaussian_kernel1d(sigma: torch.Tensor, size: int = 5) -> torch.Tensor:
    """Normalized Gaussian taps at -size//2 .. size//2: sigma (M,) -> (M, size), rows sum to 1.
    sigma -> 0 gives the unit impulse (exactly, for sigma below ~0.1 in float32)."""
    x = torch.arange(size, device=sigma.device, dtype=sigma.dtype) - (size // 2)
    var = sigma.clamp_min(1e-6).square()[:, None]  # 1e-6: sigma = 0 is the impulse, not 0/0
    w = torch.exp(-x.square() / (2.0 * var))
    return w / w.sum(-1, keepdim=True)


def gaussian_blur(images: torch.Tensor, sigma: torch.Tensor, size: int = 5) -> torch.Tensor:
    """Blur each image (N, C, H, W) with its own sigma (N,): separable, reflect padding.

    Batched as one grouped convolution per axis (N * C groups), no loop over images.
    """
    n, c, h, w = images.shape
    if n == 0:
        return images.clone()
    r = size // 2
    k = gaussian_kernel1d(sigma.to(images), size).repeat_interleave(c, dim=0)  # (N * C, size)
    x = images.reshape(1, n * c, h, w)
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="reflect"), k[:, None, None, :], groups=n * c)
    x = F.conv2d(F.pad(x, (0, 0, r, r), mode="reflect"), k[:, None, :, None], groups=n * c)
    return x.reshape(n, c, h, w)


def apply_params(images: torch.Tensor, params: AugmentParams, config: AugmentConfig | None = None) -> torch.Tensor:
    """Flip, shift and blur each image as `params` say; a new tensor, `images` is left alone."""
    cfg = config if config is not None else AugmentConfig()
    if images.ndim != 4 or not images.is_floating_point():
        raise ValueError(f"augment expects float images (N, C, H, W) in [0, 1], got {images.dtype} "
                         f"{tuple(images.shape)}")
    col = (-1, 1, 1, 1)  # per-image scalars against (N, C, H, W)
    out = torch.where(params.flip.view(col), images.flip(-1), images)  # horizontal: the width axis
    shifted = params.shift != 0
    out = torch.where(shifted.view(col), (out + params.shift.to(out).view(col)).clamp(0.0, 1.0), out)
    idx = params.blur.nonzero().squeeze(1)
    if idx.numel():  # only the chosen images pay for the convolution
        out[idx] = gaussian_blur(out[idx], params.sigma[idx], cfg.blur_kernel_size)
    return out


def augment(images: torch.Tensor, generator: torch.Generator, config: AugmentConfig | None = None) -> torch.Tensor:
    """A corrupted copy o~ of a batch of clean images (N, C, H, W) in [0, 1] (eq. 4.39, Table 5.5)."""
    params = draw_params(images.shape[0], generator, config, device=images.device)
    return apply_params(images, params, config)

