"""The image set a task's VAE learns from: task-camera images of the states a learning policy visits.

A policy in training sees the parts from far (random exploration, up to the 5 cm action bound)
and from close (near the hole, in contact), so the set mixes two kinds of episode round (all
worlds alike, on a fixed schedule with a `scripted_fraction` of scripted rounds):

- the scripted demonstrator (`envs.scripted`) with injected noise: its pose command is offset by
  a per-episode N(0, noise_offset) on x, y and a per-step N(0, noise_step) on x, y, z, so that
  the set holds near-misses, contacts on the rim and insertions, not only perfect ones;
- uniform random actions through the SAC action path (`env.step`), Factory's delta-pose mapping.

Every `frame_stride` control steps all worlds render their hand camera (`sim.camera.TaskCamera`,
Table 5.6 pose, `resolution` x `resolution`) and the privileged state is stored beside the image:
the fixed part's tip relative to the TCP, in the TCP frame (x, y, z, m), and the relative yaw
(fixed yaw - TCP yaw, wrapped to [-pi, pi)). The VAE never sees it; the linear probe checks that
the latent carries it. Beside it, for the near-hole probe (`vision.probe.near_hole_probe`): the
geometry of the frame (held part, fixed tip, the image's frame in the world: `GEOMETRY_COLUMNS`)
and privileged pixel measurements of both parts (of GearMesh's fixed part, its target shaft:
`FIXED_PIXEL_PARTS`) from a shape-index and a depth render of the same camera (`PIXEL_COLUMNS`:
what the image itself allows, the probe's baseline).

Episodes are numbered episode_round * num_envs + world, so the writer's train/validation split is
by (world, episode): frames of one trajectory never straddle the split.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm import tqdm

import numpy as np

from ..rotations import euler_xyz_from_quat, quat_conjugate, quat_rotate
from ..vision.dataset import IMAGESET_FORMAT, ImageSetWriter
from ..vision.probe import part_pixel_features

__all__ = ["CollectConfig", "collect_images", "default_image_dir", "relative_target_state", "collect_camera_spec",
           "part_shape_ids", "FIXED_PIXEL_PARTS"]


@dataclass(frozen=True)
class CollectConfig:
    task: str = "PegInsert"
    num_images: int = 4_096
    resolution: int = 64  # the quick preset's; the thesis's is 256 (Table 5.6)
    num_envs: int = 16
    family: str = "factory"
    action_dim: int = 4
    scripted_fraction: float = 0.5  # of episodes; the rest act uniformly at random
    frame_stride: int = 3  # control steps between two stored frames of a world
    episode_steps: int | None = None  # control steps per episode round (None: the whole episode)
    noise_offset: float = 0.003  # m, per-episode x, y offset of the demonstrator's command (std)
    noise_step: float = 0.001  # m, per-step command noise (std)
    val_fraction: float = 0.1
    seed: int = 0
    device: str = "cpu"
    # the camera: Table 5.6's pose and lens (sim.camera.TASK_CAMERAS) unless overridden here
    focal_length: float | None = None  # mm; None: Table 5.6's (Isaac Lab's 24 mm)
    camera_rpy_deg: tuple[float, float, float] | None = None  # None: Table 5.6's mount angles
    camera_pos_hand: tuple[float, float, float] | None = None  # m, in the hand frame; None: Table 5.6's
    samples_per_pixel: int = 1  # > 1: multisample anti-aliasing

    def __post_init__(self) -> None:
        for name in ("num_images", "resolution", "num_envs", "frame_stride", "episode_steps"):
            v = getattr(self, name)
            if name == "episode_steps" and v is None:
                continue
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise ValueError(f"CollectConfig.{name}={v!r}; allowed: an integer >= 1")
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(f"CollectConfig.val_fraction={self.val_fraction!r}; allowed: [0, 1)")
        if not 0.0 <= self.scripted_fraction <= 1.0:
            raise ValueError(f"CollectConfig.scripted_fraction={self.scripted_fraction!r}; allowed: [0, 1]")
        for name in ("noise_offset", "noise_step"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"CollectConfig.{name}={getattr(self, name)!r}; allowed: >= 0 (m)")
        collect_camera_spec(self)  # the camera fields are checked by CameraSpec
        if self.val_fraction > 0 and self.episodes() < 2:  # (ImageSetWriter's split would refuse it at the end)
            raise ValueError(f"CollectConfig.num_images={self.num_images} with num_envs={self.num_envs} covers "
                             f"{self.episodes()} episode; val_fraction={self.val_fraction} needs at least 2 (more "
                             "images or worlds, or val_fraction=0)")

    def episodes(self) -> int:
        """How many episodes the images come from, at least (collect_images: a round of num_envs worlds stores a
        frame of each every frame_stride control steps, the next round's worlds are new episodes)."""
        from ..tasks import get_task

        steps = min(self.episode_steps or get_task(self.task).episode_steps, get_task(self.task).episode_steps)
        per_round = self.num_envs * math.ceil(steps / self.frame_stride)
        return min(self.num_envs, self.num_images) + max(0, math.ceil((self.num_images - per_round) / per_round)) \
            * self.num_envs


def collect_camera_spec(cfg: CollectConfig):
    """The camera a collection renders with: its task's Table 5.6 camera at the config's resolution,
    lens and sampling."""
    from ..sim.camera import TASK_CAMERAS

    if cfg.task not in TASK_CAMERAS:
        raise ValueError(f"CollectConfig.task={cfg.task!r}; allowed: {sorted(TASK_CAMERAS)}")
    base = TASK_CAMERAS[cfg.task]
    return dataclasses.replace(base, width=cfg.resolution, height=cfg.resolution,
                               focal_length=base.focal_length if cfg.focal_length is None else float(cfg.focal_length),
                               samples_per_pixel=cfg.samples_per_pixel,
                               rpy_deg=base.rpy_deg if cfg.camera_rpy_deg is None
                               else tuple(float(a) for a in cfg.camera_rpy_deg),
                               pos_hand=base.pos_hand if cfg.camera_pos_hand is None
                               else tuple(float(a) for a in cfg.camera_pos_hand))


def relative_target_state(env) -> torch.Tensor:
    """(E, 4): the fixed tip relative to the TCP in the TCP frame (x, y, z, m) and the relative yaw."""
    tcp_p, tcp_q = env.tcp_pose()
    rel = quat_rotate(quat_conjugate(tcp_q), env.fixed_tip_w - tcp_p)
    _, _, tcp_yaw = euler_xyz_from_quat(tcp_q)
    d_yaw = env.fixed_yaw - tcp_yaw
    d_yaw = torch.atan2(torch.sin(d_yaw), torch.cos(d_yaw))
    return torch.cat((rel, d_yaw.unsqueeze(-1)), dim=-1)


def is_scripted_round(episode_round: int, scripted_fraction: float) -> bool:
    """A fixed schedule with exactly that fraction of scripted rounds over any prefix (+-1)."""
    return math.floor((episode_round + 1) * scripted_fraction) > math.floor(episode_round * scripted_fraction)


def collect_images(config: CollectConfig, out_dir, progress: bool = True, log=print, env=None) -> Path:
    """Roll out, render and write `config.num_images` images into the new directory `out_dir`.

    `env`: an AssemblyEnv to use instead of building one from the config (tests share theirs);
    its task, family, action dimension and world count then replace the config's.
    """
    from ..envs.assembly_env import AssemblyEnv, EnvConfig
    from ..envs.scripted import ScriptedInserter
    from ..sim.camera import TaskCamera

    if env is not None:
        config = dataclasses.replace(config, task=env.cfg.task, family=env.cfg.family,
                                     action_dim=env.cfg.action_dim, num_envs=env.num_envs)
    cfg = config
    out_dir = Path(out_dir)
    spec = collect_camera_spec(cfg)
    meta = {"source": "scripted demonstrator with command noise + uniform random actions",
            "family": cfg.family, "action_dim": cfg.action_dim, "num_envs": cfg.num_envs,
            "scripted_fraction": cfg.scripted_fraction, "frame_stride": cfg.frame_stride,
            "noise_offset": cfg.noise_offset, "noise_step": cfg.noise_step, "episode_steps": cfg.episode_steps,
            "camera": dataclasses.asdict(spec),
            "fixed_pixels": FIXED_PIXEL_PARTS.get(cfg.task, "the whole fixed part"),
            "state": "fixed tip relative to the TCP in the TCP frame (x, y, z, m), relative yaw (rad)"}
    # the writer first: a non-empty out_dir is refused before anything is built
    writer = ImageSetWriter(out_dir, cfg.num_images, cfg.resolution, cfg.task, cfg.val_fraction, cfg.seed, meta)
    if env is None:
        env = AssemblyEnv(EnvConfig(task=cfg.task, family=cfg.family, action_dim=cfg.action_dim,
                                    num_envs=cfg.num_envs, device=cfg.device, seed=cfg.seed))
    steps = min(cfg.episode_steps or env.max_episode_length, env.max_episode_length)
    camera = TaskCamera(env.model, spec, env.num_envs)
    dirs = camera.ray_directions_optical()
    fixed_ids, held_ids = part_shape_ids(env)
    demonstrator = ScriptedInserter(seed=cfg.seed)
    gen = torch.Generator(device=env.tdev).manual_seed(cfg.seed + 1)
    n, written, episode_round = env.num_envs, 0, 0
    t0 = time.perf_counter()
    # the bar in the with: closed on a stop too (else its last state is printed after the stop's one line)
    with writer, tqdm(total=cfg.num_images, unit="img", disable=not progress,
                      desc=f"images {cfg.task} {cfg.resolution}px") as bar:
        while written < cfg.num_images:
            env.reset()
            scripted = is_scripted_round(episode_round, cfg.scripted_fraction)
            if scripted:
                demonstrator.reset(env)
                offset = torch.zeros(n, 3, device=env.tdev)
                offset[:, :2] = cfg.noise_offset * torch.randn(n, 2, generator=gen, device=env.tdev)
            episode_ids = episode_round * n + torch.arange(n, device=env.tdev, dtype=torch.int32)
            for k in range(steps):
                if written >= cfg.num_images:
                    break  # no need to finish the episode
                if k % cfg.frame_stride == 0:
                    take = min(n, cfg.num_images - written)
                    hand_p, hand_q = env.hand_pose()
                    images, shape_index, depth = camera.render_labelled(env.state_0, hand_p, hand_q)
                    state = relative_target_state(env)
                    geometry = torch.cat((env.held_pose()[0], env.fixed_tip_w, camera.optical_poses_w(hand_p, hand_q)),
                                         dim=-1)
                    pixels = np.concatenate((part_pixel_features(shape_index, depth, dirs, fixed_ids),
                                             part_pixel_features(shape_index, depth, dirs, held_ids)), axis=1)
                    writer.add(images[:take], state[:take], episode_ids[:take], geometry[:take], pixels[:take])
                    written += take
                    bar.update(take)
                if scripted:
                    pos, quat = demonstrator.act(env)
                    noise = cfg.noise_step * torch.randn(n, 3, generator=gen, device=env.tdev)
                    env.step_pose(pos + offset + noise, quat)
                else:
                    env.step(2.0 * torch.rand(n, cfg.action_dim, generator=gen, device=env.tdev) - 1.0)
            episode_round += 1
    wall = time.perf_counter() - t0
    log(f"{cfg.num_images} images ({episode_round} episode rounds of {n} worlds) in {wall:.0f} s "
        f"({cfg.num_images / max(wall, 1e-9):.1f} images/s) -> {out_dir}")
    return out_dir


# The fixed part's shapes whose pixels the near-hole probe's pixel baseline measures, where that is
# not the whole fixed part: the label suffix of the one feature the held part must reach. GearMesh's
# fixed part is the base plate with the two flanking gears (many times the shaft's area, often cut
# by the image border), so its centroid says little about where the one shaft is.
FIXED_PIXEL_PARTS = {"GearMesh": "/gear_base/shaft"}


def part_shape_ids(env) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per world, the global shape indices of the fixed part (for GearMesh only its target shaft,
    `FIXED_PIXEL_PARTS`) and of the held part."""
    fixed = [np.asarray(row) for row in env.scene.socket_shapes.numpy()]
    suffix = FIXED_PIXEL_PARTS.get(env.cfg.task)
    if suffix is not None:
        per_world = len(env.scene.labels["shapes"])  # the template's shapes, replicated per world
        keep = [np.array([s for s in row if env.scene.labels["shapes"][s % per_world].endswith(suffix)])
                for row in fixed]
        if any(len(k) == 0 for k in keep):
            raise ValueError(f"{env.cfg.task}: no fixed-part shape is labelled *{suffix}; re-author the stage "
                             "(assets_usd/author.py)")
        fixed = keep
    shape_body = env.model.shape_body.numpy()
    held = [np.flatnonzero(shape_body == b) for b in env.scene.held_body.numpy()]
    return fixed, held


def collection_key(cfg: CollectConfig) -> str:
    """A short hash of everything that makes an image set what it is: every CollectConfig field
    but the device, the camera it renders with (resolved: the camera fields enter only through it,
    so Table 5.6's lens given explicitly or left at None is the same set), the image-set format and
    the demonstrator's version (its scripted rounds are part of the set)."""
    import hashlib
    import json

    from ..envs.scripted import DEMONSTRATOR_VERSION

    camera_fields = ("focal_length", "camera_rpy_deg", "camera_pos_hand", "samples_per_pixel")
    fields = {k: v for k, v in dataclasses.asdict(cfg).items() if k != "device" and k not in camera_fields}
    blob = {"config": fields, "camera": dataclasses.asdict(collect_camera_spec(cfg)), "format": IMAGESET_FORMAT,
            "demonstrator": DEMONSTRATOR_VERSION}
    if cfg.task in FIXED_PIXEL_PARTS:  # the pixel baseline's fixed shapes (only where not the whole part)
        blob["fixed_pixels"] = FIXED_PIXEL_PARTS[cfg.task]
    return hashlib.sha256(json.dumps(blob, sort_keys=True).encode()).hexdigest()[:10]


def default_image_dir(cache_dir, cfg: CollectConfig) -> Path:
    """Where run.py caches a task's image set: the readable settings in the name, then
    `collection_key` (any other setting that differs makes a new entry, never reuses an old one)."""
    from ..envs.scripted import DEMONSTRATOR_VERSION

    return Path(cache_dir) / cfg.task / (f"images_v{DEMONSTRATOR_VERSION}_r{cfg.resolution}_n{cfg.num_images}"
                                         f"_seed{cfg.seed}_{collection_key(cfg)}")

