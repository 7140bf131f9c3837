"""Peak contact and constraint-row counts per task: what SimConfig.nconmax / njmax must hold.

    python -m vkgrl_newton.tools.contact_peaks --tasks PegInsert GearMesh NutThread --num-worlds 8 --json out.json

Runs one episode per policy (the scripted demonstrator through `step_pose`; uniform random
actions through `step`; "press": delta actions driving the part down into the fixed part at 70 %
of full speed with a +-30 % wobble, the worst a learning policy does) on eager physics with generous buffers (4x the task defaults, so nothing
overflows while measuring) and reads, after every substep, Newton's rigid contact count (all
worlds share one buffer: the peak total / worlds is what `nconmax` per world must cover) and
MuJoCo-Warp's constraint rows per world (`nefc`: `njmax` is per world). The reset's grip settle
is included. The task defaults (sim/scene.py, TASK_CONTACT_LIMITS) are these peaks with headroom.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import torch
import warp as wp

from .._io import atomic_write_text
from ..cli_types import add_device_option, positive_int
from ..runtime import parse_cli
from ..sim.scene import TASK_CONTACT_LIMITS, SimConfig
from ..tasks import TASKS
from ..envs.assembly_env import AssemblyEnv, EnvConfig
from ..envs.scripted import ScriptedInserter


POLICIES = ("scripted", "random", "press")


def measure(task: str, num_worlds: int, policy: str, device=None, seed: int = 0) -> dict:
    nconmax, njmax = (4 * v for v in TASK_CONTACT_LIMITS[task])
    peaks = {"contacts_per_world": 0.0, "nefc_per_world": 0}
    cfg = EnvConfig(task=task, num_envs=num_worlds, action_dim=4, family="factory", device=device, seed=seed,
                    graph=False, sim=replace(SimConfig(), nconmax=nconmax, njmax=njmax))
    # the env resets in its constructor: wrap the solver's step before, through the scene's make_solver
    from ..sim import physics

    original = physics.make_solver

    def make_solver_recording(scene):
        solver, pipeline = original(scene)
        step = solver.step

        def recording_step(s0, s1, control, contacts, dt, **kw):
            step(s0, s1, control, contacts, dt, **kw)
            peaks["contacts_per_world"] = max(peaks["contacts_per_world"],
                                              int(contacts.rigid_contact_count.numpy()[0]) / num_worlds)
            nefc = getattr(getattr(solver, "mjw_data", None), "nefc", None)
            if nefc is not None:
                peaks["nefc_per_world"] = max(peaks["nefc_per_world"], int(nefc.numpy().max()))

        solver.step = recording_step
        return solver, pipeline

    physics.make_solver = make_solver_recording
    try:
        env = AssemblyEnv(cfg)
    finally:
        physics.make_solver = original
    g = torch.Generator(device=env.tdev).manual_seed(seed)
    inserter = ScriptedInserter(seed=seed)
    inserter.reset(env)
    successes = 0.0
    for _ in range(env.max_episode_length):
        if policy == "scripted":
            _, _, _, extras = env.step_pose(*inserter.act(env))
        elif policy == "random":
            a = 2 * torch.rand(num_worlds, 4, device=env.tdev, generator=g) - 1
            _, _, _, extras = env.step(a)
        else:  # press
            a = 0.3 * (2 * torch.rand(num_worlds, 4, device=env.tdev, generator=g) - 1)
            a[:, 2] = -0.7
            _, _, _, extras = env.step(a)
        if "episode" in extras:
            successes = extras["episode"]["success_rate"]
    return {"task": task, "policy": policy, "num_worlds": num_worlds, "success_rate": successes,
            "overflows": env.contact_overflows_total, **peaks}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tasks", nargs="+", default=sorted(TASKS), choices=sorted(TASKS))
    ap.add_argument("--policies", nargs="+", default=list(POLICIES), choices=POLICIES)
    ap.add_argument("--num-worlds", type=positive_int, default=8)
    add_device_option(ap)
    ap.add_argument("--json", type=Path, default=None, help="output file (never overwritten)")
    args = parse_cli(ap, argv, device=True)
    if args.json is not None and args.json.exists():
        ap.error(f"--json {args.json} exists; choose another path (results are never overwritten)")
    rows = []
    for task in args.tasks:
        for policy in args.policies:
            r = measure(task, args.num_worlds, policy, args.device)
            rows.append(r)
            print(f"{task:>10} {policy:>9}: peak {r['contacts_per_world']:.1f} contacts / world, "
                  f"{r['nefc_per_world']} constraint rows / world (defaults {TASK_CONTACT_LIMITS[task]}), "
                  f"success {r['success_rate']:.2f}", flush=True)
    if args.json is not None:
        atomic_write_text(args.json, json.dumps({"warp": wp.__version__, "results": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
