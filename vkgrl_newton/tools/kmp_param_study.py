"""The numbers behind the KMP defaults (lam, beta, l): `python -m vkgrl_newton.tools.kmp_param_study`.

For each (lam, beta, l) it builds the per-step tables of a task from synthetic
demonstrations (Table 5.2 spread, 1 mm target noise) and reports, over the control grid:
  cond      max condition number of K + gamma Sigma (what the float64 Cholesky must carry);
  fit_mm    max |m[n] - mu_GMR(s_n)| over position axes, mm (how faithfully the prior follows the demos);
  fit_deg   the same over rotation axes, degrees;
  reach_mm  median over steps of the largest position move of one action axis at |a| = 1
            (|B[n] w e_i| with the Table 5.4 weights w_pos, w_rot), mm;
  reach_deg the same for rotation, degrees;
  r/sig     median over steps and axes of reach / (GMR standard deviation) for position: 1 means
            a full action moves the command by one demonstrated standard deviation.
"""

from __future__ import annotations

import argparse
import itertools
import math

import torch

from ..runtime import parse_cli
from ..tasks import get_task
from ..kmp.demos import synthetic_demos
from ..kmp.gmr import fit_gmm, gmr
from ..kmp.tables import build_kmp_tables, control_grid, reference_window


def study_row(gmm, spec, lam, beta, l, action_dim=6) -> dict:
    tables = build_kmp_tables(gmm, spec.kmp_dt, spec.kmp_horizon, lam, beta, l, action_dim)
    grid = control_grid(spec.kmp_dt)
    mu, sigma = gmr(gmm, grid)
    win = reference_window(spec.kmp_dt, spec.kmp_horizon)
    mu_w, sig_w = gmr(gmm, win.reshape(-1))
    w_len = win.shape[1]
    sig_w = sig_w.reshape(-1, w_len, 6, 6)
    k = torch.exp(-l * (win[:, :, None] - win[:, None, :]) ** 2)
    gamma = lam + beta
    big = torch.kron(k, torch.eye(6, dtype=torch.float64)) + gamma * torch.stack(
        [torch.block_diag(*sig_w[i].unbind(0)) for i in range(sig_w.shape[0])]
    )
    cond = torch.linalg.cond(big).max().item()
    fit = (tables.mean - mu).abs()
    w = torch.tensor([spec.w_pos] * 3 + [spec.w_rot] * 3, dtype=torch.float64)
    moves = (tables.gain * w[None, None, :]).abs()  # column j: move per unit action on axis j
    reach_pos = torch.linalg.vector_norm(moves[:, :3, :3], dim=1).amax(dim=1)
    reach_rot = torch.linalg.vector_norm(moves[:, 3:, 3:], dim=1).amax(dim=1)
    std_pos = torch.sqrt(torch.diagonal(sigma, dim1=1, dim2=2)[:, :3])
    per_axis = torch.linalg.vector_norm(moves[:, :3, :3], dim=1) / std_pos
    return dict(
        lam=lam,
        beta=beta,
        l=l,
        cond=cond,
        fit_mm=fit[:, :3].max().item() * 1e3,
        fit_deg=math.degrees(fit[:, 3:].max().item()),
        reach_mm=reach_pos.median().item() * 1e3,
        reach_deg=math.degrees(reach_rot.median().item()),
        r_over_sigma=per_axis.median().item(),
    )


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="PegInsert")
    p.add_argument("--num-demos", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    # the grid the defaults in prior.py were chosen from
    p.add_argument("--lam", type=float, nargs="+", default=[0.1, 1.0, 6.0])
    p.add_argument("--beta", type=float, nargs="+", default=[1.0, 2.0, 3.0, 4.0, 6.0, 10.0, 30.0])
    p.add_argument("--l", type=float, nargs="+", default=[2.0, 20.0, 200.0, 1000.0])
    args = parse_cli(p, argv)
    spec = get_task(args.task)
    demos = synthetic_demos(spec.name, args.num_demos, action_dim=6, seed=args.seed)
    gmm = fit_gmm(demos.s, demos.eta, seed=args.seed)
    print(f"{spec.name}: {args.num_demos} synthetic demos, KMP dt 1/{spec.kmp_steps}, h {spec.kmp_horizon}, "
          f"w_pos {spec.w_pos}, w_rot {spec.w_rot}")
    print(f"{'lam':>6} {'beta':>6} {'l':>6} {'cond':>10} {'fit_mm':>8} {'fit_deg':>8} {'reach_mm':>9} {'reach_deg':>9} {'r/sig':>7}")
    for lam, beta, l in itertools.product(args.lam, args.beta, args.l):
        r = study_row(gmm, spec, lam, beta, l)
        print(f"{lam:6g} {beta:6g} {l:6g} {r['cond']:10.3g} {r['fit_mm']:8.3f} {r['fit_deg']:8.3f} "
              f"{r['reach_mm']:9.3f} {r['reach_deg']:9.3f} {r['r_over_sigma']:7.3f}")


if __name__ == "__main__":
    main()
