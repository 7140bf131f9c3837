"""The near-hole probe (vkgrl_newton/vision/probe.py) against constructions with a known answer:
the image-frame target against scipy's rotations, the selection against its definition, pixel
measurements of a drawn disc against a brute-force loop, and the regressions on latents and on a
blob moved by known sub-pixel offsets."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation


def _geometry(rng, target_image, n):
    """(n, 13) float64 geometry whose fixed tip is `target_image` (n, 3) from the held part in the
    frame of a random camera orientation, at a random place near a Franka's table."""
    q = Rotation.random(n, random_state=rng).as_quat()  # xyzw
    held = rng.uniform([0.4, -0.2, 0.1], [0.7, 0.2, 0.3], size=(n, 3))
    fixed = held + Rotation.from_quat(q).apply(target_image)
    cam = held + rng.uniform(-0.2, 0.2, size=(n, 3))
    return np.column_stack([held, fixed, cam, q])


def test_relative_in_image_against_scipy():
    from vkgrl_newton.vision.probe import relative_in_image

    rng = np.random.default_rng(0)
    t = rng.uniform(-0.01, 0.01, size=(500, 3))
    g = _geometry(rng, t, 500)
    np.testing.assert_allclose(relative_in_image(g), t, atol=1e-15 * 10)  # float64: a few ulps of 1 m
    # stored as float32 (the image set's dtype): positions ~0.7 m have an ulp of 6e-8 m; the
    # difference of two such values and a rotation stay within 4 ulps of the larger operand
    got32 = relative_in_image(g.astype(np.float32))
    assert np.abs(got32 - t).max() < 4 * np.spacing(np.float32(0.7))


def test_near_hole_mask_is_its_definition():
    """Strict bounds: the held part strictly within 1 cm (xy) of the fixed tip and strictly less
    than 2 cm above it; any depth below counts (in contact, inside the hole)."""
    from vkgrl_newton.vision.probe import near_hole_mask

    def frame(dx, dy, dz):
        return [0.5 + dx, 0.1 + dy, 0.2 + dz, 0.5, 0.1, 0.2, 0, 0, 0.5, 0, 0, 0, 1]

    cases = [((0, 0, 0), True), ((0.0099, 0, 0.019), True), ((0, -0.0099, -0.05), True),
             ((0.006, 0.0079, 0.0), True),  # 0.99 cm diagonal
             ((0.006, 0.0081, 0.0), False),  # 1.007 cm diagonal
             ((0.0101, 0, 0), False), ((0, 0, 0.0201), False), ((0.02, 0.02, -0.01), False)]
    g = np.array([frame(*d) for d, _ in cases], np.float64)
    np.testing.assert_array_equal(near_hole_mask(g), [want for _, want in cases])
    # brute force on random frames: the same set as the definition's loop
    rng = np.random.default_rng(1)
    g = np.array([frame(*d) for d in rng.uniform([-0.02, -0.02, -0.03], [0.02, 0.02, 0.04], size=(2000, 3))])
    want = [math.hypot(r[0] - r[3], r[1] - r[4]) < 0.01 and r[2] - r[5] < 0.02 for r in g]
    np.testing.assert_array_equal(near_hole_mask(g), want)
    assert 0.1 < np.mean(want) < 0.5  # both kinds present


def _disc_images(centres, radius, h=48, w=48, shape_id=7, background=3):
    """Shape-index images (n, h, w) of a disc of `shape_id`: pixels whose centre is inside."""
    vv, uu = np.mgrid[0:h, 0:w] + 0.5
    out = np.full((len(centres), h, w), background, np.uint32)
    for i, (cu, cv) in enumerate(centres):
        out[i][(uu - cu) ** 2 + (vv - cv) ** 2 < radius ** 2] = shape_id
    return out


def test_part_pixel_features_against_a_loop():
    from vkgrl_newton.vision.probe import part_pixel_features

    rng = np.random.default_rng(2)
    h = w = 48
    centres = rng.uniform(15, 33, size=(5, 2))
    seg = _disc_images(centres, 6.3)
    seg[4] = 3  # world 4: the part is not in view
    depth = rng.uniform(0.1, 0.3, size=(5, h, w)).astype(np.float32)
    dirs = rng.normal(size=(h, w, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    got = part_pixel_features(seg, depth, dirs, [np.array([7, 99])] * 5)
    for e in range(4):
        pts, us, vs = [], [], []
        for r in range(h):
            for c in range(w):
                if seg[e, r, c] in (7, 99):
                    us.append(c + 0.5), vs.append(r + 0.5), pts.append(float(depth[e, r, c]) * dirs[r, c])
        want = [np.mean(us), np.mean(vs), len(us), *np.mean(pts, axis=0)]
        # float64 sums rounded once to float32 (0.5 ulp: 6e-8 relative); atol for the 3D means near 0
        np.testing.assert_allclose(got[e], want, rtol=1e-6, atol=1e-7)
    assert got[4, 2] == 0 and np.isnan(got[4, [0, 1, 3, 4, 5]]).all()


def test_regressions_recover_a_known_latent_relation():
    """latent = the target (mm) plus N(0, sigma) per axis, mixed by a random rotation into 16
    dimensions with 13 more of pure noise: the best affine map's validation RMSE is sigma up to
    the fit's excess error (factor sqrt(1 + d/n)) and the estimate's sampling error (relative
    std 1/sqrt(2 n_val)); the MLP can do no better than that map and must come near it."""
    from vkgrl_newton.vision.probe import regression_rmse

    rng = np.random.default_rng(3)
    n_fit, n_val, sigma, d = 800, 600, 0.3, 16
    y = rng.uniform(-5, 5, size=(n_fit + n_val, 3))  # mm
    signal = np.column_stack([y + sigma * rng.normal(size=y.shape), rng.normal(size=(len(y), d - 3))])
    mix = Rotation.random(random_state=rng).as_matrix()
    big = np.eye(d)
    big[:3, :3] = mix
    z = signal @ big.T * 0.7 + 2.0  # any affine image of it
    lin = regression_rmse(z[:n_fit], y[:n_fit], z[n_fit:], y[n_fit:], "linear")
    expected = sigma * math.sqrt(1 + d / n_fit)
    assert np.all(np.abs(lin / expected - 1) < 4 / math.sqrt(2 * n_val)), lin
    mlp = regression_rmse(z[:n_fit], y[:n_fit], z[n_fit:], y[n_fit:], "mlp")
    assert np.all(mlp > 0.85 * sigma) and np.all(mlp < 1.6 * sigma), mlp
    with pytest.raises(ValueError, match="model='svm'"):
        regression_rmse(z, y, z, y, "svm")


def test_near_hole_probe_on_a_blob_moved_by_sub_pixel_offsets():
    """A synthetic image set with a known answer. Near-hole frames: the fixed part is a disc drawn
    where a 1 px-per-mm camera sees the fixed tip (x, y in the image plane), moved by sub-pixel
    offsets; the latent is the target plus 0.2 mm of noise; far frames (outside the selection)
    carry garbage that must be ignored. The pixel baseline regresses the target on the disc's
    measured centroid: its RMSE is at most the digitization error of the centroid (the best
    affine map beats the true one, whose error is exactly that), which a brute-force pass over
    the same discs gives; the latent's RMSE is ~0.2 mm."""
    from vkgrl_newton.vision.dataset import PIXEL_COLUMNS
    from vkgrl_newton.vision.probe import near_hole_mask, near_hole_probe, part_pixel_features

    rng = np.random.default_rng(4)
    n = 1000
    near_drawn = rng.random(n) < 0.75
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    t = np.where(near_drawn[:, None], rng.uniform(-4e-3, 4e-3, size=(n, 3)),  # the fixed tip from the held
                 direction * rng.uniform(0.025, 0.04, size=(n, 1)))  # part in the image frame, m
    g = _geometry(rng, t, n)
    near = near_hole_mask(g)
    assert near[near_drawn].all()  # |t| < 7 mm: near in any orientation
    keep = near_drawn | ~near  # drop the far draws that some orientation still put near the hole
    g, t, near = g[keep], t[keep], near[keep]
    n = len(g)
    assert 0.6 < near.mean() < 0.9
    centres = 24.0 + 1e3 * t[:, :2]  # 1 px per mm, image centre 24 px
    seg = _disc_images(centres, 5.5)
    depth = np.full(seg.shape, 0.15, np.float32)
    dirs = np.zeros((48, 48, 3))
    dirs[..., 2] = 1.0  # every ray along the optical axis (the 3D columns then carry only depth)
    fixed = part_pixel_features(seg, depth, dirs, [np.array([7])] * n)
    held = np.tile([24.0, 30.0, 40.0, 0.0, 0.0, 0.14], (n, 1))  # the held part does not move in the image
    pixels = np.column_stack([fixed, held]).astype(np.float32)
    assert pixels.shape[1] == len(PIXEL_COLUMNS)
    latent = np.column_stack([1e3 * t + 0.2 * rng.normal(size=(n, 3)), rng.normal(size=(n, 5))])
    latent[~near] = 1e3 * rng.normal(size=((~near).sum(), 8))  # far frames: unrelated, huge
    tr = np.arange(n) < int(0.7 * n)
    episode = np.arange(n) // 10  # 10 frames an episode
    p = near_hole_probe(latent[tr], g[tr], latent[~tr], g[~tr], pixels[tr], pixels[~tr], episodes_val=episode[~tr])
    assert p["num_episodes"] == len(np.unique(episode[~tr][near[~tr]]))
    assert 0 < p["latent_linear_rmse_mm_se"]["x"] < 0.05 and set(p["pixel_baseline_rmse_mm_se"]) == set("xyz")
    assert p["num_images"] == int(near[~tr].sum()) and p["num_fit"] == int(near[tr].sum())
    assert p["observation_noise_mm"] == 1.0 and p["pixel_baseline_num_images"] == p["num_images"]
    for axis in "xy":
        err = (fixed[near & ~tr, "xy".index(axis)] - centres[near & ~tr, "xy".index(axis)])  # px = mm
        bound = math.sqrt(np.mean(err ** 2)) * 1.15  # + the fit's excess and sampling error
        assert 0.005 < p["pixel_baseline_linear_rmse_mm"][axis] <= bound, (axis, p, bound)
        assert p["pixel_baseline_rmse_mm"][axis] < 3 * bound
        # the latent is the target plus 0.2 mm noise: RMSE 0.2 mm up to the fit's excess (~1 %) and its
        # sampling error over ~200 scored frames (1 / sqrt(2 n) ~ 5 %, 0.01 mm): the band is ~3 standard errors
        # either side (the draws are seeded PCG64, the same on any CPU; the MLP's float rounding moves it far less)
        assert 0.17 < p["latent_linear_rmse_mm"][axis] < 0.24
        assert 0.17 < p["latent_mlp_rmse_mm"][axis] < 0.4
        assert abs(p["mean_predictor_rmse_mm"][axis] - 8 / math.sqrt(12)) < 0.25  # U(-4, 4) mm: std 2.31
    # the disc does not move with z: the baseline cannot beat predicting the mean there
    assert p["pixel_baseline_linear_rmse_mm"]["z"] > 0.9 * p["mean_predictor_rmse_mm"]["z"]
    few = near_hole_probe(latent[:30], g[:30], latent[-30:], g[-30:])
    assert few["latent_linear_rmse_mm"] is None and "at least 20" in few["skipped"]


def test_episode_bootstrap_se_resamples_whole_episodes():
    """RMSE of n draws of N(0, 1) has a standard error of ~1 / sqrt(2 n) (delta method). Errors
    constant within each of 60 episodes of 20 frames count as 60 draws, not 1 200; independent
    frames as 1 200. Tolerances: the bootstrap's own spread at 2 000 draws and 60 episodes (~20 %)."""
    from vkgrl_newton.vision.probe import episode_bootstrap_se

    rng = np.random.default_rng(5)
    episodes = np.repeat(np.arange(60), 20)
    per_episode = np.repeat(rng.normal(size=(60, 1)), 20, axis=0)
    se = episode_bootstrap_se(per_episode, episodes, draws=2000)
    assert abs(se[0] * math.sqrt(2 * 60) - 1) < 0.3, se
    frames = rng.normal(size=(1200, 1))
    se_frames = episode_bootstrap_se(frames, np.arange(1200), draws=2000)
    assert abs(se_frames[0] * math.sqrt(2 * 1200) - 1) < 0.2, se_frames
    # against a direct loop over the same draws
    ids = np.unique(episodes)
    pick = np.random.default_rng(0).integers(0, len(ids), size=(50, len(ids)))
    loop = [math.sqrt(np.mean(np.concatenate([per_episode[episodes == ids[k], 0] ** 2 for k in row]))) for row in pick]
    np.testing.assert_allclose(episode_bootstrap_se(per_episode, episodes, draws=50, seed=0)[0], np.std(loop, ddof=1),
                               rtol=1e-12)
