"""Every check that needs a GPU, in one command and one JSON report.

    python -m vkgrl_newton.tools.gpu_check --out docs/gpu_check_<device>.json
    (`python -m vkgrl_newton.gpu_check` still works: it forwards here)

Run that once on a CUDA machine (e.g. `--out docs/gpu_check_h200.json`) and put the figures into
docs/log/benchmarks.md with the device named (the report's `meta.device_name`). It takes about 10
minutes: `--budget-s` (default 600) is checked before each check and before each (task, worlds)
run of graph_vs_eager; from the first one that starts after the budget is spent, everything left
is recorded as {"skipped": "time budget"}. A run that has started finishes, so the command can
outlast the budget by one run; where a machine gives a hard 10-minute limit per command, pass e.g.
`--budget-s 420`. A machine whose Warp kernel cache is empty first compiles Newton's, MuJoCo-Warp's
and this package's kernels for CUDA (minutes, counted in the budget). The report is written after
each check (`"complete": false` until the end), so a run killed from outside still leaves what it
measured.

The checks (`--checks`, default all four; they run in the order sac_updates, kernel_bench,
parts_mesh, graph_vs_eager: the bounded ones first, then the graph/eager sizes, smallest first,
until the budget):
1. graph_vs_eager: per task (`--tasks`) and world count (`--worlds`; CUDA 128 1024 4096, CPU 4),
   two envs (Factory, 4-D actions, seed 0), the physics eager (EnvConfig.graph=False) and as one
   captured graph (True), driven by the scripted demonstrator through `step_pose` for two untimed
   warm-up steps (the first runs eagerly, the second records the graph) and `--steps` timed steps
   (CUDA 20, CPU 3), then 3 steps of fixed delta actions through `step` (the SAC path: the
   delta-command kernel in its own graph). `bitwise_equal`: torch.equal of state_0.body_q and of
   obs["policy"] after every step, both modes; `max_abs_diff` of each;
   throughput of both modes (env_steps_per_s = worlds x steps / wall, ms_per_env_step; the device
   synchronized before the clock is read). From 1024 worlds on, the eager env runs only
   min(3, --steps) steps (equality over those, its throughput from those), the graph env all of
   them. Where graph and eager differ, a second eager env is run over the compared steps
   (`eager_vs_eager_bitwise_equal`): it tells a graph bug from a nondeterministic device.
2. parts_mesh: vkgrl_newton.tools.parts with the mesh + SDF geometry on the device: NutThread
   advances one pitch (2 mm) per clockwise turn within 10 %, GearMesh seats when aligned and is
   blocked 20 mm higher when turned by half a tooth (the scenarios of `parts.main`, the criteria
   of tests/test_parts.py; `passed`). On a CPU there is no SDF and the triangle BVH is slow: only
   with `--cpu-parts`.
3. kernel_bench: vkgrl_newton.tools.bench_kernels on the device, its JSON embedded (CUDA: every case,
   its default batches and repeats; CPU: kmp_horizon, 5 repeats).
4. sac_updates: gradient updates (CUDA 200, CPU 20) of the thesis SAC (Table 5.3: [512, 256, 128]
   ELU, 2 critics, batch 256, policy_delay 4) on observation dim 8 and action dim 4, as
   vkgrl_newton.tools.bench_sac's `ours_thesis` variant: grad_steps_per_s.

Each check records its wall time (`wall_s`); an exception in one is recorded as
{"error": "<type>: <message>"} and the others still run. Exit code 0 when no check that ran has an
error, every graph_vs_eager run is bitwise equal and parts_mesh (when run) passed; else 1. An
existing --out file is never overwritten.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import math
import os
import platform
import sys
import tempfile
import time
import traceback
from datetime import datetime, timezone
from pathlib import Path

import torch
import warp as wp

from .._io import atomic_write, atomic_write_text
from ..cli_types import add_device_option, device_name
from ..runtime import parse_cli, torch_device
from ..signals import run_cli

__all__ = ["CHECKS", "TASKS", "main", "cli", "check_graph_vs_eager", "check_parts_mesh", "check_kernel_bench",
           "check_sac_updates"]

CHECKS = ("graph_vs_eager", "parts_mesh", "kernel_bench", "sac_updates")
RUN_ORDER = ("sac_updates", "kernel_bench", "parts_mesh", "graph_vs_eager")
TASKS = ("PegInsert", "GearMesh", "NutThread")
BIG_WORLDS = 1024  # from here on graph_vs_eager times the graph only (eager: equality over EQ_STEPS_BIG)
EQ_STEPS_BIG = 3
DEFAULTS = {  # (cuda, cpu)
    "worlds": ([128, 1024, 4096], [4]),
    "steps": (20, 3),
    "sac_updates": (200, 20),
}
SKIPPED_BUDGET = {"skipped": "time budget"}


def _error(e: BaseException) -> dict:
    msg = str(e).strip().splitlines()
    return {"error": f"{type(e).__name__}: {msg[0][:500] if msg else ''}"}


def _num(x: float):
    """A float for JSON: NaN and infinities as strings (strict JSON has neither)."""
    x = float(x)
    return x if math.isfinite(x) else str(x)


class Budget:
    def __init__(self, seconds: float):
        self.t0, self.seconds = time.perf_counter(), seconds

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def spent(self) -> bool:
        return self.elapsed() > self.seconds


# ----------------------------------------------------------------------------- 1. graph vs eager
def _run_env(task: str, n: int, dev: str, graph: bool, steps: int, record: int) -> dict:
    """One env, the scripted demonstrator for 2 warm-up + `steps` steps through `step_pose`, then 3
    steps of fixed delta actions through `step`; body_q and obs of the first `record` pose steps
    (warm-up included) and of the 3 delta steps kept on the device; the `steps` after the warm-up timed."""
    from ..envs.assembly_env import AssemblyEnv, EnvConfig
    from ..envs.scripted import ScriptedInserter

    t0 = time.perf_counter()
    env = AssemblyEnv(EnvConfig(task=task, num_envs=n, action_dim=4, family="factory", device=dev, graph=graph))
    inserter = ScriptedInserter(seed=0)
    inserter.reset(env)
    wp.synchronize_device(dev)
    build_s = time.perf_counter() - t0
    body_q, obs_rec = [], []

    def step(i):
        obs = env.step_pose(*inserter.act(env))[0]
        if i < record:
            body_q.append(wp.to_torch(env.state_0.body_q).clone())
            obs_rec.append(obs["policy"].clone())

    step(0)  # warm-up: the first control step runs eagerly (kernels compile) ...
    step(1)  # ... and the second records the graph (and replays it): both untimed
    wp.synchronize_device(dev)
    t0 = time.perf_counter()
    for i in range(2, steps + 2):
        step(i)
    wp.synchronize_device(dev)
    wall = time.perf_counter() - t0
    # then the SAC path (delta actions: the delta-command kernel inside the graph), 3 recorded steps
    # of fixed actions: eager, captured, replayed
    g = torch.Generator(device=env.tdev).manual_seed(7)
    delta_body_q, delta_obs = [], []
    for _ in range(3):
        obs = env.step(0.5 * (2 * torch.rand(n, 4, device=env.tdev, generator=g) - 1))[0]
        delta_body_q.append(wp.to_torch(env.state_0.body_q).clone())
        delta_obs.append(obs["policy"].clone())
    out = {
        "timing": {"timed_steps": steps, "wall_s": wall, "ms_per_env_step": wall / steps * 1e3,
                   "env_steps_per_s": n * steps / wall, "build_s": build_s,
                   "captures": env.physics.captures, "physics_resets": env.physics_resets_total,
                   "contact_overflows": env.contact_overflows_total},
        "body_q": body_q, "obs": obs_rec, "delta_body_q": delta_body_q, "delta_obs": delta_obs,
    }
    del env, inserter
    gc.collect()
    return out


def _compare(a: dict, b: dict, k: int, delta: bool = True) -> dict:
    """The first k pose steps; with `delta`, also the 3 delta-action steps after them (only when both
    envs ran the same number of pose steps before, i.e. start the delta steps from the same state)."""
    res = {}
    first = None
    for key in ("body_q", "obs"):
        eq, diff = True, 0.0
        pairs = list(zip(a[key][:k], b[key][:k]))
        if delta:
            pairs += list(zip(a["delta_" + key], b["delta_" + key]))
        for i, (x, y) in enumerate(pairs):
            if not torch.equal(x, y):
                eq = False
                first = i if first is None else min(first, i)
            diff = max(diff, float((x.double() - y.double()).abs().max()) if x.numel() else 0.0)
        res[key] = (eq, diff)
    return {
        "bitwise_equal": res["body_q"][0] and res["obs"][0],
        "bitwise_equal_body_q": res["body_q"][0], "bitwise_equal_obs": res["obs"][0],
        "max_abs_diff": {"body_q": _num(res["body_q"][1]), "obs": _num(res["obs"][1])},
        "compared_steps": k, "compared_delta_steps": 3 if delta else 0,
        "first_differing_step": first,  # 0, 1: the warm-up steps; k.. the delta-action steps
    }


def graph_vs_eager_one(task: str, n: int, dev: str, steps: int) -> dict:
    eager_steps = steps if n < BIG_WORLDS else min(EQ_STEPS_BIG, steps)
    k = 2 + eager_steps  # compared: the warm-up steps and the eager env's timed steps
    eager = _run_env(task, n, dev, graph=False, steps=eager_steps, record=k)
    graph = _run_env(task, n, dev, graph=True, steps=steps, record=k)
    entry = _compare(eager, graph, k, delta=eager_steps == steps)
    entry.update(eager=eager.pop("timing"), graph=graph.pop("timing"))
    del graph
    gc.collect()
    if not entry["bitwise_equal"]:  # a graph bug, or a device that is not deterministic?
        again = _run_env(task, n, dev, graph=False, steps=eager_steps, record=k)
        entry["eager_vs_eager_bitwise_equal"] = _compare(eager, again, k, delta=True)["bitwise_equal"]
        del again
    del eager
    gc.collect()
    return entry


def check_graph_vs_eager(dev: str, tasks, worlds, steps: int, budget: Budget, log=print) -> dict:
    results: dict[str, dict[str, dict]] = {t: {} for t in tasks}
    for n in sorted(worlds):
        for task in tasks:
            if budget.spent():
                results[task][str(n)] = dict(SKIPPED_BUDGET)
                continue
            t0 = time.perf_counter()
            try:
                entry = graph_vs_eager_one(task, n, dev, steps)
            except Exception as e:  # noqa: BLE001 - recorded; the other sizes still run
                entry = _error(e)
                gc.collect()
            entry["wall_s"] = time.perf_counter() - t0
            results[task][str(n)] = entry
            if "error" in entry:
                log(f"  graph_vs_eager {task} {n}: {entry['error']}")
            else:
                log(f"  graph_vs_eager {task} {n}: bitwise_equal {entry['bitwise_equal']}, graph "
                    f"{entry['graph']['env_steps_per_s']:.1f} env steps/s, eager "
                    f"{entry['eager']['env_steps_per_s']:.1f} ({entry['wall_s']:.0f} s)")
    return {"steps": steps, "worlds": sorted(worlds), "tasks": list(tasks), "results": results}


# ----------------------------------------------------------------------------- 2. parts, mesh + SDF
def check_parts_mesh(dev: str) -> dict:
    """parts.main's two scenarios with geometry "mesh" on `dev`, measured and judged by the
    criteria of tests/test_parts.py."""
    import numpy as np

    from ..assets_usd.dimensions import GEAR_HEIGHT, GEAR_MEDIUM_X, GEAR_TEETH, THREAD_PITCH
    from .parts import advance_per_turn, build_parts, nut_rest_height, run_drive
    from ..sim.scene import SimConfig

    out = {}
    t0 = time.perf_counter()
    try:
        sim = build_parts("NutThread", config=SimConfig(num_worlds=1, device=dev, geometry="mesh"))
        yaw0 = math.pi / 2
        z0 = nut_rest_height(yaw0) - THREAD_PITCH  # the mesh bolt's top turn is the runout: one lower
        r = run_drive(sim, (0.0, 0.0, z0), yaw0, 1.0, force_z=-0.5, omega_des=-2 * math.pi, torque_kd=1e-3)
        turns = (yaw0 - r.yaw[-1, 0]) / (2 * math.pi)
        adv = advance_per_turn(r)
        off_axis = float(np.hypot(r.pos[-1, 0, 0], r.pos[-1, 0, 1]))
        tilt = float(r.tilt.max())
        nut = {"clockwise_turns": float(turns), "dz_mm": 1e3 * float(r.pos[-1, 0, 2] - r.pos[0, 0, 2]),
               "advance_mm_per_turn": 1e3 * adv, "max_tilt_deg": math.degrees(tilt),
               "off_axis_mm": 1e3 * off_axis, "mean_contacts": float(r.contacts.mean())}
        nut["passed"] = bool(turns > 0.4 and abs(adv - THREAD_PITCH) <= 0.1 * THREAD_PITCH
                             and tilt < math.radians(5.0) and off_axis < 0.0005)
    except Exception as e:  # noqa: BLE001
        nut = _error(e)
    nut["wall_s"] = time.perf_counter() - t0
    out["NutThread"] = nut
    gc.collect()

    t0 = time.perf_counter()
    try:
        sim = build_parts("GearMesh", config=SimConfig(num_worlds=2, device=dev, geometry="mesh"))
        pitch = 2 * math.pi / GEAR_TEETH["medium"]
        r = run_drive(sim, (GEAR_MEDIUM_X, 0.0, 0.03), [0.0, pitch / 2], 0.5, force_z=-1.0)
        z_aligned, z_blocked = float(r.pos[-1, 0, 2]), float(r.pos[-1, 1, 2])
        xy = float(np.hypot(r.pos[-1, 0, 0] - GEAR_MEDIUM_X, r.pos[-1, 0, 1]))
        gear = {"aligned_z_mm": 1e3 * z_aligned, "misaligned_z_mm": 1e3 * z_blocked,
                "aligned_xy_offset_mm": 1e3 * xy,
                "max_tilt_deg": [math.degrees(float(r.tilt[:, w].max())) for w in (0, 1)],
                "mean_contacts": float(r.contacts.mean())}
        gear["passed"] = bool(abs(z_aligned) < 0.0005 and abs(z_blocked - GEAR_HEIGHT) <= 0.0005 and xy < 0.0005)
    except Exception as e:  # noqa: BLE001
        gear = _error(e)
    gear["wall_s"] = time.perf_counter() - t0
    out["GearMesh"] = gear
    out["passed"] = all(v.get("passed", False) for v in (nut, gear))
    return out


# ----------------------------------------------------------------------------- 3. kernel bench
def check_kernel_bench(dev: str, verbose: bool = False) -> dict:
    from . import bench_kernels as bench

    cuda = wp.get_device(dev).is_cuda
    threads = torch.get_num_threads()  # bench pins torch's CPU threads (--torch-threads): restored below
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "kernels.json"
        argv = ["--devices", dev, "--json", str(path)]
        if not cuda:
            argv += ["--only", "kmp_horizon", "--repeats", "5", "--warmup", "2"]
        if verbose:
            argv.append("--verbose")
        try:
            rc = bench.main(argv)
        except SystemExit as e:  # bench's argument errors
            raise RuntimeError(f"bench_kernels {argv}: {e}") from None
        finally:
            torch.set_num_threads(threads)
        if rc not in (0, None):
            raise RuntimeError(f"bench_kernels returned {rc}")
        result = json.loads(path.read_text())
    result["argv"] = argv
    return result


# ----------------------------------------------------------------------------- 4. SAC updates
def check_sac_updates(dev: str, updates: int) -> dict:
    """bench_sac's ours_thesis on the torch device of `dev`: the thesis preset, replay buffer
    pre-filled with random transitions, one warm-up call, then `updates` timed gradient steps."""
    from .bench_sac import _random_transitions, make_ours

    tdev = torch.device(torch_device(dev))
    args = argparse.Namespace(fill=20_000, batch_size=256, hidden=[512, 256, 128], obs_dim=8, action_dim=4,
                              device=tdev)
    data = _random_transitions(args.fill, args.obs_dim, args.action_dim, seed=0)
    run, cpu_matmul = make_ours(args, data, policy_delay=4, cpu_matmul="auto")  # (cuBLAS on CUDA: "torch")

    def sync():
        if tdev.type == "cuda":
            torch.cuda.synchronize(tdev)

    run(max(1, min(8, updates)))  # warm-up: allocator, optimizer state, lazy init
    sync()
    t0 = time.perf_counter()
    run(updates)
    sync()
    wall = time.perf_counter() - t0
    return {"preset": "thesis", "variant": "ours_thesis (bench_sac)", "obs_dim": 8, "action_dim": 4,
            "hidden": args.hidden, "batch_size": 256, "policy_delay": 4, "torch_device": str(tdev), "cpu_matmul": cpu_matmul,
            "torch_threads": torch.get_num_threads(), "updates": updates, "timed_s": wall,
            "grad_steps_per_s": updates / wall}


# ----------------------------------------------------------------------------- report
def _meta(dev: str, argv, start: datetime) -> dict:
    import newton

    d = wp.get_device(dev)
    meta = {"device": dev, "device_name": d.name, "is_cuda": d.is_cuda, "warp": wp.config.version,
            "newton": getattr(newton, "__version__", None), "torch": torch.__version__,
            "python": platform.python_version(), "platform": platform.platform(), "cpu_count": os.cpu_count(),
            "start_utc": start.isoformat(timespec="seconds"), "argv": list(argv)}
    if d.is_cuda:
        meta["torch_cuda"] = torch.version.cuda
        with contextlib.suppress(Exception):
            props = torch.cuda.get_device_properties(torch.device(torch_device(dev)))
            meta["gpu_memory_gib"] = props.total_memory / 2**30
    return meta


def failures(report: dict) -> list[str]:
    """What makes the exit code 1: errors anywhere in a check that ran, graph/eager runs that
    are not bitwise equal, a parts_mesh criterion that failed."""
    out = []

    def walk(node, path):
        if isinstance(node, dict):
            if "error" in node:
                out.append(f"{path}: {node['error']}")
            for k, v in node.items():
                if k != "error":
                    walk(v, f"{path}.{k}")

    for name, res in report["checks"].items():
        walk(res, name)
        if name == "graph_vs_eager":
            for task, sizes in res.get("results", {}).items():
                for n, e in sizes.items():
                    if "bitwise_equal" in e and not e["bitwise_equal"]:
                        out.append(f"graph_vs_eager.{task}.{n}: graph and eager differ "
                                   f"(max abs diff {e['max_abs_diff']})")
        if name == "parts_mesh" and "passed" in res and not res["passed"]:
            out.append("parts_mesh: a criterion failed")
    return out


def summary(report: dict) -> str:
    lines = [f"gpu_check on {report['meta']['device']} ({report['meta']['device_name']}), "
             f"{report['wall_s']:.0f} s"]
    for name in CHECKS:
        res = report["checks"].get(name)
        if res is None:
            continue
        if "skipped" in res or "error" in res:
            lines.append(f"  {name}: {res.get('skipped') or res.get('error')}")
            continue
        if name == "graph_vs_eager":
            for task, sizes in res["results"].items():
                for n, e in sizes.items():
                    if "bitwise_equal" in e:
                        lines.append(f"  graph_vs_eager {task:9s} {n:>5} worlds: bitwise_equal {e['bitwise_equal']}, "
                                     f"graph {e['graph']['env_steps_per_s']:.1f} / eager "
                                     f"{e['eager']['env_steps_per_s']:.1f} env steps/s")
                    else:
                        lines.append(f"  graph_vs_eager {task:9s} {n:>5} worlds: {e.get('skipped') or e.get('error')}")
        elif name == "parts_mesh":
            for task in ("NutThread", "GearMesh"):
                e = res.get(task, {})
                detail = e.get("error") or (f"{e['advance_mm_per_turn']:.3f} mm/turn" if task == "NutThread"
                                            else f"z aligned {e['aligned_z_mm']:.2f} mm, misaligned "
                                                 f"{e['misaligned_z_mm']:.2f} mm")
                lines.append(f"  parts_mesh {task}: passed {e.get('passed', False)} ({detail})")
        elif name == "kernel_bench":
            lines.append(f"  kernel_bench: {len(res.get('rows', []))} rows")
        elif name == "sac_updates":
            lines.append(f"  sac_updates: {res['grad_steps_per_s']:.1f} grad steps/s ({res['updates']} updates)")
    return "\n".join(lines)


def _write(path: Path, report: dict, first: bool) -> None:
    text = json.dumps(report, indent=2)
    if first:
        atomic_write_text(path, text)  # never replaces a file that appeared meanwhile
    else:  # our own file, written by this run a moment ago
        atomic_write(path, True, lambda f: f.write(text.encode("utf-8")))


def _positive_int(flag):
    def parse(s):
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} takes integers >= 1, got {s!r}") from None
        if v < 1:
            raise argparse.ArgumentTypeError(f"{flag} takes integers >= 1, got {v}")
        return v
    return parse


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    ap = argparse.ArgumentParser(prog="python -m vkgrl_newton.tools.gpu_check", description=__doc__.split("\n")[0])
    add_device_option(ap)
    ap.add_argument("--out", type=Path, default=None,
                    help="report file, never overwritten (default runs/gpu_check/<device>_<UTC time>.json)")
    ap.add_argument("--worlds", type=_positive_int("--worlds"), nargs="+", default=None,
                    help="graph_vs_eager world counts (default: CUDA 128 1024 4096, CPU 4)")
    ap.add_argument("--steps", type=_positive_int("--steps"), default=None,
                    help="graph_vs_eager timed control steps (default: CUDA 20, CPU 3)")
    ap.add_argument("--tasks", nargs="+", choices=TASKS, default=list(TASKS), help="graph_vs_eager tasks")
    ap.add_argument("--checks", nargs="+", choices=CHECKS, default=list(CHECKS), help="checks to run")
    ap.add_argument("--cpu-parts", action="store_true", help="run parts_mesh on a CPU too (slow: no SDF)")
    ap.add_argument("--budget-s", type=float, default=600.0,
                    help="no check or graph_vs_eager size starts after this many seconds (default 600)")
    args = parse_cli(ap, argv, device=True)
    try:
        device = wp.get_device(args.device)
    except Exception:  # noqa: BLE001 - Warp's message varies by version
        ap.error(f"--device {args.device!r} is not a Warp device here; available: "
                 f"{[d.alias for d in wp.get_devices()]}")
    dev = device.alias
    cuda = device.is_cuda
    if not (args.budget_s > 0 and math.isfinite(args.budget_s)):
        ap.error(f"--budget-s must be a positive number of seconds, got {args.budget_s}")
    worlds = args.worlds or DEFAULTS["worlds"][0 if cuda else 1]
    steps = args.steps or DEFAULTS["steps"][0 if cuda else 1]
    if "graph_vs_eager" in args.checks:
        from ..tasks import get_task

        shortest = min(get_task(t).episode_steps for t in args.tasks)
        if 2 + steps + 3 >= shortest:
            ap.error(f"--steps {steps}: 2 warm-up + {steps} + 3 delta steps must stay inside one episode ({shortest} "
                     f"steps for {args.tasks}), so that no time-out reset is timed")
    start = datetime.now(timezone.utc)
    out = args.out
    if out is None:
        out = Path("runs/gpu_check") / f"{dev.replace(':', '')}_{start.strftime('%Y%m%dT%H%M%SZ')}.json"
    if out.exists():
        ap.error(f"--out {out} exists; choose another path (reports are never overwritten)")
    tasks = list(dict.fromkeys(args.tasks))
    selected = set(args.checks)

    budget = Budget(args.budget_s)
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    report = {"meta": _meta(dev, argv, start), "budget_s": args.budget_s, "complete": False, "wall_s": 0.0,
              "checks": {}}
    results: dict[str, dict] = {}
    first_write = True
    for name in RUN_ORDER:
        if name not in selected:
            continue
        if budget.spent():
            results[name] = dict(SKIPPED_BUDGET)
            continue
        if name == "parts_mesh" and not cuda and not args.cpu_parts:
            results[name] = {"skipped": "cpu: mesh SDF needs CUDA"}
            continue
        log(f"[gpu_check] {name} ({budget.elapsed():.0f} s elapsed)")
        t0 = time.perf_counter()
        try:
            if name == "graph_vs_eager":
                res = check_graph_vs_eager(dev, tasks, worlds, steps, budget, log=log)
            elif name == "parts_mesh":
                res = check_parts_mesh(dev)
            elif name == "kernel_bench":
                res = check_kernel_bench(dev, verbose=args.verbose)
            else:
                res = check_sac_updates(dev, DEFAULTS["sac_updates"][0 if cuda else 1])
        except Exception as e:  # noqa: BLE001 - recorded; the other checks still run
            res = _error(e)
            if args.verbose:
                traceback.print_exc()
        res["wall_s"] = time.perf_counter() - t0
        results[name] = res
        gc.collect()
        report["checks"] = {k: results[k] for k in CHECKS if k in results}
        report["wall_s"] = budget.elapsed()
        _write(out, report, first_write)
        first_write = False
    report["checks"] = {k: results[k] for k in CHECKS if k in results}
    report["wall_s"] = budget.elapsed()
    report["complete"] = True
    failed = failures(report)
    report["failures"] = failed
    _write(out, report, first_write)
    print(summary(report))
    for f in failed:
        print(f"  FAILED {f}")
    print(f"wrote {out}")
    return 1 if failed else 0


def cli() -> int:
    """The command: main() with SIGTERM / SIGHUP handled like Ctrl-C (also the vkgrl_newton.gpu_check forwarder's)."""
    return run_cli(main, "gpu_check", "the checks finished before the stop are in its JSON report (complete: false)")


if __name__ == "__main__":
    raise SystemExit(cli())
