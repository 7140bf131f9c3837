"""Collect the task-camera image set a task's denoising VAE is trained on.

    python train/collect_images.py --task PegInsert --num-images 4096 --out runs/images/peg_r64
    python train/collect_images.py --task PegInsert --num-images 130000 --resolution 256 --device cuda:0 ...

Rolls out the scripted demonstrator with command noise and uniform random actions in
`--num-envs` worlds, renders every world's hand camera every `--frame-stride` control steps, and
writes images.npy (uint8), the privileged relative target pose per image (state.npy, for the
linear probe only), episode ids and a train/validation split by episode into the new directory
`--out` (vkgrl_newton/vision/collect.py, dataset.py). An existing non-empty directory is never
written into. `train/run.py --method vision_kgrl` collects its own set when none is cached.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vkgrl_newton.cli_types import positive_int  # noqa: E402

from vkgrl_newton.envs.assembly_env import ACTION_DIMS, FAMILIES  # noqa: E402
from vkgrl_newton.runtime import parse_cli  # noqa: E402
from vkgrl_newton.tasks import TASKS  # noqa: E402
from vkgrl_newton.vision.collect import CollectConfig, collect_images  # noqa: E402


def main(argv=None) -> int:
    d = CollectConfig()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default=d.task, choices=sorted(TASKS))
    ap.add_argument("--num-images", type=positive_int, default=d.num_images)
    ap.add_argument("--out", type=Path, required=True, help="new directory (never written into if not empty)")
    ap.add_argument("--resolution", type=positive_int, default=d.resolution,
                    help="square image side in pixels (the thesis: 256; quick: 64)")
    ap.add_argument("--num-envs", type=positive_int, default=d.num_envs)
    ap.add_argument("--env", default=d.family, choices=FAMILIES)
    ap.add_argument("--action-dim", type=int, default=d.action_dim, choices=ACTION_DIMS)
    ap.add_argument("--scripted-fraction", type=float, default=d.scripted_fraction,
                    help="fraction of episode rounds run by the noisy demonstrator (the rest: random actions)")
    ap.add_argument("--frame-stride", type=positive_int, default=d.frame_stride)
    ap.add_argument("--val-fraction", type=float, default=d.val_fraction)
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--device", default=None, help="cpu or cuda:0 (default: cuda:0 when present)")
    ap.add_argument("--no-progress", action="store_true")
    args = parse_cli(ap, argv, device=True)
    if args.out.exists() and (not args.out.is_dir() or any(args.out.iterdir())):
        ap.error(f"--out {args.out} exists and is not an empty directory; image sets are never overwritten")
    device = args.device
    try:
        cfg = CollectConfig(task=args.task, num_images=args.num_images, resolution=args.resolution,
                            num_envs=args.num_envs, family=args.env, action_dim=args.action_dim,
                            scripted_fraction=args.scripted_fraction, frame_stride=args.frame_stride,
                            val_fraction=args.val_fraction, seed=args.seed, device=device)
    except ValueError as e:
        ap.error(str(e))
    collect_images(cfg, args.out, progress=not args.no_progress)
    return 0


if __name__ == "__main__":
    sys.exit(main())
