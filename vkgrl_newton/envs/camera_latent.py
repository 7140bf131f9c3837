"""The visual latent of the policy observation (thesis eq. 5.6): task camera -> frozen VAE encoder mean.

`CameraLatent(env, encoder)` is the callable that `AssemblyEnv.attach_vision` takes: it renders
every world's hand camera (`sim.camera.TaskCamera`, the camera the encoder's images were taken
with, `FrozenEncoder.camera`; Table 5.6's at the encoder's resolution for an older VAE) and returns mu of the frozen encoder, (E, d_z) on the env's device. Images stay on the
sim device (`TaskCamera.render_torch`: no host round trip on CUDA) and are encoded in chunks of
`batch` worlds so that 256 x 256 images of thousands of worlds do not need one huge activation.
With a probe (--vision-probe-obs), the probe's estimate of the held part over the hole follows the latent.
"""

from __future__ import annotations

import dataclasses

import torch

from ..vision.vae import FrozenEncoder

__all__ = ["CameraLatent", "LatentLateral", "LATERAL_DIM"]


class CameraLatent:
    def __init__(self, env, encoder: FrozenEncoder, batch: int = 256, probe=None) -> None:
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
        # --vision-probe-obs: the near-hole probe (vision.probe.ProbeMLP) read off the latent and turned into the
        # world by the camera's pose, appended: (E, d_z + 2)
        self.probe = None if probe is None else probe.to(env.tdev)

    @torch.no_grad()
    def __call__(self, env) -> torch.Tensor:
        hand = env.hand_pose()  # (read once: the render and the probe's camera pose share it)
        images = self.camera.render_torch(env.state_0, *hand)  # uint8 (E, R, R, 3) view
        z = torch.cat([self.encoder(images[i:i + self.batch]) for i in range(0, images.shape[0], self.batch)])
        if self.probe is None:
            return z  # on env.tdev, where the encoder is; timings: python -m vkgrl_newton.tools.bench_vision
        return torch.cat([z, self.lateral(hand, z)], -1)

    def lateral(self, hand, z: torch.Tensor) -> torch.Tensor:
        """(E, 2) the probe's estimate of the held part's origin minus the fixed tip, world x, y (m), from latent z
        and the hand's world pose `hand` (pos, quat xyzw) this image was taken from."""
        from ..vision.probe import lateral_from_image

        q = self.camera.optical_poses_w(*hand)[:, 3:]
        return lateral_from_image(self.probe(z), q).to(z.dtype)


LATERAL_DIM = 2  # the probe's estimate in the policy's input: world x, y


class LatentLateral:
    """The held part's lateral error read from the camera: (E, 2) float64 m, world x, y, of the held part's origin
    minus the fixed tip, as a controller may steer by (tools/ceiling.py `oracle_latent`, `centre_latent`): exactly
    what --vision-probe-obs appends to the policy's input (`CameraLatent` with the probe). The controllers read it
    only once blocked near the hole, where the probe was fitted; elsewhere it means nothing.

    It also keeps score, for the record and never for the controller: the squared error of each estimate against
    the privileged truth on the frames the probe was fitted for (`vision.probe.near_hole_mask`), `rmse_mm()`.
    """

    def __init__(self, env, encoder: FrozenEncoder, probe, batch: int = 256) -> None:
        self.latent = CameraLatent(env, encoder, batch, probe)
        self.sq = torch.zeros(2, dtype=torch.float64, device=env.tdev)  # sum of squared errors, x, y (m^2)
        self.count = torch.zeros((), dtype=torch.float64, device=env.tdev)  # near-hole frames scored

    @torch.no_grad()
    def __call__(self, env) -> torch.Tensor:
        estimate = self.latent(env)[:, -LATERAL_DIM:].to(torch.float64)
        self.score(env, estimate)
        return estimate

    def score(self, env, estimate: torch.Tensor) -> None:
        from ..vision.probe import NEAR_HOLE_HEIGHT, NEAR_HOLE_XY

        truth = (env.held_pose()[0] - env.fixed_tip_w).to(torch.float64)  # the score's only use of it
        near = (torch.linalg.vector_norm(truth[:, :2], dim=-1) < NEAR_HOLE_XY) & (truth[:, 2] < NEAR_HOLE_HEIGHT)
        self.sq += (((estimate - truth[:, :2]) ** 2) * near.unsqueeze(-1)).sum(0)
        self.count += near.sum()

    def reset_score(self) -> None:
        self.sq.zero_()
        self.count.zero_()

    def rmse_mm(self) -> dict:
        """{"x", "y": RMSE in mm over the near-hole frames scored (None before any), "frames": their count}."""
        n = float(self.count)
        rmse = (self.sq / max(n, 1.0)).sqrt().tolist()
        return {"x": 1e3 * rmse[0] if n else None, "y": 1e3 * rmse[1] if n else None, "frames": int(n)}


