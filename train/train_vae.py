"""Train a task's denoising VAE on its camera image set (thesis 5.6, Table 5.5; Figs. 6.7-6.9).

    python train/train_vae.py --images runs/images/PegInsert_r256
    python train/train_vae.py --images runs/images/PegInsert_r256 --device cpu --epochs 20
    python train/train_vae.py --images runs/images/PegInsert_r256 --out runs/vae/peg --resume
    python train/train_vae.py --images runs/images/PegInsert_r64 --device cpu --epochs 40 \
        --batch-size 32 --kl-weight 0.01 --no-group-norm        # the quick preset's CPU settings
    python train/train_vae.py --images DIR --probe-only runs/vae/peg/vae.pt   # probes only, as JSON
    python train/train_vae.py --images S1 S2 --probe-only runs/vae/peg/vae.pt # probes fitted and scored
                                                                              # on two sets pooled

Thesis settings by default: Adam lr 1e-3, batch 128, 400 epochs, the Table 5.5 augmentations on
the encoder input. The run directory (default runs/vae/<task>_r<resolution>_<date-time>) holds
vae.pt (the best weights by validation loss, which the RL side loads), checkpoints/last.pt
(written every epoch; --resume continues from it), tb/ (tensorboard), loss_curves.png,
reconstructions.png and metrics.json (losses, throughput, the whole-range linear probe of the
latent and the near-hole probe: RMSE in mm of where the hole is, vision/probe.py);
vkgrl_newton/vision/train.py describes each. A directory that already holds a run is never
reused without --resume. On --resume, --batch-size, --lr, --seed, --channels, --kl-weight,
--no-group-norm, --epochs and --device default to the run's own; --epochs may be raised.

Torch uses its default number of CPU threads. On a CPU that other jobs keep busy, that can be
far slower than one thread (OpenMP threads wait on each other): run with OMP_NUM_THREADS=1.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vkgrl_newton.cli_types import add_device_option, nonnegative_int, positive_float, positive_int  # noqa: E402
from vkgrl_newton.runtime import default_device, parse_cli  # noqa: E402  (light: Warp loads inside)
from vkgrl_newton.signals import describe, exit_code, stop_signals_as_interrupts  # noqa: E402


# VAEConfig().channels, named here so that --help needs no torch (tests/test_cli_reliability.py checks it)
DEFAULT_CHANNELS = (32, 64, 128, 256, 256)

DEFAULTS = {"epochs": 400, "batch_size": 128, "lr": 1e-3, "seed": 0, "kl_weight": 1.0,
            "group_norm": True}  # thesis Table 5.5, eq. 4.48, 5.6.1


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--images", type=Path, required=True, nargs="+",
                    help="image set directory (vision.dataset.ImageSetWriter); with --probe-only several sets "
                         "may be given, pooled: the probes are fitted on all their training splits and scored on "
                         "all their validation splits")
    ap.add_argument("--out", type=Path, default=None,
                    help="run directory (default runs/vae/<task>_r<resolution>_<date-time>)")
    ap.add_argument("--epochs", type=positive_int, default=None,
                    help="total epochs (default 400 as the thesis; a CPU wants ~20)")
    ap.add_argument("--batch-size", type=positive_int, default=None, help="default 128 (thesis)")
    ap.add_argument("--lr", type=positive_float, default=None, help="Adam learning rate (default 1e-3, thesis)")
    ap.add_argument("--seed", type=nonnegative_int, default=None, help="default 0")
    ap.add_argument("--channels", type=_channels, default=None, metavar="C1,C2,C3,C4,C5",
                    help=f"encoder widths, multiples of 8 (default {','.join(map(str, DEFAULT_CHANNELS))})")
    add_device_option(ap)
    ap.add_argument("--kl-warmup-epochs", type=nonnegative_int, default=None,
                    help="epochs over which the KL weight rises from 0 to --kl-weight (default 0, the thesis)")
    ap.add_argument("--kl-weight", type=positive_float, default=None,
                    help="weight of the KL term (default 1, eq. 4.48; the quick preset uses 0.01 at 64 px, see "
                         "vkgrl_newton/prepare/vision.py)")
    ap.add_argument("--no-group-norm", dest="group_norm", action="store_const", const=False, default=None,
                    help="no GroupNorm layers (the quick preset's CPU setting; default: GroupNorm(8) as 5.6.1)")
    ap.add_argument("--resume", action="store_true", help="continue the run in --out from checkpoints/last.pt")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--probe-only", type=Path, default=None, metavar="VAE_PT",
                    help="train nothing: print both probes of this vae.pt on --images as JSON (writes no file); "
                         "--batch-size sets the encoder's batch (default 128)")
    return ap


def _channels(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 5 or min(values) < 1:
        raise argparse.ArgumentTypeError(f"must be 5 comma-separated positive integers, got {text!r}")
    return values


def _device(ap: argparse.ArgumentParser, text: str | None) -> str:
    import torch

    if text is None:
        return default_device()
    try:
        device = torch.device(text)
    except RuntimeError:
        ap.error(f"--device {text!r} is not a torch device (cpu, cuda, cuda:0, ...)")
    if device.type == "cuda" and not torch.cuda.is_available():
        ap.error(f"--device {text}: CUDA is not available here; use --device cpu")
    if device.type not in ("cpu", "cuda"):
        ap.error(f"--device {text}: only cpu and cuda are supported")
    return text


def main(argv=None) -> int:
    ap = build_parser()
    args = parse_cli(ap, argv)
    # the heavy modules, once the arguments parse (--help and argparse errors answer without them)
    import torch
    from tqdm import tqdm

    from vkgrl_newton.vision.dataset import ImageSet
    from vkgrl_newton.vision.train import CHECKPOINT, train_vae
    from vkgrl_newton.vision.vae import VAEConfig, load_vae

    if len(args.images) > 1 and args.probe_only is None:
        ap.error(f"--images: {len(args.images)} image sets given; a VAE trains on one (several only with --probe-only)")
    try:
        sets = [ImageSet(d) for d in args.images]
    except (FileNotFoundError, ValueError) as e:
        ap.error(f"--images: {e}")
    images = sets[0]
    if args.probe_only is not None:
        import json

        from vkgrl_newton.vision.train import describe_near_hole_probe, probe_vae

        try:
            probes = probe_vae(args.probe_only, [s.dir for s in sets], batch_size=args.batch_size or 128,
                               device=_device(ap, args.device))
        except (FileNotFoundError, ValueError) as e:
            ap.error(f"--probe-only: {e}")
        print(describe_near_hole_probe(probes["probe_near_hole"]), file=sys.stderr)
        print(json.dumps(probes, indent=2))
        return 0
    if args.resume:  # the run's settings come from its checkpoint unless given again (then they must agree)
        if args.out is None:
            ap.error("--resume needs --out (the run directory to continue)")
        try:
            _, payload = load_vae(args.out / CHECKPOINT, map_location="cpu")
        except (FileNotFoundError, ValueError) as e:
            ap.error(f"--resume: {e}")
        if payload.get("extra") is None or payload.get("epoch") is None:
            ap.error(f"--resume: {args.out / CHECKPOINT} holds weights only, not a train_vae checkpoint")
        meta = payload["meta"]
        saved = {"batch_size": meta["batch_size"], "lr": meta["lr"], "seed": meta["seed"],
                 "kl_warmup_epochs": meta.get("kl_warmup_epochs", 0), "kl_weight": meta.get("kl_weight", 1.0),
                 "group_norm": payload["config"].get("group_norm", True),
                 "channels": tuple(payload["config"]["channels"]), "epochs": payload["extra"]["epochs"]}
        for name, value in saved.items():
            given = getattr(args, name)
            if given is None:
                setattr(args, name, value)
            elif name != "epochs" and given != value:
                flag = "--no-group-norm" if name == "group_norm" else f"--{name.replace('_', '-')} {given}"
                ap.error(f"{flag}: the run in {args.out} was trained with {name}={value}; "
                         "drop the flag to keep the run's value, or start a new run")
        if args.epochs < payload["epoch"]:
            ap.error(f"--epochs {args.epochs}: the run in {args.out} has trained {payload['epoch']} epochs already")
        same_set = {k: meta[k] for k in ("task", "resolution", "image_count", "num_train", "num_val")}
        this_set = {"task": images.task, "resolution": images.resolution, "image_count": len(images),
                    "num_train": len(images.train_idx), "num_val": len(images.val_idx)}
        if same_set != this_set:
            ap.error(f"--images {images.dir} ({this_set}) is not the image set the run in {args.out} was trained "
                     f"on ({meta['image_dir']}: {same_set})")
        run_device = payload["extra"]["noise_device"]
        if args.device is None:
            args.device = "cuda:0" if run_device == "cuda" else "cpu"
        elif torch.device(_device(ap, args.device)).type != run_device:
            ap.error(f"--device {args.device}: the run in {args.out} was trained on {run_device}; resume it there "
                     "(its random stream is device-specific)")
    device = _device(ap, args.device)
    for name, value in DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    config = None
    if args.channels is not None or not args.group_norm:
        try:
            config = VAEConfig(resolution=images.resolution, channels=args.channels or VAEConfig().channels,
                               group_norm=args.group_norm)
        except ValueError as e:
            ap.error(f"--channels: {e}")
    out = args.out or Path("runs/vae") / f"{images.task}_r{images.resolution}_{time.strftime('%Y%m%d-%H%M%S')}"
    if not args.resume and out.exists() and (not out.is_dir() or any(out.iterdir())):
        ap.error(f"--out {out} already holds a run; pass --resume to continue it or choose another directory")
    from vkgrl_newton._io import output_path_error

    if why := output_path_error(out, "--out", may_exist=True):  # (before the first epoch, not at its checkpoint)
        ap.error(why)
    try:
        train_vae(images.dir, out, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, seed=args.seed,
                  kl_warmup_epochs=args.kl_warmup_epochs or 0, kl_weight=args.kl_weight,
                  device=device, config=config, resume=args.resume, progress=not args.no_progress, log=tqdm.write)
    except KeyboardInterrupt as e:  # the epochs finished so far are checkpointed in --out
        print(f"train/train_vae.py: {describe(e)}; --resume --out {out} continues from its last checkpoint",
              file=sys.stderr)
        return exit_code(e)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    with stop_signals_as_interrupts():  # SIGTERM / SIGHUP as Ctrl-C: the checkpoint path above
        sys.exit(main())
