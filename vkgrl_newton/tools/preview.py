"""Render the task camera (thesis Table 5.6) of a few worlds into one PNG.

    python -m vkgrl_newton.tools.preview --task PegInsert --out peg_camera.png
    python -m vkgrl_newton.tools.preview --task GearMesh --camera contact --out gear_contact.png

The worlds are reset (Table 5.2 randomization) and the scripted demonstrator runs `--steps`
control steps (default 18: the peg is above the hole, the approach under way), then each world's
hand camera (`--camera`: Table 5.6's, or the quick preset's contact camera) renders one
`--resolution` square image (default 256); the images are tiled left to right, world 0 first.
An existing output file is never overwritten.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import sys
from pathlib import Path

import numpy as np

from ..cli_types import add_device_option
from .._io import atomic_write
from ..runtime import parse_cli
from ..sim.camera import CAMERA_SETS, TaskCamera
from ..sim.scene import GEOMETRIES, SimConfig, geometry_error
from ..tasks import TASKS
from ..envs.assembly_env import AssemblyEnv, EnvConfig
from ..envs.scripted import ScriptedInserter


def render_preview(task: str, num_worlds: int, steps: int, seed: int = 0, device: str | None = None,
                   geometry: str = "primitives", camera: str = "table5.6", resolution: int = 256) -> np.ndarray:
    """uint8 (H, num_worlds * W, 3): the task camera of each world after `steps` scripted steps."""
    env = AssemblyEnv(EnvConfig(task=task, family="factory", action_dim=6, num_envs=num_worlds, device=device,
                                seed=seed, sim=SimConfig(geometry=geometry)))
    env.reset()
    policy = ScriptedInserter(seed=seed)
    policy.reset(env)
    for _ in range(steps):
        env.step_pose(*policy.act(env))
    if camera not in CAMERA_SETS:
        raise ValueError(f"render_preview: camera={camera!r}; allowed: {sorted(CAMERA_SETS)}")
    spec = dataclasses.replace(CAMERA_SETS[camera][task], width=resolution, height=resolution)
    images = TaskCamera(env.model, spec, num_worlds).render(env.state_0, *env.hand_pose())
    return np.concatenate(list(images), axis=1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default="PegInsert", choices=sorted(TASKS))
    ap.add_argument("--out", type=Path, required=True, help="PNG file to write (never overwritten)")
    ap.add_argument("--num-worlds", type=int, default=4)
    ap.add_argument("--steps", type=int, default=18, help="scripted control steps before rendering")
    ap.add_argument("--seed", type=int, default=0)
    add_device_option(ap)
    ap.add_argument("--geometry", default="primitives", choices=GEOMETRIES, help="GearMesh/NutThread part geometry")
    ap.add_argument("--camera", default="table5.6", choices=sorted(CAMERA_SETS),
                    help="table5.6 (the thesis's cameras) or contact (the quick vision preset's)")
    ap.add_argument("--resolution", type=int, default=256, help="square image side in pixels (>= 8)")
    args = parse_cli(ap, argv, device=True)
    if args.num_worlds < 1:
        ap.error("--num-worlds must be >= 1")
    if args.steps < 0:
        ap.error("--steps must be >= 0")
    if args.resolution < 8:
        ap.error("--resolution must be >= 8")
    if geometry_error(args.task, args.geometry):
        ap.error(f"--{geometry_error(args.task, args.geometry)}")
    if args.out.exists():
        ap.error(f"--out {args.out} exists; choose another path (files are never overwritten)")
    tiled = render_preview(args.task, args.num_worlds, args.steps, args.seed, args.device, args.geometry, args.camera,
                           args.resolution)

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    plt.imsave(buf, tiled, format="png")
    atomic_write(args.out, overwrite=False, write=lambda f: f.write(buf.getvalue()), suffix=".png")
    print(f"wrote {args.out} ({tiled.shape[1]} x {tiled.shape[0]} px, {args.num_worlds} worlds)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
