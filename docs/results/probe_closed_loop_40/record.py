"""Record the camera controller's own frames (issue 40): the near-hole probe's estimate where the controller uses it.

Runs tools/ceiling.py's `centre_latent` (the camera controller, --kgrl-base centre_latent's a = 0) on 16 worlds x
ROUNDS episodes of an eval seed and saves, for every control step of every world: the frozen encoder's latent z, the
probe's estimate (world x, y of the held part's origin minus the fixed tip), the privileged truth, the frame's
geometry (vision.dataset.GEOMETRY_COLUMNS: held, fixed tip, optical frame), the TCP's x, y, the step, and the
controller's state (the step it was found blocked, whether the part dropped). Per episode, the ceiling's record.

    python docs/results/probe_closed_loop_40/record.py --eval-seed 20000 --rounds 8 --out runs/probe_cl/train_20000.npz
    [--probe P.npz]  (another probe file in place of the cache's: the refitted one)
    [--push-mm P]    (the settled press below the prior's z, in place of the ceiling's 3 mm)
    [--seat-press-mm S]  (the prior's tables pressed S mm below its seat from the seat on)
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--eval-seed", type=int, required=True)
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--probe", type=Path, default=None)
    ap.add_argument("--push-mm", type=float, default=None, help="the settled press below the prior's z (default: the "
                    "ceiling's ORACLE_PUSH_MM, 3)")
    ap.add_argument("--seat-press-mm", type=float, default=0.0, help="the prior's tables pressed this far below its "
                    "seat from the seat on (kmp.tables.with_seat_press, --kgrl-seat-press's), for a part that goes in "
                    "without being blocked")
    ap.add_argument("--cache-dir", default="runs/cache")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    if args.out.exists():
        sys.exit(f"--out {args.out}: exists; give a new file")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    from vkgrl_newton.runtime import configure_warp, cpu_model

    configure_warp()
    import torch

    torch.set_num_threads(1)
    from vkgrl_newton.envs.camera_latent import LATERAL_DIM, LatentLateral
    from vkgrl_newton.prepare.vision import VISION_PRESETS, load_or_make_encoder, load_or_make_probe
    from vkgrl_newton.tools import ceiling

    task = "PegInsert"
    env, tables, _ = ceiling.build(task, args.num_envs, args.cache_dir, 0)
    if args.seat_press_mm:
        tables = ceiling.pushed_prior(tables, 1e-3 * args.seat_press_mm)
    preset = VISION_PRESETS["quick"]
    encoder, _ = load_or_make_encoder(task, preset, args.cache_dir, "cpu")
    probe, probe_path, _ = load_or_make_probe(task, preset, args.cache_dir, encoder, path=args.probe)
    log = {k: [] for k in ("z", "estimate", "truth", "geometry", "tcp_xy", "step", "since", "found")}

    class Logged(LatentLateral):
        policy = None

        @torch.no_grad()
        def __call__(self, env):
            hand = env.hand_pose()
            out = self.latent(env)
            est = out[:, -LATERAL_DIM:].to(torch.float64)
            truth = (env.held_pose()[0] - env.fixed_tip_w).to(torch.float64)
            geom = torch.cat((env.held_pose()[0], env.fixed_tip_w, self.latent.camera.optical_poses_w(*hand)), -1)
            log["z"].append(out[:, :-LATERAL_DIM].float().numpy().copy())
            log["estimate"].append(est.numpy().copy())
            log["truth"].append(truth[:, :2].numpy().copy())
            log["geometry"].append(geom.double().numpy().copy())
            log["tcp_xy"].append(env.tcp_pose()[0][:, :2].double().numpy().copy())
            log["step"].append(env.episode_length_buf.long().numpy().copy())
            log["since"].append(self.policy.since.numpy().copy())
            log["found"].append(self.policy.found.numpy().copy())
            return est

    estimate = Logged(env, encoder, probe)
    policy = ceiling.make_controller("centre_latent", env, tables, task, 0, 0.0, estimate)
    estimate.policy = policy
    if args.push_mm is not None:
        policy.push_mm = float(args.push_mm)
    records, wall = ceiling.run_controller(env, policy, args.rounds, args.eval_seed, task)
    arrays = {k: np.stack(v) for k, v in log.items()}  # (T, E, ...)
    success = np.array([r["success"] for r in records])
    np.savez_compressed(args.out, success=success, **arrays)
    meta = {"eval_seed": args.eval_seed, "push_mm": policy.push_mm, "seat_press_mm": args.seat_press_mm, "rounds": args.rounds, "num_envs": args.num_envs, "probe": str(probe_path),
            "success": float(success.mean()), "n_success": int(success.sum()), "episodes": len(records),
            "wall_s": round(wall, 1), "cpu": cpu_model(), "records": records}
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=1))
    print(f"{args.out}: success {success.sum()}/{len(success)} in {wall:.0f} s")


if __name__ == "__main__":
    main()
