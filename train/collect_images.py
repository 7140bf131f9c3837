"""Collect the task-camera image set a task's denoising VAE is trained on.

    python train/collect_images.py --task PegInsert --num-images 4096 --out runs/images/peg_r64
    python train/collect_images.py --task PegInsert --num-images 130000 --resolution 256 --device cuda:0 ...
    python train/collect_images.py --preset quick --task PegInsert --out runs/images/peg_quick   # as run.py

Rolls out the scripted demonstrator with command noise and uniform random actions in
`--num-envs` worlds, renders every world's hand camera every `--frame-stride` control steps, and
writes images.npy (uint8), the privileged relative target pose per image (state.npy, for the
linear probe only), each frame's geometry and the two parts' pixel measurements (geometry.npy,
pixels.npy, for the near-hole probe only), episode ids and a train/validation split by episode
into the new directory `--out` (vkgrl_newton/prepare/images.py, dataset.py). `--preset` takes a
vision preset's collection settings (its camera, resolution, count, rounds and split); the
other flags then change single settings of it. An existing non-empty directory is never
written into. `train/run.py --method vision_kgrl` collects its own set when none is cached.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vkgrl_newton._io import output_path_error  # noqa: E402
from vkgrl_newton.cli_types import add_device_option, positive_int, device_name, seed_error  # noqa: E402

from vkgrl_newton.envs.assembly_env import ACTION_DIMS, FAMILIES  # noqa: E402
from vkgrl_newton.runtime import parse_cli  # noqa: E402
from vkgrl_newton.signals import run_cli  # noqa: E402
from vkgrl_newton.tasks import TASKS  # noqa: E402
from vkgrl_newton.sim.camera import CAMERA_SETS  # noqa: E402
from vkgrl_newton.prepare.images import CollectConfig, collect_images  # noqa: E402
from vkgrl_newton.prepare.vision import VISION_PRESETS  # noqa: E402
from vkgrl_newton.vision.vae import VAE_RESOLUTIONS  # noqa: E402


def main(argv=None) -> int:
    d = CollectConfig()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default=d.task, choices=sorted(TASKS))
    ap.add_argument("--preset", default=None, choices=sorted(VISION_PRESETS),
                    help="start from this vision preset's collection (default: CollectConfig's defaults)")
    ap.add_argument("--camera", default=None, choices=sorted(CAMERA_SETS),
                    help="table5.6 (the thesis's cameras) or contact (aimed where the parts meet); "
                         "default: the preset's, else table5.6")
    ap.add_argument("--episode-steps", type=positive_int, default=None,
                    help="control steps per collection round (default: the whole episode)")
    ap.add_argument("--samples-per-pixel", type=positive_int, default=None, help="> 1: multisample anti-aliasing")
    ap.add_argument("--num-images", type=positive_int, default=None)
    ap.add_argument("--out", type=Path, required=True, help="new directory (never written into if not empty)")
    ap.add_argument("--resolution", type=int, choices=VAE_RESOLUTIONS, default=None, metavar="R",
                    help="square image side in pixels, a power of two a VAE accepts: 32, 64, 128, 256, 512 "
                         "(the thesis: 256; quick: 64)")
    ap.add_argument("--num-envs", type=positive_int, default=d.num_envs)
    ap.add_argument("--env", default=d.family, choices=FAMILIES)
    ap.add_argument("--action-dim", type=int, default=d.action_dim, choices=ACTION_DIMS)
    ap.add_argument("--scripted-fraction", type=float, default=d.scripted_fraction,
                    help="fraction of episode rounds run by the noisy demonstrator (the rest: random actions)")
    ap.add_argument("--frame-stride", type=positive_int, default=d.frame_stride)
    ap.add_argument("--val-fraction", type=float, default=None)
    ap.add_argument("--seed", type=int, default=None)
    add_device_option(ap)
    ap.add_argument("--no-progress", action="store_true")
    args = parse_cli(ap, argv, device=True)
    if args.out.exists() and (not args.out.is_dir() or any(args.out.iterdir())):
        ap.error(f"--out {args.out} exists and is not an empty directory; image sets are never overwritten")
    if why := output_path_error(args.out, "--out", may_exist=True):  # (an empty directory is allowed)
        ap.error(why)
    if args.seed is not None and (why := seed_error("--seed", args.seed)):
        ap.error(why)
    import dataclasses

    try:
        base = VISION_PRESETS[args.preset].collect_config(args.task, args.num_envs) if args.preset else d
        changes = {"task": args.task, "num_envs": args.num_envs, "family": args.env, "action_dim": args.action_dim,
                   "scripted_fraction": args.scripted_fraction, "frame_stride": args.frame_stride,
                   "device": args.device}
        for name in ("num_images", "resolution", "val_fraction", "seed", "episode_steps", "samples_per_pixel"):
            if getattr(args, name) is not None:
                changes[name] = getattr(args, name)
        if args.camera is not None:
            spec = CAMERA_SETS[args.camera][args.task]
            changes.update(focal_length=spec.focal_length, camera_rpy_deg=spec.rpy_deg, camera_pos_hand=spec.pos_hand)
        cfg = dataclasses.replace(base, **changes)
    except ValueError as e:
        ap.error(str(e))
    fresh = not args.out.exists()  # (else empty: checked above)
    try:
        collect_images(cfg, args.out, progress=not args.no_progress)
    except KeyboardInterrupt:  # an unfinished set (no meta.json) would only block the next try
        if fresh:
            shutil.rmtree(args.out, ignore_errors=True)
        else:  # the empty directory the user gave stays
            for path in args.out.iterdir():
                shutil.rmtree(path) if path.is_dir() else path.unlink()
        raise
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main, "train/collect_images.py", "the unfinished image set was removed; nothing was written"))
