"""Vision for Vision-KGRL (thesis 4.3, 5.6): the denoising VAE, its augmentations, the image set
it is trained on, its training loop, the frozen encoder the policy reads, and a linear probe of
the latent."""

from vkgrl_newton.vision.augment import (
    AugmentConfig,
    AugmentParams,
    apply_params,
    augment,
    draw_params,
    gaussian_blur,
    gaussian_kernel1d,
)
from vkgrl_newton.vision.dataset import IMAGESET_FILES, IMAGESET_FORMAT, STATE_DIM, ImageSet, ImageSetWriter
from vkgrl_newton.vision.probe import linear_probe
from vkgrl_newton.vision.train import train_vae
from vkgrl_newton.vision.vae import (
    VAE_FORMAT,
    VAE_KIND,
    DenoisingVAE,
    FrozenEncoder,
    VAEConfig,
    kl_divergence,
    load_vae,
    save_vae,
    to_float_images,
    vae_loss,
)

__all__ = [
    "AugmentConfig",
    "AugmentParams",
    "apply_params",
    "augment",
    "draw_params",
    "gaussian_blur",
    "gaussian_kernel1d",
    "IMAGESET_FILES",
    "IMAGESET_FORMAT",
    "STATE_DIM",
    "ImageSet",
    "ImageSetWriter",
    "linear_probe",
    "train_vae",
    "VAE_FORMAT",
    "VAE_KIND",
    "DenoisingVAE",
    "FrozenEncoder",
    "VAEConfig",
    "kl_divergence",
    "load_vae",
    "save_vae",
    "to_float_images",
    "vae_loss",
]
