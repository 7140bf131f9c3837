"""Fit the KMP prior of a demonstration file and draw it (like thesis Figs. 6.1-6.6).

    python train/plot_kmp.py --demos DEMOS.npz [--action-dim 6] [--out DIR]
    python train/plot_kmp.py --synthetic PegInsert [--num-demos 10] [--action-dim 6] [--out DIR]

Writes to --out (default: beside the demonstrations):
  - kmp_<task>_<D>d.png: per component (x, y, z in mm; rx, ry, rz in degrees) over normalized
    time: the demonstrations, the GMR reference +-2 sigma, the KMP mean (eq. 3.29) with its
    +-2 sigma envelope (eq. 3.37, lambda_c), and the KGRL prior m[n] with the band a
    saturated action can reach (m[n] +- sum_j |B[n]_kj w_j|, every action in [-1, 1], Table 5.4 weights);
  - the per-step tables `<demos>.kmp<D>d.npz` beside the demonstrations (reused when current);
and prints how the prior follows the demonstrations (vkgrl_newton.kmp.prior.prior_fit: the largest
gap between m[n] and their mean, the reference's sd against theirs, the reach of a full action).
With --synthetic the demonstrations come from the synthetic demonstrator and are saved to
--out first (an existing file of the same name and parameters is reused, never overwritten).

Success criteria a reader can check on the plot: the KMP mean stays inside the GMR band, the
prior m[n] follows it, and the reach band narrows where the demonstrations agree.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from vkgrl_newton.kmp import (  # noqa: E402
    KMP_BETA,
    KMP_L,
    KMP_LAMBDA,
    DemoSet,
    gmr,
    kmp_covariance,
    kmp_mean,
    load_or_fit_prior,
    synthetic_demos,
)
from vkgrl_newton._io import output_path_error  # noqa: E402
from vkgrl_newton.cli_types import nonnegative_float, positive_float, seed_error  # noqa: E402
from vkgrl_newton.kmp.prior import format_prior_fit, prior_fit  # noqa: E402
from vkgrl_newton.signals import run_cli  # noqa: E402
from vkgrl_newton.kmp.tables import control_grid  # noqa: E402
from vkgrl_newton.tasks import TASKS, get_task  # noqa: E402

COMPONENTS = ("x", "y", "z", "rx", "ry", "rz")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--demos", type=Path, help="demonstration file (npz, see vkgrl_newton.kmp.demos)")
    src.add_argument("--synthetic", choices=sorted(TASKS), help="use synthetic demonstrations of this task")
    p.add_argument("--num-demos", type=int, default=10, help="synthetic demonstrations to draw (default 10)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--action-dim", type=int, choices=(4, 6), default=None,
                   help="4 (xyz + yaw) or 6; default: the demonstrations' own")
    p.add_argument("--lam", type=positive_float, default=KMP_LAMBDA)
    p.add_argument("--beta", type=nonnegative_float, default=KMP_BETA)
    p.add_argument("--l", type=positive_float, default=KMP_L, help="kernel exp(-l (s_i - s_j)^2)")
    p.add_argument("--reference", choices=("gmr", "empirical"), default="gmr",
                   help="the KMP's reference distribution: gmr (the thesis) or empirical (the demonstrations' "
                        "per-step mean and covariance)")
    p.add_argument("--lam-c", type=positive_float, default=60.0, help="lambda of the KMP covariance, eq. 3.37 (Huang: 60)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: beside the demonstrations)")
    args = p.parse_args(argv)
    # (checked before the synthetic demonstrations are drawn and written to --out)
    if args.num_demos < 2:
        p.error(f"--num-demos {args.num_demos}: must be >= 2 (a distribution needs several demonstrations)")
    for why in (seed_error("--seed", args.seed), args.out and output_path_error(args.out, "--out", may_exist=True)):
        if why:
            p.error(why)
    return args


def synthetic_demo_file(task: str, num_demos: int, action_dim: int, seed: int, out: Path) -> Path:
    path = out / f"synthetic_{task}_{action_dim}d_n{num_demos}_seed{seed}.npz"
    if path.exists():
        found = DemoSet.load(path)
        if (found.task, found.num_demos, found.action_dim, found.source) != (task, num_demos, action_dim, "synthetic"):
            raise SystemExit(f"error: {path} exists but is not the synthetic set this run would draw; "
                             "move it away or choose another --out")
        return path
    return synthetic_demos(task, num_demos, action_dim=action_dim, seed=seed).save(path)


def plot_prior(demos: DemoSet, tables, lam: float, lam_c: float, path: Path) -> Path:
    spec = get_task(demos.task)
    s = control_grid(tables.dt)
    mu, sigma = gmr(tables.gmm, s)
    kmp_mu = kmp_mean(s, s, mu, sigma, lam, tables.l)
    kmp_sig = kmp_covariance(s, s, sigma, lam_c, tables.l)
    w = torch.tensor([spec.w_pos] * 3 + [spec.w_rot] * 3, dtype=torch.float64)
    reach = (tables.gain * w[None, None, :]).abs().sum(dim=2)  # all action axes saturated, per component
    std_gmr = torch.sqrt(torch.diagonal(sigma, dim1=1, dim2=2))
    std_kmp = torch.sqrt(torch.diagonal(kmp_sig, dim1=1, dim2=2).clamp(min=0))
    comps = [0, 1, 2, 3, 4, 5] if tables.action_dim == 6 else [0, 1, 2, 5]
    fig, axes = plt.subplots(2, 3, figsize=(15, 7.5), sharex=True)
    for k, ax in zip(range(6), axes.reshape(-1)):
        scale, unit = (1e3, "mm") if k < 3 else (180.0 / math.pi, "deg")
        ax.set_title(f"{COMPONENTS[k]} [{unit}]")
        if k not in comps:
            ax.text(0.5, 0.5, "held at the reference (4D)", ha="center", va="center", transform=ax.transAxes)
            continue
        for i, (sd, ed) in enumerate(demos.split()):
            ax.plot(sd, ed[:, k] * scale, color="0.55", lw=0.6, alpha=0.7, label="demonstrations" if i == 0 else None)
        band = lambda m, sd, c, a, lab: ax.fill_between(s, (m - 2 * sd) * scale, (m + 2 * sd) * scale,
                                                        color=c, alpha=a, lw=0, label=lab)
        band(mu[:, k], std_gmr[:, k], "0.3", 0.18, "GMR reference ±2σ")
        band(kmp_mu[:, k], std_kmp[:, k], "tab:blue", 0.15, f"KMP ±2σ (eq. 3.37, λc={lam_c:g})")
        ax.plot(s, kmp_mu[:, k] * scale, color="tab:blue", lw=1.8, label=f"KMP mean (eq. 3.29, λ={lam:g})")
        ax.fill_between(s, (tables.mean[:, k] - reach[:, k]) * scale, (tables.mean[:, k] + reach[:, k]) * scale,
                        color="tab:orange", alpha=0.3, lw=0, label="KGRL reach, a in [-1,1]^D")
        ax.plot(s, tables.mean[:, k] * scale, color="tab:orange", lw=1.2, ls="--", label="KGRL prior m[n] (ζ=0)")
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("normalized time s")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=6, fontsize=9, frameon=False)
    fig.suptitle(
        f"{demos.task} {tables.action_dim}D: {demos.num_demos} {demos.source} demonstrations, "
        f"KMP dt 1/{tables.n_steps}, h={tables.horizon}, λ={tables.lam:g}, β={tables.beta:g}, l={tables.l:g}, "
        f"w=({spec.w_pos:g}, {spec.w_rot:g})"
    )
    fig.tight_layout(rect=(0, 0.05, 1, 0.96))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    args = parse_args(argv)
    try:  # a damaged demonstration file (given, or a synthetic one found at --out): one line, exit 2
        if args.synthetic:
            out = args.out or Path("runs/kmp_demo")
            action_dim = args.action_dim or 6
            demo_path = synthetic_demo_file(args.synthetic, args.num_demos, action_dim, args.seed, out)
        else:
            demo_path = args.demos
            if not demo_path.exists():
                print(f"error: demonstration file {demo_path} does not exist", file=sys.stderr)
                return 2
            out = args.out or demo_path.parent
        demos = DemoSet.load(demo_path)
        png = out / f"kmp_{demos.task}_{args.action_dim or demos.action_dim}d.png"
        if png.exists():  # a plot of other parameters is a result too: never overwritten (before the fit)
            print(f"error: --out {out}: {png.name} exists; choose another --out or move it (plots are never "
                  "overwritten)", file=sys.stderr)
            return 2
        tables, tables_path, rebuilt = load_or_fit_prior(
            demo_path, args.action_dim, args.lam, args.beta, args.l, seed=args.seed, reference=args.reference
        )
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    action_dim = tables.action_dim
    png = plot_prior(demos, tables, args.lam, args.lam_c, out / f"kmp_{demos.task}_{action_dim}d.png")  # (= png)
    print(f"demonstrations: {demo_path} ({demos.num_demos} x {demos.source})")
    print(f"KMP tables:     {tables_path} ({'fitted' if rebuilt else 'cached'})")
    print(f"plot:           {png}")
    print(format_prior_fit(prior_fit(tables, demos)))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main, "train/plot_kmp.py", "nothing was written"))
