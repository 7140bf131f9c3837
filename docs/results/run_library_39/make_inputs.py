import torch
from vkgrl_newton.kmp.demos import synthetic_demos
from vkgrl_newton.vision import DenoisingVAE, VAEConfig, save_vae
synthetic_demos("PegInsert", 8, action_dim=4, seed=1).save("/tmp/ba/demos.npz")
torch.manual_seed(0)
cfg = VAEConfig(resolution=32, channels=(8, 8, 8, 8, 8))
save_vae("/tmp/ba/vae.pt", DenoisingVAE(cfg), cfg, meta={"task": "PegInsert"})
