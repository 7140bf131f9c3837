"""The camera controller's estimate where it steers (issue 40): its error, how much of it a per-episode filter
removes, and a probe refitted on the controller's own frames (closed-loop data, as DAgger).

    python docs/results/probe_closed_loop_40/analyse.py --train runs/probe_cl/cl_20000.npz \
        --eval runs/probe_cl/cl_10000.npz [--write-probe runs/probe_cl/probe_refit.npz]

Frames: "steering" = the controller found blocked and the part not yet dropped (the steps whose x, y follow the
estimate). Errors in world x, y, mm. The filtered estimate keeps, per episode, the running mean of (estimate - TCP x, y)
over the steering frames so far and adds the TCP's x, y back: the held part is fixed in the hand and the hole in the
world, so that difference is constant up to the estimate's error (and any slip in the grasp).
"""
import argparse
from pathlib import Path

import numpy as np
import torch


def load(path):
    d = dict(np.load(path))
    T, E = d["step"].shape
    rnd = np.cumsum(d["step"][:, 0] == 0) - 1  # rounds start together in every world
    d["episode"] = rnd[:, None] * E + np.arange(E)[None, :]
    return d


def steering(d):
    return (d["since"] >= 0) & ~d["found"]


def filtered(d):
    """(T, E, 2) the running per-episode mean of estimate - tcp over steering frames, plus tcp (NaN before any)."""
    c = d["estimate"] - d["tcp_xy"]
    s = steering(d)
    T, E = s.shape
    out = np.full_like(c, np.nan)
    acc, n = np.zeros((E, 2)), np.zeros(E)
    for t in range(T):
        start = d["step"][t] == 0
        acc[start], n[start] = 0.0, 0
        acc[s[t]] += c[t][s[t]]
        n[s[t]] += 1
        ok = n > 0
        out[t][ok] = acc[ok] / n[ok][:, None] + d["tcp_xy"][t][ok]
    return out


def rmse(err):
    return 1e3 * np.sqrt(np.nanmean(err ** 2, axis=0))


def decompose(err, episode):
    """RMSE (mm) of the per-episode mean error (bias) and of the rest (within), per axis."""
    ids, inv = np.unique(episode, return_inverse=True)
    mean = np.stack([np.bincount(inv, err[:, k]) / np.bincount(inv) for k in range(2)], -1)
    return 1e3 * np.sqrt((mean ** 2).mean(0)), 1e3 * np.sqrt(((err - mean[inv]) ** 2).mean(0))


def world_estimate(reg_predict, z, geometry):
    from vkgrl_newton.vision.probe import lateral_from_image

    d_img = torch.as_tensor(reg_predict(z))
    q = torch.as_tensor(geometry[:, 9:13])
    return lateral_from_image(d_img, q).numpy()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--train", type=Path, nargs="+", required=True)
    ap.add_argument("--eval", type=Path, required=True)
    ap.add_argument("--cache-dir", default="runs/cache")
    ap.add_argument("--write-probe", type=Path)
    args = ap.parse_args()
    ev = load(args.eval)
    s = steering(ev)
    err = (ev["estimate"] - ev["truth"])[s]
    print(f"eval {args.eval}: {s.sum()} steering frames in {len(np.unique(ev['episode'][s]))} episodes; "
          f"success {ev['success'].mean():.3f}")
    print(f"  probe as cached: RMSE x, y {rmse(err).round(3)} mm; per-episode bias / within {[a.round(3) for a in decompose(err, ev['episode'][s])]}")
    f = filtered(ev)
    print(f"  filtered (running mean over the episode's steering frames): RMSE {rmse((f - ev['truth'])[s]).round(3)} mm")
    # the first steering frame of each episode: what the controller steers by at the start
    first = s & ~np.vstack([np.zeros((1, s.shape[1]), bool), s[:-1]])
    print(f"  at the first steering frame: RMSE {rmse((ev['estimate'] - ev['truth'])[first]).round(3)} mm")

    # refit on the image set + the training seed's closed-loop near-hole frames
    from vkgrl_newton.prepare.vision import VISION_PRESETS, default_image_dir, load_or_make_encoder
    from vkgrl_newton.vision.dataset import ImageSet
    from vkgrl_newton.vision.probe import NearHoleRegressor, near_hole_mask

    task, preset = "PegInsert", VISION_PRESETS["quick"]
    encoder, _ = load_or_make_encoder(task, preset, args.cache_dir, "cpu")
    images = ImageSet(default_image_dir(args.cache_dir, preset.collect_config(task, 16)), resolution=preset.resolution,
                      task=task)
    z_img = np.concatenate([encoder(np.asarray(images.images[i:i + 256])).double().cpu().numpy()
                            for i in range(0, len(images), 256)])
    g_img = images.geometry.astype(np.float64)
    print(f"image set: {len(images)} frames, {near_hole_mask(g_img).sum()} near-hole")
    z_tr, g_tr = [], []
    for p in args.train:
        tr = load(p)
        z_tr.append(tr["z"].reshape(-1, tr["z"].shape[-1]).astype(np.float64))
        g_tr.append(tr["geometry"].reshape(-1, 13))
    z_tr, g_tr = np.concatenate(z_tr), np.concatenate(g_tr)
    print(f"closed-loop training frames: {len(z_tr)}, {near_hole_mask(g_tr).sum()} near-hole")
    z_ev, g_ev, truth = ev["z"][s].astype(np.float64), ev["geometry"][s], ev["truth"][s]
    old = NearHoleRegressor(z_img, g_img, seed=preset.seed)
    e_old = world_estimate(old, z_ev, g_ev) - truth
    print(f"  refit, image set only (= the cache's fit): RMSE {rmse(e_old).round(3)} mm")
    only = NearHoleRegressor(z_tr, g_tr, seed=preset.seed)
    print(f"  refit, closed-loop frames only: RMSE {rmse(world_estimate(only, z_ev, g_ev) - truth).round(3)} mm")
    both = NearHoleRegressor(np.concatenate([z_img, z_tr]), np.concatenate([g_img, g_tr]), seed=preset.seed)
    e_both = world_estimate(both, z_ev, g_ev) - truth
    print(f"  refit, image set + closed-loop frames: RMSE {rmse(e_both).round(3)} mm; bias / within "
          f"{[a.round(3) for a in decompose(e_both, ev['episode'][s])]}")
    if args.write_probe:
        from vkgrl_newton._io import atomic_savez

        st = both.state()
        arrays = {k: st[k] for k in ("x_mean", "x_scale", "y_mean", "y_scale")}
        arrays.update({f"w{i}": w for i, w in enumerate(st["weights"])})
        arrays.update({f"b{i}": b for i, b in enumerate(st["biases"])})
        atomic_savez(args.write_probe, False, num_layers=np.array(len(st["weights"])), num_fit=np.array(st["num_fit"]),
                     held_out_rmse_mm=np.full(3, np.nan), held_out_frames=np.array(0), **arrays)
        print(f"wrote {args.write_probe}")


if __name__ == "__main__":
    main()
