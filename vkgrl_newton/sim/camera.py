"""The task camera (thesis Table 5.6): one RGB image per world with Newton's `SensorCamera`.

Placement. Table 5.6 gives, per task, a position and roll/pitch/yaw "relative to the task
environment"; the thesis's Figure 5.3 shows views of the gripper and the parts from close by,
which is a camera carried by the hand. We read the table that way: the camera is rigidly mounted
on the hand, at `pos_hand` in the hand frame, rotated by XYZ Euler angles (roll, pitch, yaw) from
the hand frame, with Isaac Lab's default ("ros") optical convention: the camera looks along its
+z, image up is its -y. Newton's camera looks along its local -Z with +Y up, so the optical frame
is turned by pi about x before it is handed to the sensor. Lens: Isaac Lab's pinhole default
(focal length 24 mm, horizontal aperture 20.955 mm, about 47 degrees horizontal field of view),
since the thesis states none. Resolution: 256 x 256 (Table 5.6 text).

Rendering costs about 18-24 ms per world at 256 x 256 on a CPU core (measured for this project with
newton 1.8.0: 16 worlds, RGB and depth with shadows), so render at the control rate, only when a
method needs images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

import newton
from newton.sensors import SensorCamera

from ..rotations import quat_from_euler_xyz, quat_mul, quat_rotate

__all__ = ["CameraSpec", "TASK_CAMERAS", "CONTACT_CAMERAS", "CAMERA_SETS", "TaskCamera"]


@dataclass(frozen=True)
class CameraSpec:
    pos_hand: tuple[float, float, float]  # m, in the hand frame
    rpy_deg: tuple[float, float, float]  # XYZ Euler angles from the hand frame to the optical frame
    width: int = 256
    height: int = 256
    focal_length: float = 24.0  # mm (Isaac Lab's PinholeCameraCfg default)
    horizontal_aperture: float = 20.955  # mm
    # rays per pixel; > 1 is Newton's multisample anti-aliasing (the pixel is its coverage-weighted
    # mean colour: a sub-pixel move of an edge changes it, which one centred ray per pixel cannot)
    samples_per_pixel: int = 1

    def __post_init__(self):
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 8:
                raise ValueError(f"CameraSpec.{name} must be an integer >= 8, got {v!r}")
        if not (isinstance(self.samples_per_pixel, int) and 1 <= self.samples_per_pixel <= 64):
            raise ValueError(f"CameraSpec.samples_per_pixel={self.samples_per_pixel!r}; allowed: an integer in [1, 64]")
        for name in ("focal_length", "horizontal_aperture"):
            if not getattr(self, name) > 0:
                raise ValueError(f"CameraSpec.{name}={getattr(self, name)!r}; allowed: > 0 (mm)")

    @property
    def horizontal_fov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(0.5 * self.horizontal_aperture / self.focal_length))


# Apart from tasks.py (plain data at the bottom, importing nothing of the package): a CameraSpec is this module's
# type, beside the renderer that reads it (newton, warp, torch), and the mounts are placed against this project's
# hand hull (below); a vision preset picks one of CAMERA_SETS, Table 5.6's or the contact cameras.
#
# Thesis Table 5.6. PegInsert's "roll -20" is applied as a 20 degree tilt of the optical axis
# back toward the gripper axis (about the hand y axis): rendered literally, about the optical x
# axis, a camera 8 cm beside the hand looks past the fingers at the bare table (checked), and the
# thesis's images show the gripper and the parts. GearMesh and NutThread: "(0, 0, 0.05), yaw 90"
# puts the camera inside this project's hand hull (a box down to 0.06 m along the hand z; it
# renders black), so it sits 0.065 m along the hand z instead, just under the hand between the
# fingers, looking down the gripper axis: the held gear's teeth and the fixed gears around its
# hub, or the bolt through the nut's bore (docs/images/gear_mesh_camera.png, nut_thread_camera.png).
TASK_CAMERAS = {
    "PegInsert": CameraSpec(pos_hand=(0.08, 0.0, 0.0), rpy_deg=(0.0, -20.0, 0.0)),
    "GearMesh": CameraSpec(pos_hand=(0.0, 0.0, 0.065), rpy_deg=(0.0, 0.0, 90.0)),
    "NutThread": CameraSpec(pos_hand=(0.0, 0.0, 0.065), rpy_deg=(0.0, 0.0, 90.0)),
}

# The cameras aimed at where the parts meet (the quick vision preset's; docs/log/benchmarks.md, issue
# 19). PegInsert: Table 5.6's mount, its optical axis tilted 29 degrees instead of 20 toward the
# gripper axis, through the peg's tip (0.146 m along the hand z, 0.08 m beside the mount:
# atan(0.08 / 0.146) = 28.7 degrees; at 20 the tip sits ~27 mm off the image centre), and a 48 mm
# lens (24 degrees of view instead of 47): ~1 mm per pixel at 64 px where the parts meet, both
# parts in view over the near-hole region (+-1 cm). Measured on the same states: the privileged
# pixel baseline locates the hole to 0.31 / 0.16 mm (x / y) against 0.64 / 0.20 with Table 5.6's
# reading, the VAE latent to 0.51 / 0.18 against 0.85 / 0.28. GearMesh: Table 5.6's camera looks
# down the gripper axis onto the held gear, which hides the shaft it must go onto (even the
# privileged pixel baseline did no better than the mean there). Its contact camera sits 8 cm beside
# the hand along the hand y (the fingers' closing axis, perpendicular to the gear base's row of
# shafts when the gear is aligned to mesh), 3 cm above the held gear's bottom, and looks 58 degrees
# off the gripper axis, under the gear's rim, through the lower shaft (0.16 m along the hand z):
# the shaft, the flanking gears' teeth and the held gear's lower teeth are in view, 48 mm lens.
# Measured on unseen episodes: the shaft's pixels locate it to 0.2 mm, the quick VAE's latent to
# 1.3 / 0.85 mm (x / y), against a spread of 3.2 / 4.8.
# NutThread: Table 5.6's camera already looks down the nut's bore at the bolt.
CONTACT_CAMERAS = {
    "PegInsert": CameraSpec(pos_hand=(0.08, 0.0, 0.0), rpy_deg=(0.0, -29.0, 0.0), focal_length=48.0),
    "GearMesh": CameraSpec(pos_hand=(0.0, 0.08, 0.11), rpy_deg=(58.0, 0.0, 0.0), focal_length=48.0),
    "NutThread": TASK_CAMERAS["NutThread"],
}
CAMERA_SETS = {"table5.6": TASK_CAMERAS, "contact": CONTACT_CAMERAS}

# optical frame (+z forward, -y up) -> Newton camera frame (-Z forward, +Y up): pi about x
_OPTICAL_TO_NEWTON = (1.0, 0.0, 0.0, 0.0)  # xyzw


class TaskCamera:
    """Renders the hand-mounted task camera of every world (or a subset) into uint8 RGB."""

    def __init__(self, model: newton.Model, spec: CameraSpec, num_worlds: int):
        self.model, self.spec, self.num_worlds = model, spec, num_worlds
        self.device = model.device
        config = None
        if spec.samples_per_pixel > 1:
            config = SensorCamera.RenderConfig(anti_aliasing=SensorCamera.AntiAliasing.MSAA)
        self.sensor = SensorCamera(model, default_render_config=config)
        self.sensor.create_default_light(enable_shadows=True)
        self.rays = SensorCamera.compute_camera_rays_pinhole(
            spec.width, spec.height, focal_length=spec.focal_length,
            horizontal_aperture=spec.horizontal_aperture,
            vertical_aperture=spec.horizontal_aperture * spec.height / spec.width,
            sample_count=spec.samples_per_pixel, device=self.device)
        self.color = self.sensor.allocate_image_color(num_worlds, spec.width, spec.height)
        self._labels = None  # shape-index and depth images, allocated on the first render_labelled
        roll, pitch, yaw = (math.radians(a) for a in spec.rpy_deg)
        q_opt = quat_from_euler_xyz(torch.tensor([roll]), torch.tensor([pitch]), torch.tensor([yaw]))
        self._q_mount = quat_mul(q_opt, torch.tensor([_OPTICAL_TO_NEWTON]))[0]  # hand -> Newton camera
        self._p_mount = torch.tensor(spec.pos_hand, dtype=torch.float32)

    def camera_poses_w(self, hand_pos_w: torch.Tensor, hand_quat_w: torch.Tensor) -> torch.Tensor:
        """(E, 7) camera transforms (p, q xyzw) in the world for hand poses (E, 3), (E, 4)."""
        n = hand_pos_w.shape[0]
        p_mount = self._p_mount.to(hand_pos_w).expand(n, 3)
        q_mount = self._q_mount.to(hand_quat_w).expand(n, 4)
        pos = hand_pos_w + quat_rotate(hand_quat_w, p_mount)
        return torch.cat((pos, quat_mul(hand_quat_w, q_mount)), dim=-1)

    def optical_poses_w(self, hand_pos_w: torch.Tensor, hand_quat_w: torch.Tensor) -> torch.Tensor:
        """(E, 7) the image's frame in the world: the camera position and the optical frame's
        orientation (xyzw; +x image right, +y image down, +z forward along the optical axis)."""
        pose = self.camera_poses_w(hand_pos_w, hand_quat_w)
        q_back = torch.tensor([_OPTICAL_TO_NEWTON], dtype=pose.dtype, device=pose.device).expand(pose.shape[0], 4)
        return torch.cat((pose[:, :3], quat_mul(pose[:, 3:], q_back)), dim=-1)  # pi about x is its own inverse

    def _render(self, state: newton.State, hand_pos_w: torch.Tensor, hand_quat_w: torch.Tensor, **images) -> None:
        self.model.bvh_refit_shapes(state)  # bodies moved since the last render
        poses = self.camera_poses_w(hand_pos_w, hand_quat_w).detach().float().contiguous()
        tfs = wp.from_torch(poses, dtype=wp.transformf)  # (p, q xyzw) is Warp's transform layout
        self.sensor.update(state, tfs, self.rays, color_image=self.color, **images)

    def render_labelled(self, state: newton.State, hand_pos_w: torch.Tensor, hand_quat_w: torch.Tensor
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """On the host: uint8 RGB (E, H, W, 3), the shape index seen at each pixel's centre
        (E, H, W) uint32 (global model shape index), and the ray distance to it (E, H, W) float32, m.
        For privileged pixel measurements (the vision probe's baseline), not for the policy."""
        if self._labels is None:
            w, h = self.spec.width, self.spec.height
            self._labels = {"shape_index_image": self.sensor.allocate_image_shape_index(self.num_worlds, w, h),
                            "depth_image": self.sensor.allocate_image_depth(self.num_worlds, w, h)}
        self._render(state, hand_pos_w, hand_quat_w, **self._labels)
        h, w = self.spec.height, self.spec.width
        rgb = self.color.numpy().view(np.uint8).reshape(self.num_worlds, h, w, 4)[..., :3].copy()
        return rgb, self._labels["shape_index_image"].numpy(), self._labels["depth_image"].numpy()

    def ray_directions_optical(self) -> np.ndarray:
        """(H, W, 3) float64 unit direction of each pixel's (first) ray in the optical frame."""
        d = self.rays.numpy()[:, :, 0, 1].astype(np.float64)  # Newton camera frame: -Z forward, +Y up
        d = d * np.array([1.0, -1.0, -1.0])
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def render(self, state: newton.State, hand_pos_w: torch.Tensor, hand_quat_w: torch.Tensor) -> np.ndarray:
        """uint8 (E, H, W, 3) images on the host (a copy); world i is seen by camera i."""
        self._render(state, hand_pos_w, hand_quat_w)
        h, w = self.spec.height, self.spec.width
        return self.color.numpy().view(np.uint8).reshape(self.num_worlds, h, w, 4)[..., :3].copy()

    def render_torch(self, state: newton.State, hand_pos_w: torch.Tensor, hand_quat_w: torch.Tensor) -> torch.Tensor:
        """uint8 (E, H, W, 3) images as a torch view of the sensor's buffer, on the sim device (no
        host round trip on CUDA). The next render overwrites it: consume or clone it first."""
        self._render(state, hand_pos_w, hand_quat_w)
        h, w = self.spec.height, self.spec.width
        return wp.to_torch(self.color).view(torch.uint8).reshape(self.num_worlds, h, w, 4)[..., :3]
