"""Environment-interaction force on the gripper group: per-world contact-force reduction, EMA, episode stats.

The "gripper group" of a world is a set of shapes (the held part and the finger pads), marked by
shape_group[s] = 1; every other shape (socket, table, other parts, global shapes) has 0. The
interaction force of world w is the net contact force exerted ON the group BY non-group shapes,
world frame [N]:

    F[w] = sum over live contacts c with exactly one group shape, in world w, of
           (+f_c if shape0 of c is the group shape, -f_c if shape1 is)

Contacts between two group shapes (pad-peg grip forces) and between two non-group shapes are left
out. The world of a contact is the world of its group shape.

Per-contact force f_c: the linear (top) part of `SolverBase.Observables.contact_f`, one
spatial_vector per row of the `newton.Contacts` buffer that the observables were allocated with
(rigid rows 0..rigid_contact_max-1, then soft rows, which are not read here). It is the force ON
the body of rigid_contact_shape0[c] BY the body of rigid_contact_shape1[c], world frame [N]
(Contacts.force docs; SolverMuJoCo negates mujoco_warp's force-on-geom2, and
SensorContact.accumulate_contact_forces_kernel adds +f to shape0 and -f to shape1). Rows at or
beyond rigid_contact_count[0] are stale or zero and are skipped. The torque (bottom) part is
ignored. Per step, with SolverMuJoCo (use_mujoco_contacts=False) and a newton.CollisionPipeline:

    contacts = pipeline.contacts()
    obs = solver.observables({SolverBase.ObservableKind.CONTACT_F}, contacts=contacts)
    pipeline.collide(state_0, contacts)
    solver.step(state_0, state_1, control, contacts, dt, observables=obs)
    contact_force_reduce(contact_count=contacts.rigid_contact_count, contact_shape0=contacts.rigid_contact_shape0,
                         contact_shape1=contacts.rigid_contact_shape1, contact_f=obs.contact_f, ...)

Then, once per step at which the statistics are sampled, `contact_force_update`:

    F_s   <- alpha F + (1 - alpha) F_s       EMA, alpha = 0.25 (Forge ft_smoothing_factor); F_s feeds
                                             the Forge force observation and contact penalty
    sum   += |F|,  count += 1                thesis eq. 6.1: mean contact force magnitude = sum / count
    peak  <- max(peak, |F|)

The statistics use the RAW force F, not F_s. `contact_force_reset` zeroes F_s and the statistics
of the worlds being reset (Forge resets F_s to 0 at episode start).
"""

from __future__ import annotations

import warp as wp

__all__ = [
    "FORGE_FT_SMOOTHING",
    "contact_force_reduce_kernel",
    "contact_force_update_kernel",
    "contact_force_reset_kernel",
    "contact_force_reduce",
    "contact_force_update",
    "contact_force_reset",
    "contact_forces_torch",
]

FORGE_FT_SMOOTHING = 0.25
"""EMA weight of the newest force sample (Forge `ft_smoothing_factor`)."""


@wp.kernel
def contact_force_reduce_kernel(
    contact_count: wp.array(dtype=wp.int32),  # (1,) live rigid contacts (Contacts.rigid_contact_count)
    contact_shape0: wp.array(dtype=wp.int32),  # (C,) shape0 per contact row, -1 = invalid
    contact_shape1: wp.array(dtype=wp.int32),  # (C,) shape1 per contact row, -1 = invalid
    # (>= C,) Observables.contact_f: wrench on shape0's body by shape1's, world frame; top = force [N]
    contact_f: wp.array(dtype=wp.spatial_vector),
    shape_group: wp.array(dtype=wp.int32),  # (S,) 1 = gripper group, 0 = other
    shape_world: wp.array(dtype=wp.int32),  # (S,) world of each shape (Model.shape_world), -1 = global
    # (E,) out, accumulated (zero it first): force on the group by non-group shapes, world frame [N]
    interaction_force_w: wp.array(dtype=wp.vec3),
):
    c = wp.tid()
    if c >= contact_count[0]:
        return
    s0 = contact_shape0[c]
    s1 = contact_shape1[c]
    if s0 < 0 or s1 < 0:
        return
    g0 = shape_group[s0] != 0
    g1 = shape_group[s1] != 0
    if g0 == g1:
        return  # group-group (grip) or other-other contact
    f = wp.spatial_top(contact_f[c])
    s = s0
    if g1:
        s = s1
        f = -f  # contact_f is the force on shape0; the group is shape1
    w = shape_world[s]
    if w < 0:
        w = 0  # single-world model built without worlds: all shapes are global
    if w >= interaction_force_w.shape[0]:
        return
    wp.atomic_add(interaction_force_w, w, f)


@wp.kernel
def contact_force_update_kernel(
    interaction_force_w: wp.array(dtype=wp.vec3),  # (E,) raw interaction force F of this step, world frame [N]
    alpha: wp.float32,  # EMA weight of the new sample
    force_smoothed_w: wp.array(dtype=wp.vec3),  # (E,) in/out: EMA F_s, world frame [N]
    force_norm_sum: wp.array(dtype=wp.float32),  # (E,) in/out: episode sum of |F| [N]
    force_sample_count: wp.array(dtype=wp.int32),  # (E,) in/out: episode number of samples
    force_peak: wp.array(dtype=wp.float32),  # (E,) in/out: episode max of |F| [N]
):
    e = wp.tid()
    f = interaction_force_w[e]
    force_smoothed_w[e] = alpha * f + (1.0 - alpha) * force_smoothed_w[e]
    mag = wp.length(f)
    force_norm_sum[e] = force_norm_sum[e] + mag
    force_sample_count[e] = force_sample_count[e] + 1
    force_peak[e] = wp.max(force_peak[e], mag)


@wp.kernel
def contact_force_reset_kernel(
    reset_mask: wp.array(dtype=wp.bool),  # (E,) True = zero this world's smoothed force and statistics
    force_smoothed_w: wp.array(dtype=wp.vec3),  # (E,) in/out
    force_norm_sum: wp.array(dtype=wp.float32),  # (E,) in/out
    force_sample_count: wp.array(dtype=wp.int32),  # (E,) in/out
    force_peak: wp.array(dtype=wp.float32),  # (E,) in/out
):
    e = wp.tid()
    if reset_mask[e]:
        force_smoothed_w[e] = wp.vec3(0.0)
        force_norm_sum[e] = 0.0
        force_sample_count[e] = 0
        force_peak[e] = 0.0


def _check_len(num: int, what: str, **arrays: wp.array) -> None:
    for name, arr in arrays.items():
        if arr.shape[0] != num:
            raise ValueError(f"{name} has {arr.shape[0]} entries, expected {num} ({what})")


def contact_force_reduce(
    *,
    contact_count: wp.array,
    contact_shape0: wp.array,
    contact_shape1: wp.array,
    contact_f: wp.array,
    shape_group: wp.array,
    shape_world: wp.array,
    interaction_force_w: wp.array,
) -> None:
    """Zero `interaction_force_w` and accumulate the group's interaction force into it (one thread per contact row).

    Shapes: contact_count (1,) int32; contact_shape0, contact_shape1 (C,) int32 (C = rigid_contact_max);
    contact_f (>= C,) spatial_vector (Observables.contact_f: force on shape0 by shape1, world frame, in the
    top three entries); shape_group, shape_world (S,) int32; interaction_force_w (E,) vec3, out.
    The launch covers all C rows (no host read of the count, so it can be graph-captured).
    Raises ValueError on mismatched lengths.
    """
    num_rows = contact_shape0.shape[0]
    _check_len(num_rows, "one per contact row, like contact_shape0", contact_shape1=contact_shape1)
    if contact_f.shape[0] < num_rows:
        raise ValueError(f"contact_f has {contact_f.shape[0]} rows, fewer than the {num_rows} contact rows")
    if contact_count.shape[0] != 1:
        raise ValueError(f"contact_count must have one entry, has {contact_count.shape[0]}")
    _check_len(shape_group.shape[0], "one per shape, like shape_group", shape_world=shape_world)
    interaction_force_w.zero_()
    if num_rows == 0:
        return
    wp.launch(
        contact_force_reduce_kernel,
        dim=num_rows,
        inputs=[contact_count, contact_shape0, contact_shape1, contact_f, shape_group, shape_world],
        outputs=[interaction_force_w],
        device=interaction_force_w.device,
    )


def contact_force_update(
    *,
    interaction_force_w: wp.array,
    force_smoothed_w: wp.array,
    force_norm_sum: wp.array,
    force_sample_count: wp.array,
    force_peak: wp.array,
    alpha: float = FORGE_FT_SMOOTHING,
) -> None:
    """EMA of the interaction force and episode statistics of its raw magnitude, one thread per world.

    Shapes: interaction_force_w (E,) vec3 (raw F from `contact_force_reduce`); in/out force_smoothed_w (E,) vec3
    (F_s <- alpha F + (1 - alpha) F_s), force_norm_sum (E,) float32 (+= |F|), force_sample_count (E,) int32
    (+= 1), force_peak (E,) float32 (max with |F|). Mean contact force (eq. 6.1) = force_norm_sum /
    force_sample_count. Raises ValueError on mismatched lengths or alpha outside [0, 1].
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must lie in [0, 1], got {alpha}")
    num_worlds = interaction_force_w.shape[0]
    _check_len(num_worlds, "one per world, like interaction_force_w", force_smoothed_w=force_smoothed_w,
               force_norm_sum=force_norm_sum, force_sample_count=force_sample_count, force_peak=force_peak)
    wp.launch(
        contact_force_update_kernel,
        dim=num_worlds,
        inputs=[interaction_force_w, float(alpha)],
        outputs=[force_smoothed_w, force_norm_sum, force_sample_count, force_peak],
        device=interaction_force_w.device,
    )


def contact_force_reset(
    *,
    reset_mask: wp.array,
    force_smoothed_w: wp.array,
    force_norm_sum: wp.array,
    force_sample_count: wp.array,
    force_peak: wp.array,
) -> None:
    """Zero the smoothed force and the episode statistics of the worlds with reset_mask[e] True.

    Shapes: reset_mask (E,) bool (the dtype of SolverMuJoCo.reset's world_mask; wp.from_torch of a torch.bool
    tensor gives it); force_smoothed_w (E,) vec3, force_norm_sum (E,) float32, force_sample_count (E,) int32,
    force_peak (E,) float32, all in/out. Raises ValueError on mismatched lengths.
    """
    num_worlds = reset_mask.shape[0]
    _check_len(num_worlds, "one per world, like reset_mask", force_smoothed_w=force_smoothed_w,
               force_norm_sum=force_norm_sum, force_sample_count=force_sample_count, force_peak=force_peak)
    wp.launch(
        contact_force_reset_kernel,
        dim=num_worlds,
        inputs=[reset_mask],
        outputs=[force_smoothed_w, force_norm_sum, force_sample_count, force_peak],
        device=reset_mask.device,
    )


def contact_forces_torch(
    contact_count,
    contact_shape0,
    contact_shape1,
    contact_f,
    shape_group,
    shape_world,
    force_smoothed_w,
    force_norm_sum,
    force_sample_count,
    force_peak,
    alpha: float = FORGE_FT_SMOOTHING,
):
    """torch version of `contact_force_reduce` followed by `contact_force_update` (same semantics).

    Tensors: contact_count (1,) int; contact_shape0/1 (C,) int; contact_f (>= C, 6) float, force in [:, :3];
    shape_group, shape_world (S,) int; in/out (updated in place) force_smoothed_w (E, 3), force_norm_sum (E,),
    force_sample_count (E,) int, force_peak (E,). Returns the raw interaction force (E, 3). No host sync:
    invalid rows are masked, not removed.
    """
    import torch  # kept local: the kernels themselves need no torch

    num_rows = contact_shape0.shape[0]
    num_worlds = force_smoothed_w.shape[0]
    device = contact_shape0.device
    s0 = contact_shape0.long()
    s1 = contact_shape1.long()
    live = (torch.arange(num_rows, device=device) < contact_count.long()) & (s0 >= 0) & (s1 >= 0)
    s0 = s0.clamp_min(0)
    s1 = s1.clamp_min(0)
    g0 = shape_group[s0] != 0
    g1 = shape_group[s1] != 0
    group_shape = torch.where(g0, s0, s1)
    world = shape_world[group_shape].long().clamp_min(0)
    keep = live & (g0 != g1) & (world < num_worlds)
    sign = torch.where(g0, 1.0, -1.0).to(contact_f.dtype) * keep.to(contact_f.dtype)
    force = torch.zeros(num_worlds, 3, dtype=contact_f.dtype, device=device)
    force.index_add_(0, world.clamp_max(num_worlds - 1), contact_f[:num_rows, :3] * sign[:, None])
    force = force.to(force_smoothed_w.dtype)
    force_smoothed_w.mul_(1.0 - alpha).add_(force, alpha=alpha)
    mag = torch.linalg.vector_norm(force, dim=1)
    force_norm_sum.add_(mag)
    force_sample_count.add_(1)
    torch.maximum(force_peak, mag, out=force_peak)
    return force
