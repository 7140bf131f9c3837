"""Tests of the vision package (vkgrl_newton.vision) on the CPU, each against a reference written
independently of the code under test: torch.distributions and a Monte-Carlo estimate for the KL,
eq. 4.48 by hand, exact flips and scipy's Gaussian filter for the augmentations, binomial bounds
for their probabilities, the ridge normal equations for the probe."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from vkgrl_newton.agents.checkpoint import load_checkpoint, save_checkpoint
from vkgrl_newton.vision import (
    AugmentConfig,
    DenoisingVAE,
    FrozenEncoder,
    ImageSet,
    ImageSetWriter,
    VAEConfig,
    apply_params,
    augment,
    draw_params,
    gaussian_blur,
    gaussian_kernel1d,
    kl_divergence,
    linear_probe,
    load_vae,
    save_vae,
    to_float_images,
    vae_loss,
)

SMALL = dict(channels=(8, 16, 16, 32, 32), groups=8)  # widths for fast tests, divisible by 8


# small nets: one intra-op thread is fast and immune to a busy second core (conftest.py)
pytestmark = pytest.mark.usefixtures("torch_one_thread")


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ----------------------------------------------------------------------------- config and network
@pytest.mark.parametrize("resolution,channels", [(32, SMALL["channels"]), (64, SMALL["channels"]),
                                                 (256, VAEConfig().channels)])
def test_shapes(resolution, channels):
    vae = DenoisingVAE(VAEConfig(resolution=resolution, channels=channels), gen())
    x = torch.rand((2, 3, resolution, resolution), generator=gen(1))
    mu, logvar = vae.encode(x)
    assert mu.shape == logvar.shape == (2, 16)
    z = vae.reparameterize(mu, logvar, gen(2))
    assert z.shape == (2, 16)
    recon = vae.decode(z)
    assert recon.shape == (2, 3, resolution, resolution)
    assert recon.min() > 0 and recon.max() < 1  # sigmoid
    recon2, mu2, logvar2 = vae(x, gen(2))
    assert torch.equal(recon2, recon) and torch.equal(mu2, mu) and torch.equal(logvar2, logvar)
    with pytest.raises(ValueError, match=f"3, {resolution}, {resolution}"):
        vae.encode(torch.rand(2, 3, resolution // 2, resolution // 2))


def test_architecture_follows_the_thesis():
    vae = DenoisingVAE(VAEConfig(resolution=64, **SMALL))
    convs = [m for m in vae.encoder if isinstance(m, torch.nn.Conv2d)]
    deconvs = [m for m in vae.decoder if isinstance(m, torch.nn.ConvTranspose2d)]
    assert len(convs) == len(deconvs) == 5
    for m in convs + deconvs:
        assert m.kernel_size == (4, 4) and m.stride == (2, 2) and m.padding == (1, 1)
    # conv -> LeakyReLU -> GroupNorm(8) in the encoder; the decoder's last layer is a sigmoid
    kinds = [type(m).__name__ for m in vae.encoder]
    assert kinds[:3] == ["Conv2d", "LeakyReLU", "GroupNorm"] and kinds[-1] == "Flatten"
    assert all(m.num_groups == 8 for m in vae.modules() if isinstance(m, torch.nn.GroupNorm))
    assert isinstance(vae.decoder[-1], torch.nn.Sigmoid)
    # weights are drawn from the given generator only
    cfg = VAEConfig(resolution=32, **SMALL)
    a, b = DenoisingVAE(cfg, gen(5)), DenoisingVAE(cfg, gen(5))
    assert all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters()))


def test_group_norm_off_removes_only_the_norm_layers():
    with_norm = DenoisingVAE(VAEConfig(resolution=64, **SMALL), gen(3))
    without = DenoisingVAE(VAEConfig(resolution=64, group_norm=False, **SMALL), gen(3))
    assert not any(isinstance(m, torch.nn.GroupNorm) for m in without.modules())
    assert sum(isinstance(m, torch.nn.GroupNorm) for m in with_norm.modules()) == 9  # 5 encoder + 4 decoder
    strip = lambda net: [type(m).__name__ for m in net.modules() if not isinstance(m, torch.nn.GroupNorm)]  # noqa: E731
    assert strip(with_norm) == strip(without)
    # same weights from the same generator (GroupNorm draws nothing), different outputs
    conv = lambda net: [m.weight for m in net.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]  # noqa: E731
    assert all(torch.equal(a, b) for a, b in zip(conv(with_norm), conv(without)))
    x = torch.rand((2, 3, 64, 64), generator=gen(4))
    assert not torch.allclose(with_norm.encode(x)[0], without.encode(x)[0])


@pytest.mark.parametrize("kwargs,field", [
    (dict(group_norm="no"), "group_norm"),
    (dict(resolution=48), "resolution"), (dict(resolution=1024), "resolution"), (dict(resolution=16), "resolution"),
    (dict(latent_dim=0), "latent_dim"), (dict(channels=(8, 8, 8, 8)), "channels"),
    (dict(channels=(8, 8, 12, 8, 8)), "channels"), (dict(leaky_slope=1.5), "leaky_slope"), (dict(groups=0), "groups"),
])
def test_config_errors_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=f"VAEConfig.{field}"):
        VAEConfig(**kwargs)


def test_to_float_images():
    u8 = torch.randint(0, 256, (2, 5, 7, 3), dtype=torch.uint8, generator=gen())
    x = to_float_images(u8)
    assert x.shape == (2, 3, 5, 7) and x.dtype == torch.float32 and x.is_contiguous()
    assert torch.equal(x[1, 2, 4, 6], u8[1, 4, 6, 2].float() / 255)
    ro = u8.numpy().copy()
    ro.flags.writeable = False  # as a read-only memmap
    assert torch.equal(to_float_images(ro), x)
    with pytest.raises(ValueError, match="uint8"):
        to_float_images(u8.float())


# ----------------------------------------------------------------------------- loss
def test_kl_against_torch_distributions_and_monte_carlo():
    g = gen(3)
    mu = torch.randn((5, 4), generator=g, dtype=torch.float64)
    logvar = torch.randn((5, 4), generator=g, dtype=torch.float64)
    sigma = (0.5 * logvar).exp()
    ref = torch.distributions.kl_divergence(torch.distributions.Normal(mu, sigma),
                                            torch.distributions.Normal(0.0, 1.0)).sum(-1)
    kl = kl_divergence(mu, logvar)
    assert kl.shape == (5,)
    # float64, two formulas of ~10 operations (exp, log on both sides): ~1e-15 relative; 1e-12 bounds it
    torch.testing.assert_close(kl, ref, rtol=1e-12, atol=1e-12)
    # Monte Carlo: E_q[log q(z) - log p(z)], within 5 standard errors
    m = 200_000
    z = mu + sigma * torch.randn((m, 5, 4), generator=g, dtype=torch.float64)
    log_q = (-0.5 * ((z - mu) / sigma) ** 2 - sigma.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
    log_p = (-0.5 * z**2 - 0.5 * math.log(2 * math.pi)).sum(-1)
    d = log_q - log_p  # (m, 5)
    se = d.std(0) / math.sqrt(m)
    assert ((d.mean(0) - kl).abs() < 5 * se).all(), (d.mean(0), kl, se)


def test_loss_is_eq_4_48_by_hand():
    g = gen(4)
    recon, target = torch.rand((2, 3, 2, 2), generator=g), torch.rand((2, 3, 2, 2), generator=g)
    mu, logvar = torch.randn((2, 3), generator=g), torch.randn((2, 3), generator=g)
    terms = []
    for t in range(2):
        sq = sum((float(recon[t].flatten()[i]) - float(target[t].flatten()[i])) ** 2 for i in range(12))
        kl = 0.5 * sum(float(mu[t, j]) ** 2 + math.exp(float(logvar[t, j])) - float(logvar[t, j]) - 1 for j in range(3))
        terms.append((sq, kl))
    out = vae_loss(recon, target, mu, logvar)
    # float32 against float64 of the same float32 inputs. The squared errors are non-negative: 12-term sums of
    # rounded differences and squares, <= ~16 u32 of themselves; the KL's terms mu^2 + e^lv - lv - 1 cancel, so
    # bound them by 16 u32 of the magnitudes summed, 0.5 sum(mu^2 + e^lv + |lv| + 1) (was rel_tol 1e-5, no origin)
    mag_kl = sum(0.5 * sum(float(mu[t, j]) ** 2 + math.exp(float(logvar[t, j])) + abs(float(logvar[t, j])) + 1
                           for j in range(3)) for t in range(2)) / 2
    u32 = 2.0 ** -24
    sq_mean = sum(s for s, _ in terms) / 2
    assert abs(out["loss"].item() - sum(s + k for s, k in terms) / 2) <= 16 * u32 * (sq_mean + mag_kl)
    assert abs(out["recon"].item() - sq_mean) <= 16 * u32 * sq_mean
    assert abs(out["kl"].item() - sum(k for _, k in terms) / 2) <= 16 * u32 * mag_kl
    assert abs(out["mse"].item() - sum(s for s, _ in terms) / 24) <= 16 * u32 * sq_mean / 12
    assert out["loss"].ndim == 0


# ----------------------------------------------------------------------------- augmentations
def binomial_ok(count: int, n: int, p: float, k: float = 5.0) -> bool:
    return abs(count - n * p) <= k * math.sqrt(n * p * (1 - p))


def test_augment_leaves_input_alone_and_is_seeded():
    x = torch.rand((64, 3, 16, 16), generator=gen())
    before = x.clone()
    a = augment(x, gen(7))
    assert torch.equal(x, before)
    assert a.data_ptr() != x.data_ptr() and a.shape == x.shape
    assert a.min() >= 0 and a.max() <= 1
    assert torch.equal(a, augment(x, gen(7))) and not torch.equal(a, augment(x, gen(8)))
    # augment = draw_params + apply_params on the same stream
    assert torch.equal(a, apply_params(x, draw_params(64, gen(7))))
    # nothing drawn -> a copy
    off = AugmentConfig(flip_p=0, brightness_p=0, blur_p=0)
    c = augment(x, gen(7), off)
    assert torch.equal(c, x) and c.data_ptr() != x.data_ptr()


def test_flip_probability_and_exactness():
    n = 2000
    x = torch.rand((n, 3, 4, 6), generator=gen(1))
    out = augment(x, gen(2), AugmentConfig(brightness_p=0, blur_p=0))
    flipped = (out == x.flip(-1)).flatten(1).all(1)
    same = (out == x).flatten(1).all(1)
    assert bool((flipped ^ same).all())  # each image is exactly one of the two
    assert binomial_ok(int(flipped.sum()), n, 0.5), int(flipped.sum())


def test_brightness_shift():
    n = 2000
    x = 0.1 + 0.8 * torch.rand((n, 3, 4, 4), generator=gen(1))  # no clamping for |b| <= 15/255
    out = augment(x, gen(3), AugmentConfig(flip_p=0, blur_p=0))
    diff = (out - x).flatten(1)
    const = diff.mean(1)
    assert (diff.max(1).values - diff.min(1).values).max() < 1e-6  # one constant per image
    assert const.abs().max() <= 15 / 255 + 1e-6
    changed = const.abs() > 1e-7
    assert binomial_ok(int(changed.sum()), n, 0.3), int(changed.sum())
    assert const.min() < -12 / 255 and const.max() > 12 / 255  # spread over U(-15, 15)
    # clamped to [0, 1]
    ones = torch.ones((200, 3, 4, 4))
    bright = augment(ones, gen(4), AugmentConfig(flip_p=0, blur_p=0, brightness_p=1.0))
    params = draw_params(200, gen(4), AugmentConfig(flip_p=0, blur_p=0, brightness_p=1.0))
    assert bright.max() <= 1.0
    torch.testing.assert_close(bright[:, 0, 0, 0], (1 + params.shift).clamp(max=1.0))


def test_blur_kernel_and_identity():
    sig = torch.tensor([0.0, 1e-3, 0.05, 0.3, 0.7])
    k = gaussian_kernel1d(sig, 5)
    torch.testing.assert_close(k.sum(-1), torch.ones(5))
    assert torch.equal(k, k.flip(-1))
    assert torch.equal(k[0], torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0]))
    x = torch.rand((3, 3, 9, 11), generator=gen(5))
    assert torch.equal(gaussian_blur(x, torch.zeros(3)), x)  # sigma -> 0: identity
    assert torch.equal(gaussian_blur(x, torch.full((3,), 1e-4)), x)
    c = torch.full((2, 3, 8, 8), 0.37)
    b = gaussian_blur(c, torch.tensor([0.4, 0.7]))
    torch.testing.assert_close(b, c)
    # a constant through two 5-tap passes whose weights sum to 1 (each <= ~5 u32 of 0.37) and a float32 mean of
    # 384 values (<= ~9 u32 pairwise): <= ~20 u32 * 0.37 ~ 4.4e-7; 1e-6 bounds it (assert_close above: torch's
    # float32 defaults, rtol 1.3e-6 / atol 1e-5, looser than that)
    assert abs(b.mean().item() - 0.37) < 1e-6


def test_blur_matches_scipy_and_its_probability():
    ndimage = pytest.importorskip("scipy.ndimage")
    x = torch.rand((4, 3, 10, 12), generator=gen(6), dtype=torch.float64)
    sigma = torch.tensor([0.2, 0.45, 0.6, 0.7], dtype=torch.float64)
    out = gaussian_blur(x, sigma)
    for i in range(4):
        for c in range(3):
            # scipy "mirror" = torch "reflect" (d c b | a b c d | c b a); radius 2 = our 5 taps
            ref = ndimage.gaussian_filter(x[i, c].numpy(), float(sigma[i]), radius=2, mode="mirror")
            np.testing.assert_allclose(out[i, c].numpy(), ref, rtol=1e-10, atol=1e-12)
    n = 2000
    cfg = AugmentConfig(flip_p=0, brightness_p=0, blur_sigma_range=(0.5, 0.7))
    img = torch.rand((n, 3, 6, 6), generator=gen(7))
    a = augment(img, gen(8), cfg)
    changed = (a != img).flatten(1).any(1)
    assert binomial_ok(int(changed.sum()), n, 0.3), int(changed.sum())
    p = draw_params(n, gen(8), cfg)
    assert torch.equal(changed, p.blur)
    assert p.sigma.min() >= 0.5 and p.sigma.max() <= 0.7
    idx = p.blur.nonzero().squeeze(1)[:5]
    torch.testing.assert_close(a[idx], gaussian_blur(img[idx], p.sigma[idx]))


# ----------------------------------------------------------------------------- training
def squares(n: int, g: torch.Generator, r: int = 32, side: int = 8) -> torch.Tensor:
    """Black images with one coloured square at a random position: (n, 3, r, r) in [0, 1]."""
    x = torch.zeros((n, 3, r, r))
    pos = torch.randint(0, r - side + 1, (n, 2), generator=g)
    col = 0.3 + 0.7 * torch.rand((n, 3), generator=g)
    for i in range(n):  # test data only
        x[i, :, pos[i, 0]: pos[i, 0] + side, pos[i, 1]: pos[i, 1] + side] = col[i, :, None, None]
    return x


def test_tiny_training_run_lowers_validation_loss():
    g = gen(10)
    train, val = squares(64, g), squares(32, g)
    vae = DenoisingVAE(VAEConfig(resolution=32, **SMALL), gen(11))
    # lr 3e-3 rather than the thesis's 1e-3: 40 steps at 1e-3 only take ~15 % off the loss
    opt = torch.optim.Adam(vae.parameters(), lr=3e-3)

    def val_loss() -> float:
        with torch.no_grad():
            recon, mu, logvar = vae(val, gen(99))
            return vae_loss(recon, val, mu, logvar)["loss"].item()

    before = val_loss()
    for _ in range(40):
        idx = torch.randint(0, 64, (32,), generator=g)
        clean = train[idx]
        recon, mu, logvar = vae(augment(clean, g), g)  # encoder: augmented, decoder target: clean
        loss = vae_loss(recon, clean, mu, logvar)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = val_loss()
    assert math.isfinite(after) and after < 0.6 * before, (before, after)  # ~0.46 seen


# ----------------------------------------------------------------------------- frozen encoder
def test_frozen_encoder():
    vae = DenoisingVAE(VAEConfig(resolution=32, **SMALL), gen(12))
    enc = FrozenEncoder(vae)
    params = list(enc.parameters())
    assert params and not any(p.requires_grad for p in params)
    enc.train()  # a policy switching to training mode does not move it
    assert not enc.training
    x = torch.rand((4, 3, 32, 32), generator=gen(13))
    z = enc(x)
    assert z.shape == (4, 16) and not z.requires_grad
    assert torch.equal(z, vae.encode(x)[0])  # the mean, same ops on the same weights
    u8 = torch.randint(0, 256, (4, 32, 32, 3), dtype=torch.uint8, generator=gen(14))
    assert torch.equal(enc(u8), vae.encode(to_float_images(u8))[0])
    assert torch.equal(enc(u8.numpy()), enc(u8))
    snapshot = {k: v.clone() for k, v in enc.state_dict().items()}
    head = torch.nn.Linear(16, 2)
    opt = torch.optim.Adam(head.parameters(), lr=1e-2)
    head(enc(x)).square().sum().backward()
    opt.step()
    assert head.weight.grad is not None
    assert all(torch.equal(v, snapshot[k]) for k, v in enc.state_dict().items())
    # a copy: training the VAE further leaves it alone
    with torch.no_grad():
        vae.fc_mu.weight.add_(1.0)
    assert torch.equal(enc.fc_mu.weight, snapshot["fc_mu.weight"])
    with pytest.raises(ValueError, match="expected images of 32 x 32.*got 64 x 64"):
        enc(torch.rand(1, 3, 64, 64))
    with pytest.raises(ValueError, match="expected images of 32 x 32.*got 16 x 16"):
        enc(torch.zeros((1, 16, 16, 3), dtype=torch.uint8))


# ----------------------------------------------------------------------------- image set
def write_set(out_dir, episodes: int = 10, frames: int = 6, r: int = 8, val_fraction: float = 0.2):
    g = np.random.default_rng(0)
    n = episodes * frames
    images = g.integers(0, 256, (n, r, r, 3), dtype=np.uint8)
    state = g.normal(size=(n, 4)).astype(np.float32)
    episode = np.repeat(np.arange(100, 100 + episodes), frames)
    w = ImageSetWriter(out_dir, n, r, "PegInsert", val_fraction=val_fraction, seed=3,
                       meta_extra={"source": "test: random pixels"})
    for sl in (slice(0, 7), slice(7, 40), slice(40, n)):  # uneven chunks, tensors and arrays
        w.add(torch.from_numpy(images[sl]) if sl.start == 7 else images[sl], state[sl], episode[sl])
    assert w.close() == out_dir
    return images, state, episode


def test_image_set_round_trip_and_split(tmp_path):
    d = tmp_path / "set"
    images, state, episode = write_set(d)
    ds = ImageSet(d, resolution=8, task="PegInsert")
    assert isinstance(ds.images, np.memmap) and len(ds) == 60
    assert np.array_equal(ds.images, images) and np.array_equal(ds.state, state)
    assert np.array_equal(ds.episode, episode) and ds.episode.dtype == np.int32
    assert ds.meta["source"] == "test: random pixels" and ds.meta["val_fraction"] == 0.2
    assert ds.meta["count"] == 60 and ds.meta["resolution"] == 8 and ds.meta["task"] == "PegInsert"
    # by episode: 2 of 10 episodes, all of their frames, none of the others
    assert np.array_equal(np.sort(np.concatenate([ds.train_idx, ds.val_idx])), np.arange(60))
    val_eps, train_eps = set(episode[ds.val_idx]), set(episode[ds.train_idx])
    assert len(val_eps) == 2 and not val_eps & train_eps and len(ds.val_idx) == 12
    assert json.loads((d / "meta.json").read_text())["num_val_episodes"] == 2
    assert sorted(p.name for p in d.iterdir()) == sorted(["images.npy", "state.npy", "episode.npy", "split.npy",
                                                          "meta.json", "geometry.npy", "pixels.npy"])
    assert not ds.has_geometry and np.isnan(ds.geometry).all()  # the writer was given none
    # a format-1 set (before geometry.npy and pixels.npy) is still read, without them
    meta = json.loads((d / "meta.json").read_text())
    (d / "meta.json").write_text(json.dumps({**meta, "format": 1}))
    for name in ("geometry.npy", "pixels.npy"):
        (d / name).unlink()
    old = ImageSet(d)
    assert old.geometry is None and old.pixels is None and not old.has_geometry and len(old) == 60
    with pytest.raises(ValueError, match="resolution 8, requested 64"):
        ImageSet(d, resolution=64)
    with pytest.raises(ValueError, match="GearMesh"):
        ImageSet(d, task="GearMesh")


def test_image_set_keeps_geometry_and_pixels(tmp_path):
    g = np.random.default_rng(1)
    n = 12
    geometry = g.normal(size=(n, 13)).astype(np.float32)
    pixels = g.normal(size=(n, 12)).astype(np.float32)
    pixels[3, :6] = np.nan  # the fixed part out of view in frame 3
    w = ImageSetWriter(tmp_path / "s", n, 8, "PegInsert", val_fraction=0.25)
    images = np.zeros((n, 8, 8, 3), np.uint8)
    with pytest.raises(ValueError, match="geometry must be finite"):
        w.add(images[:2], np.zeros((2, 4)), np.arange(2), np.full((2, 13), np.nan), pixels[:2])
    with pytest.raises(ValueError, match=r"pixels must be \(2, 12\)"):
        w.add(images[:2], np.zeros((2, 4)), np.arange(2), geometry[:2], pixels[:2, :6])
    w.add(images, np.zeros((n, 4)), np.arange(n), torch.from_numpy(geometry), pixels)
    w.close()
    ds = ImageSet(tmp_path / "s")
    assert ds.has_geometry and np.array_equal(ds.geometry, geometry)
    np.testing.assert_array_equal(ds.pixels, pixels)  # NaN where NaN was written


def test_image_set_refuses_and_names_what_is_missing(tmp_path):
    d = tmp_path / "set"
    write_set(d)
    with pytest.raises(FileExistsError, match="not empty"):
        ImageSetWriter(d, 4, 8, "PegInsert")
    (d / "split.npy").unlink()
    with pytest.raises(FileNotFoundError, match="split.npy"):
        ImageSet(d)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        ImageSet(tmp_path / "nowhere")
    # an interrupted writer leaves no meta.json, and the reader says so
    u = tmp_path / "unfinished"
    with pytest.raises(KeyboardInterrupt):
        with ImageSetWriter(u, 4, 8, "PegInsert", val_fraction=0.5) as w:
            w.add(np.zeros((2, 8, 8, 3), np.uint8), np.zeros((2, 4)), np.array([0, 1]))
            raise KeyboardInterrupt
    with pytest.raises(FileNotFoundError, match="meta.json.*did not finish"):
        ImageSet(u)
    w = ImageSetWriter(tmp_path / "short", 4, 8, "PegInsert")
    w.add(np.zeros((2, 8, 8, 3), np.uint8), np.zeros((2, 4)), np.array([0, 1]))
    with pytest.raises(ValueError, match="2 of num_images=4"):
        w.close()
    with pytest.raises(ValueError, match="uint8"):
        w.add(np.zeros((2, 8, 8, 3), np.float32), np.zeros((2, 4)), np.array([0, 1]))


# ----------------------------------------------------------------------------- probe
def test_linear_probe():
    g = np.random.default_rng(1)
    zt, zv = g.normal(size=(2000, 8)), g.normal(size=(1000, 8))
    a, b = g.normal(size=(8, 3)), g.normal(size=3)
    out = linear_probe(zt, zt @ a + b, torch.from_numpy(zv), zv @ a + b)
    assert out["r2"].shape == (3,) and (out["r2"] > 0.9999).all()
    # against the ridge normal equations in float64: penalty ridge ||W||^2 against the MEAN
    # squared error, unpenalized bias (centred data)
    yt = zt @ a + b + g.normal(size=(2000, 3))
    out = linear_probe(zt, yt, zv, zv @ a + b, ridge=0.5)
    zc, yc = zt - zt.mean(0), yt - yt.mean(0)
    w_ref = np.linalg.solve(zc.T @ zc + 0.5 * 2000 * np.eye(8), zc.T @ yc)
    # float64 ridge solves of condition ~ (1 + 0.5) / 0.5 = 3 on 2000 rows (sums ~2000 u64): ~1e-13 relative,
    # whatever BLAS/LAPACK kernels the CPU gets; 1e-8 bounds it
    np.testing.assert_allclose(out["weight"], w_ref, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(out["bias"], yt.mean(0) - zt.mean(0) @ w_ref, rtol=1e-8, atol=1e-10)
    # an independent target: nothing to read
    r = linear_probe(zt, g.normal(size=2000), zv, g.normal(size=1000))["r2"]
    assert r.shape == (1,) and abs(r[0]) < 0.05


# ----------------------------------------------------------------------------- checkpoints
def test_vae_checkpoint_round_trip_and_errors(tmp_path):
    cfg = VAEConfig(resolution=32, **SMALL)
    vae = DenoisingVAE(cfg, gen(20))
    opt = torch.optim.Adam(vae.parameters(), lr=1e-3)
    x = torch.rand((2, 3, 32, 32), generator=gen(21))
    recon, mu, logvar = vae(x, gen(22))
    vae_loss(recon, x, mu, logvar)["loss"].backward()  # an optimizer with state
    opt.step()
    path = tmp_path / "vae" / "PegInsert.pt"
    save_vae(path, vae, cfg, {"task": "PegInsert", "images": "runs/img"}, optimizer=opt, epoch=3)
    loaded, payload = load_vae(path, expect={"task": "PegInsert", "resolution": 32, "latent_dim": 16})
    assert loaded.config == cfg and not loaded.training and payload["epoch"] == 3
    assert payload["meta"] == {"task": "PegInsert", "images": "runs/img", "resolution": 32, "latent_dim": 16}
    assert all(torch.equal(v, loaded.state_dict()[k]) for k, v in vae.state_dict().items())
    opt2 = torch.optim.Adam(loaded.parameters(), lr=1e-3)
    opt2.load_state_dict(payload["optimizer"])
    # a VAE checkpoint is not a training run's, and the default still asks for a run's keys
    with pytest.raises(ValueError, match="missing"):
        load_checkpoint(path)

    with pytest.raises(ValueError, match="resolution mismatch, expected 64, checkpoint has 32"):
        load_vae(path, expect={"resolution": 64})
    with pytest.raises(ValueError, match="task mismatch, expected 'GearMesh', checkpoint has 'PegInsert'"):
        load_vae(path, expect={"task": "GearMesh"})
    with pytest.raises(ValueError, match="does not store camera"):
        load_vae(path, expect={"camera": "hand"})
    with pytest.raises(FileNotFoundError, match="collect_images.py --task NutThread.*train_vae.py --images"):
        load_vae(tmp_path / "missing.pt", expect={"task": "NutThread"})
    bad = tmp_path / "garbage.pt"
    bad.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(ValueError, match="damaged"):
        load_vae(bad)
    torn = tmp_path / "torn.pt"
    torn.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(ValueError, match="damaged"):
        load_vae(torn)
    other = save_checkpoint(tmp_path / "agent.pt", {"meta": {}, "counters": {}, "agent": {}, "rng": {}})
    with pytest.raises(ValueError, match="missing"):
        load_vae(other)
    with pytest.raises(ValueError, match="config"):
        save_vae(tmp_path / "x.pt", vae, VAEConfig(resolution=64, **SMALL), {})
    with pytest.raises(ValueError, match="meta"):  # would save, then fail to load with weights_only
        save_vae(tmp_path / "x.pt", vae, cfg, {"images": tmp_path})
    with pytest.raises(ValueError, match="resolution"):
        save_vae(tmp_path / "x.pt", vae, cfg, {"resolution": 64})
    assert not (tmp_path / "x.pt").exists()


def test_vae_loss_kl_weight_scales_only_the_kl_term():
    g = torch.Generator().manual_seed(5)
    recon, target = torch.rand(3, 3, 4, 4, generator=g), torch.rand(3, 3, 4, 4, generator=g)
    mu, logvar = torch.randn(3, 16, generator=g), torch.randn(3, 16, generator=g)
    full, half = vae_loss(recon, target, mu, logvar), vae_loss(recon, target, mu, logvar, kl_weight=0.5)
    sse = (recon - target).double().square().flatten(1).sum(1)
    kl = 0.5 * (mu.double().square() + logvar.double().exp() - logvar.double() - 1).sum(1)
    # float32: 48-term sums of squares and 16-term KL sums (terms that cancel: bound by their magnitudes),
    # then a mean of 3: <= ~(48 + 16) u32 of the magnitudes summed (was rtol 1e-5, atol 1e-5, no origin)
    mag = (sse + 0.5 * (mu.double().square() + logvar.double().exp() + logvar.double().abs() + 1).sum(1)).mean()
    bound = float(64 * 2.0 ** -24 * mag)
    torch.testing.assert_close(full["loss"].double(), (sse + kl).mean(), rtol=0, atol=bound)
    torch.testing.assert_close(half["loss"].double(), (sse + 0.5 * kl).mean(), rtol=0, atol=bound)


def test_presets_and_their_cache_names(tmp_path):
    """The thesis preset is Tables 5.5-5.6 with eq. 4.48 and GroupNorm as written; every setting
    in which a preset differs from it is in its cache directory's name, so a VAE trained with
    other settings is never picked up for it."""
    import dataclasses

    from vkgrl_newton.prepare.images import collection_key
    from vkgrl_newton.prepare.vision import VISION_PRESETS, VisionPreset, default_vae_dir

    thesis, quick = VISION_PRESETS["thesis"], VISION_PRESETS["quick"]
    assert (thesis.resolution, thesis.num_images, thesis.vae_epochs, thesis.vae_batch_size) == (256, 130_000, 400, 128)
    assert thesis.kl_weight == 1.0 and thesis.group_norm and thesis.vae_config().group_norm
    assert (thesis.camera, thesis.samples_per_pixel) == ("table5.6", 1)  # Table 5.6
    from vkgrl_newton.sim.camera import TASK_CAMERAS
    from vkgrl_newton.prepare.images import collect_camera_spec

    for task, spec in TASK_CAMERAS.items():  # the thesis preset renders Table 5.6's camera at 256 px
        assert collect_camera_spec(thesis.collect_config(task)) == dataclasses.replace(spec, width=256, height=256)
    from vkgrl_newton.sim.camera import CONTACT_CAMERAS

    for task, spec in CONTACT_CAMERAS.items():  # the quick preset renders the contact camera, all of it
        assert collect_camera_spec(quick.collect_config(task)) == dataclasses.replace(spec, width=64, height=64)
    key = collection_key(thesis.collect_config("PegInsert"))
    assert default_vae_dir(tmp_path, "PegInsert", thesis) == (
        tmp_path / "PegInsert" / f"vae_v1_r256_n130000_e400_seed0_{key}")
    assert default_vae_dir(tmp_path, "GearMesh", quick).name.startswith(
        f"vae_v1_r{quick.resolution}_n{quick.num_images}_e{quick.vae_epochs}_b32_kl0.01_nonorm_seed0_")
    assert quick.vae_config() == VAEConfig(resolution=quick.resolution, group_norm=False)
    names = {default_vae_dir(tmp_path, "PegInsert", VisionPreset(64, 4096, 10, **kw)).name
             for kw in ({}, {"vae_batch_size": 32}, {"kl_weight": 0.5}, {"group_norm": False}, {"seed": 1})}
    assert len(names) == 5


def test_any_preset_or_collection_change_makes_a_new_cache_entry(tmp_path):
    """Each field of VisionPreset and of CollectConfig (but the device), changed alone, names a new
    image-set and VAE entry: an old cache entry is never reused for other settings."""
    import dataclasses

    from vkgrl_newton.prepare.images import CollectConfig, default_image_dir
    from vkgrl_newton.prepare.vision import VISION_PRESETS, default_vae_dir

    other = {int: lambda v: v + 1, float: lambda v: v * 0.5 + 0.01, bool: lambda v: not v, str: None,
             type(None): None}
    quick = VISION_PRESETS["quick"]
    changes = {"camera": "table5.6" if quick.camera != "table5.6" else "contact", "samples_per_pixel": 4,
               "val_fraction": 0.3, "episode_steps": 45}
    base_vae = default_vae_dir(tmp_path, "PegInsert", quick)
    for f in dataclasses.fields(quick):
        v = getattr(quick, f.name)
        new = changes.get(f.name, other[type(v)](v) if other.get(type(v)) else None)
        if new == v or new is None:
            new = changes[f.name]
        changed = dataclasses.replace(quick, **{f.name: new})
        assert default_vae_dir(tmp_path, "PegInsert", changed) != base_vae, f.name
    cfg = CollectConfig()
    base_images = default_image_dir(tmp_path, cfg)
    # the camera enters the key as the camera rendered, however its settings were written
    from vkgrl_newton.sim.camera import TASK_CAMERAS

    table = TASK_CAMERAS["PegInsert"]
    spelled = dataclasses.replace(cfg, focal_length=table.focal_length, camera_rpy_deg=table.rpy_deg)
    assert default_image_dir(tmp_path, spelled) == base_images
    collect_changes = {"task": "GearMesh", "family": "forge", "action_dim": 6, "episode_steps": 40,
                       "focal_length": 48.0, "camera_rpy_deg": (0.0, -29.0, 0.0), "camera_pos_hand": (0.0, 0.08, 0.11)}
    for f in dataclasses.fields(cfg):
        if f.name == "device":
            assert default_image_dir(tmp_path, dataclasses.replace(cfg, device="cuda:0")) == base_images
            continue
        v = getattr(cfg, f.name)
        new = collect_changes.get(f.name) or other[type(v)](v)
        if f.name in ("scripted_fraction", "val_fraction"):
            new = 0.25
        assert default_image_dir(tmp_path, dataclasses.replace(cfg, **{f.name: new})) != base_images, f.name


def test_the_pixel_baselines_fixed_shapes_are_part_of_the_cache_key(tmp_path, monkeypatch):
    """GearMesh's pixel baseline measures its target shaft alone (collect.FIXED_PIXEL_PARTS): that
    choice is in the image set's key, so a set measured with another choice is never reused; the
    tasks without an entry keep the key they had (their baseline is the whole fixed part)."""
    import vkgrl_newton.prepare.images as collect

    gear, peg = collect.CollectConfig(task="GearMesh"), collect.CollectConfig(task="PegInsert")
    before = collect.default_image_dir(tmp_path, gear), collect.default_image_dir(tmp_path, peg)
    monkeypatch.setattr(collect, "FIXED_PIXEL_PARTS", {"GearMesh": "/gear_base/plate"})
    assert collect.default_image_dir(tmp_path, gear) != before[0]
    assert collect.default_image_dir(tmp_path, peg) == before[1]
