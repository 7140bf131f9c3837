"""The visual latent of the policy observation (thesis eq. 5.6): task camera -> frozen VAE encoder mean.

`CameraLatent(env, encoder)` is the callable that `AssemblyEnv.attach_vision` takes: it renders
every world's hand camera (`sim.camera.TaskCamera`, the camera the encoder's images were taken
with, `FrozenEncoder.camera`; Table 5.6's at the encoder's resolution for an older VAE) and returns mu of the frozen encoder, (E, d_z) on the env's device. Images stay on the
sim device (`TaskCamera.render_torch`: no host round trip on CUDA) and are encoded in chunks of
`batch` worlds so that 256 x 256 images of thousands of worlds do not need one huge activation.
"""

from __future__ import annotations

import dataclasses

import torch

from ..vision.vae import FrozenEncoder

__all__ = ["CameraLatent"]


class CameraLatent:
    def __init__(self, env, encoder: FrozenEncoder, batch: int = 256) -> None:
        from ..sim.camera import TASK_CAMERAS, CameraSpec, TaskCamera

        r = encoder.config.resolution
        if encoder.camera is not None:  # the camera the encoder's images came from
            spec = encoder.camera
            self.spec = CameraSpec(**{**spec, "pos_hand": tuple(spec["pos_hand"]), "rpy_deg": tuple(spec["rpy_deg"])})
            if (self.spec.width, self.spec.height) != (r, r):
                raise ValueError(f"CameraLatent: the encoder's camera renders {self.spec.width} x {self.spec.height}, "
                                 f"its input is {r} x {r}")
        else:
            self.spec = dataclasses.replace(TASK_CAMERAS[env.cfg.task], width=r, height=r)
        self.camera = TaskCamera(env.model, self.spec, env.num_envs)
        self.encoder = encoder.to(env.tdev)
        self.batch = int(batch)

    @torch.no_grad()
    def __call__(self, env) -> torch.Tensor:
        images = self.camera.render_torch(env.state_0, *env.hand_pose())  # uint8 (E, R, R, 3) view
        z = torch.cat([self.encoder(images[i:i + self.batch]) for i in range(0, images.shape[0], self.batch)])
        return z  # on env.tdev, where the encoder is; timings: python -m vkgrl_newton.tools.bench_vision
