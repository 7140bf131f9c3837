"""The visual latent of the policy observation (thesis eq. 5.6): task camera -> frozen VAE encoder mean.

`CameraLatent(env, encoder)` is the callable that `AssemblyEnv.attach_vision` takes: it renders
every world's hand camera (`sim.camera.TaskCamera`, the thesis's Table 5.6 pose, at the encoder's
resolution) and returns mu of the frozen encoder, (E, d_z) on the env's device. Images stay on the
sim device (`TaskCamera.render_torch`: no host round trip on CUDA) and are encoded in chunks of
`batch` worlds so that 256 x 256 images of thousands of worlds do not need one huge activation.
"""

from __future__ import annotations

import dataclasses
import time

import torch

from .vae import FrozenEncoder

__all__ = ["CameraLatent"]


class CameraLatent:
    def __init__(self, env, encoder: FrozenEncoder, batch: int = 256) -> None:
        from ..sim.camera import TASK_CAMERAS, TaskCamera

        r = encoder.config.resolution
        self.spec = dataclasses.replace(TASK_CAMERAS[env.cfg.task], width=r, height=r)
        self.camera = TaskCamera(env.model, self.spec, env.num_envs)
        self.encoder = encoder.to(env.tdev)
        self.batch = int(batch)
        self.render_s = self.encode_s = 0.0  # accumulated wall time, for the throughput report
        self.calls = 0

    @torch.no_grad()
    def __call__(self, env) -> torch.Tensor:
        t0 = time.perf_counter()
        images = self.camera.render_torch(env.state_0, *env.hand_pose())  # uint8 (E, R, R, 3) view
        t1 = time.perf_counter()
        z = torch.cat([self.encoder(images[i:i + self.batch]) for i in range(0, images.shape[0], self.batch)])
        if z.device.type == "cuda":
            torch.cuda.synchronize(z.device)  # honest timings; one sync per control step
        self.render_s += t1 - t0
        self.encode_s += time.perf_counter() - t1
        self.calls += 1
        return z.to(env.tdev)
