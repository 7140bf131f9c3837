"""The PegInsert scene and AssemblyEnv on a shared 4-world CPU env (conftest `peg_env`).

References are independent of the env's own helpers: Table 5.2 / Isaac Lab Factory reset ranges
(tasks.py values and Factory's `factory_env.py` `_full_reset`), socket box poses from
author.socket_pieces() composed in float64, quaternion algebra from scipy (tests/quat_ref.py), and the
TCP offset from the published Factory TCP (0.112071 m along the hand z).

Order matters (the env is shared and stateful): static checks first, then resets, steps, and the tests
that corrupt a world's state last. Tests needing a freshly reset env reset it when it has stepped.
"""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from quat_ref import q_mul as qmul
from quat_ref import q_to_matrix as qmat

TCP_Z = 0.112071  # Factory panda_fingertip_centered along the hand z
FIXED_NOMINAL = np.array([0.6, 0.0, 0.05])  # Factory fixed-asset default position
FIXED_TIP = 0.025  # hole depth: the fixed tip above the socket origin
PEG_BELOW_TCP = 0.032392  # Factory: peg height - finger pad length
IN_HAND_NOISE = 0.003  # Factory held_asset_pos_noise (0.003, 0, 0.003)
POS_BOUND = 0.05  # Factory pos_action_bounds
SUCCESS_XY, SUCCESS_Z = 0.0025, 0.001  # Factory `_get_curr_successes`: peg centred, seated to 0.04 of the hole depth
E = 4


# ------------------------------------------------------------------ float64 helpers (quaternions xyzw)


def body_q(env):
    return env._state_views(env.state_0)["body_q"].double().numpy()


def tcp_frames(env):
    """(E, 3) TCP positions and (E, 3, 3) rotations from the hand body pose, float64."""
    bq = body_q(env)
    hands = bq[env.hand_idx.numpy()]
    rots = np.array([qmat(h[3:]) for h in hands])
    pos = hands[:, :3] + rots @ np.array([0.0, 0.0, TCP_Z])
    return pos, rots


def held_frames(env):
    bq = body_q(env)[env.held_idx.numpy()]
    return bq[:, :3], np.array([qmat(q[3:]) for q in bq])


def ensure_fresh(env):
    """Reset the env if it has stepped since its last reset (other tests may have run before)."""
    if bool((env.episode_length_buf != 0).any()) or not getattr(env, "_test_fresh", True):
        env.reset()
    env._test_fresh = True
    return env


def mark_stepped(env):
    env._test_fresh = False


# ------------------------------------------------------------------ scene layout


def test_scene_per_world_indices(peg_env):
    import newton

    sc, m = peg_env.scene, peg_env.model
    bodies = sc.labels["bodies"]
    assert sc.num_worlds == E and sc.bodies_per_world == len(bodies) == 12
    hand = bodies.index("/franka/hand")
    held = bodies.index("/peg_insert/peg")
    np.testing.assert_array_equal(sc.hand_body.numpy(), [sc.bodies_per_world * w + hand for w in range(E)])
    np.testing.assert_array_equal(sc.held_body.numpy(), [sc.bodies_per_world * w + held for w in range(E)])
    body_world = m.body_world.numpy()
    for w in range(E):
        assert m.body_label[sc.hand_body.numpy()[w]].endswith("/franka/hand")
        assert m.body_label[sc.held_body.numpy()[w]].endswith("/peg_insert/peg")
        assert body_world[sc.hand_body.numpy()[w]] == w and body_world[sc.held_body.numpy()[w]] == w

    # one robot articulation per world, and it is the one that moves the hand
    mask = sc.robot_articulation_mask.numpy()
    art_world = m.articulation_world.numpy()
    art_start = m.articulation_start.numpy()
    child = m.joint_child.numpy()
    assert mask.sum() == E
    assert sorted(art_world[mask].tolist()) == list(range(E))
    robot_art = sc.robot_articulation.numpy()
    for w in range(E):
        a = robot_art[w]
        assert mask[a] and art_world[a] == w
        joints = range(art_start[a], art_start[a + 1])
        assert sc.hand_body.numpy()[w] in child[list(joints)]
        assert len(joints) == 11  # base fixed, 7 arm, hand fixed, 2 fingers
        assert sc.hand_link == [child[j] for j in joints].index(sc.hand_body.numpy()[w])
    # the peg's free joint is not a robot articulation
    joint_type = m.joint_type.numpy()
    for w in range(E):
        j = list(child).index(sc.held_body.numpy()[w])
        assert joint_type[j] == int(newton.JointType.FREE)
        assert not mask[[a for a in range(m.articulation_count) if art_start[a] <= j < art_start[a + 1]][0]]
    # every world's robot base at the origin (world_spacing 0)
    np.testing.assert_array_equal(sc.env_origins, np.zeros((E, 3)))
    np.testing.assert_allclose(sc.tcp_offset_hand, (0.0, 0.0, TCP_Z), atol=1e-7)


def test_collision_flags_and_gripper_group(peg_env):
    import newton

    m = peg_env.model
    labels = m.shape_label
    flags = m.shape_flags.numpy()
    group = peg_env.scene.gripper_group.numpy()
    world = m.shape_world.numpy()
    collide = int(newton.ShapeFlags.COLLIDE_SHAPES)
    site = int(newton.ShapeFlags.SITE)

    def kind(lbl):
        leaf = lbl.split("/")[-1]
        if "_finger/pad_" in lbl:
            return "pad"
        if lbl.startswith("/peg_insert/peg/"):
            return "peg"
        if lbl.startswith("/peg_insert/socket/"):
            return "socket"
        if lbl == "/peg_insert/table/top":
            return "table"
        return "robot:" + leaf

    counts = {}
    for s, lbl in enumerate(labels):
        k = kind(lbl)
        counts[(world[s], k.split(":")[0])] = counts.get((world[s], k.split(":")[0]), 0) + 1
        should_collide = k in ("pad", "peg", "socket", "table")
        assert bool(flags[s] & collide) == should_collide, (s, lbl, flags[s])
        assert bool(group[s]) == (k in ("pad", "peg")), (s, lbl, group[s])
        if lbl.endswith("/hand/tcp"):
            assert flags[s] & site
    for w in range(E):
        assert counts[(w, "pad")] == 10 and counts[(w, "peg")] == 1
        assert counts[(w, "socket")] == 49 and counts[(w, "table")] == 1
    assert group.sum() == 11 * E
    # socket shapes per world: the scene's list is exactly that world's socket shapes
    sock = peg_env.scene.socket_shapes.numpy()
    for w in range(E):
        expected = [s for s, lbl in enumerate(labels) if world[s] == w and kind(lbl) == "socket"]
        assert sorted(sock[w].tolist()) == expected


# ------------------------------------------------------------------ argument validation


def test_bad_arguments_raise_value_error(peg_env):
    from vkgrl_newton.envs.assembly_env import EnvConfig
    from vkgrl_newton.sim.scene import SimConfig

    for kwargs, field in [({"task": "Nope"}, "task"), ({"family": "isaac"}, "family"),
                          ({"action_dim": 5}, "action_dim"), ({"num_envs": 0}, "num_envs"),
                          ({"num_envs": 2.0}, "num_envs")]:
        with pytest.raises(ValueError, match=field):
            EnvConfig(**kwargs)
    for kwargs, field in [({"num_worlds": 0}, "num_worlds"), ({"solver": "xpbd"}, "solver"),
                          ({"substeps": 0}, "substeps"), ({"nconmax": 0}, "nconmax"), ({"njmax": 2.5}, "njmax"),
                          ({"nconmax": True}, "nconmax"), ({"geometry": "sdf"}, "geometry")]:
        with pytest.raises(ValueError, match=field):
            SimConfig(**kwargs)
    env = peg_env
    steps_before = env.episode_length_buf.clone()
    for bad in (torch.zeros(E, 4), torch.zeros(E + 1, 6), torch.zeros(6), np.zeros((E, 6))):
        with pytest.raises(ValueError, match="actions"):
            env.step(bad)
    nan = torch.zeros(E, 6)
    nan[2, 1] = float("nan")
    with pytest.raises(ValueError, match="actions"):
        env.step(nan)
    inf = torch.zeros(E, 6)
    inf[0, 0] = float("inf")
    with pytest.raises(ValueError, match="actions"):
        env.step(inf)
    with pytest.raises(ValueError, match="tcp_pos_w"):
        env.step_pose(torch.zeros(E, 2), torch.zeros(E, 4))
    torch.testing.assert_close(env.episode_length_buf, steps_before)  # nothing was stepped


# ------------------------------------------------------------------ reset


def _check_reset_state(env, author):
    task = env.task
    origins = env.origins.double().numpy()
    fixed = env.fixed_pos_w.double().numpy()
    yaw = env.fixed_yaw.double().numpy()
    target = env.target_frame_pos_w.double().numpy()

    # fixed part: Table 5.2 position noise around Factory's default, yaw in the task's range
    off = fixed - origins - FIXED_NOMINAL
    assert np.all(np.abs(off) <= np.array(task.target_pos_noise) + 1e-6), off
    assert np.all(yaw >= task.target_yaw_range[0] - 1e-6) and np.all(yaw <= task.target_yaw_range[1] + 1e-6), yaw
    tip = fixed + np.array([0.0, 0.0, FIXED_TIP])
    noise = target - tip
    assert np.all(np.linalg.norm(noise, axis=1) < 0.005), noise  # N(0, 1 mm) per axis

    # static socket shapes moved to (fixed pos, yaw) * authored local pose
    pieces = dict(author.socket_pieces())
    labels = env.model.shape_label
    shape_tf = env.model.shape_transform.numpy().astype(np.float64)
    sock = env.scene.socket_shapes.numpy()
    for w in range(E):
        q_yaw = np.array([0.0, 0.0, math.sin(yaw[w] / 2), math.cos(yaw[w] / 2)])
        r_yaw = qmat(q_yaw)
        for s in sock[w]:
            piece = pieces[labels[s].split("/")[-1]]
            qw, qx, qy, qz = piece.quat_wxyz
            p_ref = fixed[w] + r_yaw @ np.array(piece.pos)
            q_ref = qmul(q_yaw, np.array([qx, qy, qz, qw]))
            # float32 placement of positions < 1 m (a rotation and a sum: ~4 roundings of 6e-8): ~2.4e-7
            np.testing.assert_allclose(shape_tf[s, :3], p_ref, atol=2e-6, err_msg=labels[s])
            # float32 q_yaw (sin/cos, ~2 ulps) times the float32 local quaternion (4 rounded terms, ~4 ulps):
            # |q_ref . q| is 1 to ~6 * 1.19e-7 = 7e-7 on any CPU; 2e-6 leaves rounding-mode headroom
            assert abs(abs(q_ref @ shape_tf[s, 3:]) - 1.0) < 2e-6, labels[s]
    # worlds differ (each world's socket is placed on its own)
    assert len({tuple(np.round(fixed[w], 6)) for w in range(E)}) == E

    # TCP: hand-position noise box above the tip, gripper pointing down, yaw within ee_yaw_range
    tcp, rots = tcp_frames(env)
    nominal = tip + np.array([0.0, 0.0, task.hand_init_height])
    assert np.all(np.abs(tcp - nominal) <= np.array(task.ee_pos_noise) + 0.002), tcp - nominal
    down = -rots[:, :, 2] @ np.array([0.0, 0.0, 1.0])
    assert np.all(down > math.cos(math.radians(3.0))), down
    ee_yaw = np.arctan2(rots[:, 1, 0], rots[:, 0, 0])  # R = Rz(yaw) Rx(pi): x axis (cos yaw, sin yaw, 0)
    margin = math.radians(2.0)
    assert np.all(ee_yaw >= task.ee_yaw_range[0] - margin) and np.all(ee_yaw <= task.ee_yaw_range[1] + margin), \
        np.degrees(ee_yaw)

    # the peg is in the hand: origin about 32.4 mm below the TCP (in-hand noise 3 mm + 2 mm), axis vertical
    peg_p, peg_r = held_frames(env)
    below = tcp[:, 2] - peg_p[:, 2]
    assert np.all(np.abs(below - PEG_BELOW_TCP) <= IN_HAND_NOISE + 0.002), below
    assert np.all(np.linalg.norm((peg_p - tcp)[:, :2], axis=1) <= IN_HAND_NOISE + 0.002), peg_p - tcp
    assert np.all(peg_r[:, 2, 2] > math.cos(math.radians(4.0))), peg_r[:, :, 2]
    # fingers closed on the 7.986 mm peg (pads touch at about 3.1 mm), both equal (mimic / same drive)
    fingers = env._state_views(env.state_0)["joint_q"][:, 7:9].double().numpy()
    assert np.all((fingers > 0.0015) & (fingers < 0.004)), fingers
    assert np.all(np.abs(fingers[:, 0] - fingers[:, 1]) < 2e-4), fingers

    # episode buffers cleared
    assert int(env.episode_length_buf.abs().sum()) == 0
    assert not bool(env.success.any())
    assert torch.count_nonzero(env.actions_applied) == 0
    return fixed, yaw


def test_reset_distributions_within_table_5_2(peg_env):
    from vkgrl_newton.assets_usd import author

    env = ensure_fresh(peg_env)
    samples = [_check_reset_state(env, author)]
    for _ in range(2):
        env.reset()
        samples.append(_check_reset_state(env, author))
    env._test_fresh = True
    # the resets draw new samples (12 worlds in all); the yaw spreads over the 0..360 deg range
    fixed = np.concatenate([f for f, _ in samples])
    yaws = np.concatenate([y for _, y in samples])
    assert len({tuple(np.round(f, 6)) for f in fixed}) == len(fixed)
    assert yaws.max() - yaws.min() > math.radians(90.0)


# ------------------------------------------------------------------ observations


def test_observation_after_reset(peg_env):
    from vkgrl_newton.envs.assembly_env import EnvConfig

    env = ensure_fresh(peg_env)
    obs = env.get_observations()["policy"].double().numpy()
    assert obs.shape == (E, 8) and env.obs_dim == 8
    assert env.observation_space.shape == (8,) and env.action_space.shape == (6,)
    np.testing.assert_array_equal(obs[:, 0], 0.0)  # episode phase s_t
    tcp, _ = tcp_frames(env)
    np.testing.assert_allclose(obs[:, 1:4], tcp - env.target_frame_pos_w.double().numpy(), atol=2e-6)
    # the hand quaternion comes out of forward kinematics through the base and 7 arm joints: ~9 float32
    # quaternion products of ~4 rounded operations per component, so |q| is 1 to ~9 * 4 * 1.19e-7 = 4.3e-6
    np.testing.assert_allclose(np.linalg.norm(obs[:, 4:8], axis=1), 1.0, atol=1e-5)
    hand_q = body_q(env)[env.hand_idx.numpy(), 3:]
    # TCP quat = hand quat: the observation copies the float32 value, so it is equal, not merely close
    # (a dot product against 1.0 would only hold to |q|^2's rounding, which differs between CPUs)
    np.testing.assert_array_equal(obs[:, 4:8], hand_q)

    # Forge layout (8 + smoothed contact force 3 = 11) without building a second env: same buffers, forge config
    saved = env.cfg
    try:
        env.cfg = dataclasses.replace(saved, family="forge")
        forge = env.get_observations()["policy"].double().numpy()
    finally:
        env.cfg = saved
    assert forge.shape == (E, 11)
    # the same float32 observation terms, by the same code, in one process: equal but for a fused or
    # reordered float32 sum (<= a few 6e-8 of values < 1); 1e-7 bounds it
    np.testing.assert_allclose(forge[:, :8], obs, atol=1e-7)
    force = env.force_smoothed_w.double().numpy()
    assert np.all(np.abs(forge[:, 8:] - force) < 6.0)  # N(0, 1 N) observation noise
    assert EnvConfig(family="forge").dynamics_randomized and not EnvConfig().dynamics_randomized


# ------------------------------------------------------------------ stepping


def test_step_zero_action_holds_and_plus_z_moves_up(peg_env):
    env = ensure_fresh(peg_env)
    mark_stepped(env)
    tcp0, _ = tcp_frames(env)
    obs, rew, dones, extras = env.step(torch.zeros(E, 6))
    tcp1, rot1 = tcp_frames(env)
    assert np.all(np.linalg.norm(tcp1 - tcp0, axis=1) < 0.002), tcp1 - tcp0
    assert np.all(-rot1[:, 2, 2] > math.cos(math.radians(3.0)))
    np.testing.assert_array_equal(env.episode_length_buf.numpy(), 1)
    np.testing.assert_allclose(obs["policy"][:, 0].numpy(), 1.0 / 150.0, rtol=1e-6)  # one float32 division: <= u32/2
    assert not dones.any() and extras["log"]["/physics_resets"] == 0.0
    # not in the success state (peg ~15 mm above the hole): reward exactly 0
    peg_p, _ = held_frames(env)
    d = peg_p - env.fixed_pos_w.double().numpy()
    success = (np.linalg.norm(d[:, :2], axis=1) < SUCCESS_XY) & (d[:, 2] < SUCCESS_Z)
    assert not success.any()
    np.testing.assert_array_equal(rew.numpy(), 0.0)
    _check_peg_in_hand(env)

    # +z: the target is the current TCP + 0.02 m * EMA-smoothed action, clipped to 5 cm above the target frame
    target = env.target_frame_pos_w.double().numpy()
    headroom = POS_BOUND - (tcp1[:, 2] - target[:, 2])
    a = torch.zeros(E, 6)
    a[:, 2] = 1.0
    applied = []
    for _ in range(2):
        obs, rew, dones, extras = env.step(a)
        applied.append(float(env.actions_applied[0, 2]))
        cmd = env.cmd_pos_w.double().numpy()
        assert np.all(np.abs(cmd - target) <= POS_BOUND + 1e-6), cmd - target  # Factory pos_action_bounds
        np.testing.assert_array_equal(rew.numpy(), 0.0)
    np.testing.assert_allclose(applied, [0.2, 0.36], rtol=1e-6)  # EMA 0.2 from 0
    tcp2, _ = tcp_frames(env)
    dz = tcp2[:, 2] - tcp1[:, 2]
    free = headroom > 0.004
    over = headroom < 0.0
    assert free.any(), headroom
    # loose magnitude: up, by more than 0.1 mm, by less than the summed commanded offsets 0.02 * (0.2 + 0.36)
    assert np.all(dz[free] > 1e-4) and np.all(dz[free] < 0.02 * sum(applied)), dz
    # worlds that start above the bound are pulled back down to it (Factory behaviour)
    assert np.all(dz[over] < 0.0), (dz, headroom)
    assert np.all(np.abs(tcp2[:, :2] - tcp1[:, :2]) < 0.002)
    _check_peg_in_hand(env)


def _check_peg_in_hand(env):
    tcp, _ = tcp_frames(env)
    peg_p, peg_r = held_frames(env)
    below = tcp[:, 2] - peg_p[:, 2]
    assert np.all(np.abs(below - PEG_BELOW_TCP) <= IN_HAND_NOISE + 0.003), below
    assert np.all(np.linalg.norm((peg_p - tcp)[:, :2], axis=1) <= IN_HAND_NOISE + 0.003)
    assert np.all(peg_r[:, 2, 2] > math.cos(math.radians(5.0)))


# ------------------------------------------------------------------ scripted episode and task camera


def test_scripted_inserter_seats_the_peg(peg_env):
    """A short scripted episode: every world reaches the success state (Factory's test, checked here
    in float64 from the body poses), the peg ends centred and seated, contact forces stay moderate."""
    from vkgrl_newton.envs.scripted import ScriptedInserter

    env = ensure_fresh(peg_env)
    mark_stepped(env)
    policy = ScriptedInserter(seed=1)
    policy.reset(env)
    fixed = env.fixed_pos_w.double().numpy()
    seated = np.zeros(E, dtype=bool)
    for _ in range(130):  # 8.7 s of the 10 s episode; the demonstrator seats the peg in ~5-7 s
        _, rew, dones, extras = env.step_pose(*policy.act(env))
        assert not dones.any() and extras["log"]["/physics_resets"] == 0.0
        peg_p, _ = held_frames(env)
        d = peg_p - fixed
        now = (np.linalg.norm(d[:, :2], axis=1) < SUCCESS_XY) & (d[:, 2] < SUCCESS_Z)
        np.testing.assert_array_equal(env.success.numpy(), now)  # the env's test agrees with the reference
        np.testing.assert_array_equal(rew.numpy()[now], 4.0)
        seated |= now
        if seated.all():
            break
    assert seated.all(), seated
    peg_p, peg_r = held_frames(env)
    d = peg_p - fixed
    assert np.all(np.abs(d[:, 2]) < SUCCESS_Z) and np.all(np.linalg.norm(d[:, :2], axis=1) < 2e-4), d
    assert np.all(peg_r[:, 2, 2] > math.cos(math.radians(1.0)))  # upright in the hole
    peak = env.force_peak.numpy()
    assert np.all(peak > 0.1) and np.all(peak < 60.0), peak  # it touched the socket, gently


def test_task_camera_pose_and_image(peg_env):
    """Camera pose against a float64 composition of the hand pose and the Table 5.6 mount, and the
    rendered images show the peg (orange) and the socket (blue)."""
    from vkgrl_newton.sim.camera import TASK_CAMERAS, TaskCamera

    env = ensure_fresh(peg_env)
    spec = TASK_CAMERAS["PegInsert"]
    cam = TaskCamera(env.model, spec, E)
    hand = env._state_views(env.state_0)["body_q"][env.hand_idx]
    poses = cam.camera_poses_w(hand[:, :3], hand[:, 3:]).double().numpy()
    tilt = math.radians(-20.0)
    for e in range(E):
        h = hand[e].double().numpy()
        r_hand = qmat(h[3:])
        # float32 camera pose of positions < 1 m against float64 of the same float32 hand pose: ~6 roundings
        # of 6e-8 (3.6e-7); unit vectors below: ~10 roundings of 6e-8
        np.testing.assert_allclose(poses[e, :3], h[:3] + r_hand @ np.array(spec.pos_hand), atol=1e-6)
        # Newton cameras look along their local -Z: that is the optical axis, the hand z tilted
        # 20 degrees about the hand y toward the gripper axis
        forward = qmat(poses[e, 3:]) @ np.array([0.0, 0.0, -1.0])
        np.testing.assert_allclose(forward, r_hand @ np.array([math.sin(tilt), 0.0, math.cos(tilt)]), atol=1e-6)
    images = cam.render(env.state_0, hand[:, :3], hand[:, 3:])
    assert images.shape == (E, spec.height, spec.width, 3) and images.dtype == np.uint8
    rgb = images.astype(int)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    orange = (r > 150) & (r > g + 30) & (g > b + 30)
    blue = (b > r + 40) & (b > g + 20)
    assert np.all(orange.sum(axis=(1, 2)) > 200), orange.sum(axis=(1, 2))
    assert np.all(blue.sum(axis=(1, 2)) > 200), blue.sum(axis=(1, 2))


def test_contact_camera_looks_at_the_peg_tip_and_the_latent_renders_the_encoders_camera(peg_env):
    """The quick preset's PegInsert camera (sim.camera.CONTACT_CAMERAS) is aimed through the held
    peg's bottom: its optical axis passes within 2 degrees of it (Table 5.6's, tilted 20 degrees,
    ~9 degrees off), and 1 mm there spans about a pixel at 64 px. CameraLatent renders the camera
    its encoder's images came from, and refuses one of another resolution."""
    from vkgrl_newton.sim.camera import CONTACT_CAMERAS, TASK_CAMERAS, TaskCamera
    from vkgrl_newton.envs.camera_latent import CameraLatent
    from vkgrl_newton.vision.vae import DenoisingVAE, FrozenEncoder, VAEConfig

    env = ensure_fresh(peg_env)
    hand = env._state_views(env.state_0)["body_q"][env.hand_idx]
    held = env.held_pose()[0].double().numpy()

    def off_axis_deg(spec):
        poses = TaskCamera(env.model, spec, E).camera_poses_w(hand[:, :3], hand[:, 3:]).double().numpy()
        out = []
        for e in range(E):
            forward = qmat(poses[e, 3:]) @ np.array([0.0, 0.0, -1.0])
            to_tip = held[e] - poses[e, :3]
            out.append(math.degrees(math.acos(forward @ to_tip / np.linalg.norm(to_tip))))
        return np.array(out), np.linalg.norm(held - poses[:, :3], axis=1)

    contact, dist = off_axis_deg(CONTACT_CAMERAS["PegInsert"])
    table, _ = off_axis_deg(TASK_CAMERAS["PegInsert"])
    assert np.all(contact < 2.0) and np.all(table > 6.0), (contact, table)
    spec = CONTACT_CAMERAS["PegInsert"]
    mm_per_px = 1e3 * dist * spec.horizontal_aperture / spec.focal_length / 64  # pinhole, at the tip's range
    assert np.all((0.8 < mm_per_px) & (mm_per_px < 1.4)), mm_per_px
    small = dataclasses.replace(spec, width=32, height=32)
    encoder = FrozenEncoder(DenoisingVAE(VAEConfig(resolution=32, channels=(8, 8, 8, 8, 8))),
                            camera=json.loads(json.dumps(dataclasses.asdict(small))))  # as stored in a vae.pt
    latent = CameraLatent(env, encoder)
    assert latent.spec == small
    assert latent(env).shape == (E, encoder.latent_dim)
    wrong = FrozenEncoder(DenoisingVAE(VAEConfig(resolution=64, channels=(8, 8, 8, 8, 8))),
                          camera=dataclasses.asdict(small))
    with pytest.raises(ValueError, match="renders 32 x 32, its input is 64 x 64"):
        CameraLatent(env, wrong)
    # --vision-probe-obs: the probe's image-frame vector turned into the world by this camera's optical pose follows
    # the latent (an affine probe of known weights; lateral_from_image itself is checked against scipy in test_ceiling)
    from vkgrl_newton.vision.probe import ProbeMLP, lateral_from_image

    rng = np.random.default_rng(0)
    state = {"x_mean": np.zeros(encoder.latent_dim), "x_scale": np.ones(encoder.latent_dim), "y_mean": np.zeros(3),
             "y_scale": np.ones(3), "weights": [1e-3 * rng.normal(size=(encoder.latent_dim, 3))],
             "biases": [1e-3 * rng.normal(size=3)]}
    with_probe = CameraLatent(env, encoder, probe=ProbeMLP(state))
    out = with_probe(env)
    z = latent(env)
    assert out.shape == (E, encoder.latent_dim + 2) and torch.equal(out[:, :-2], z)
    d = z.double().numpy() @ state["weights"][0] + state["biases"][0]
    q = with_probe.camera.optical_poses_w(*env.hand_pose())[:, 3:]
    want = lateral_from_image(torch.from_numpy(d), q.double()).numpy()
    # float32 latent and quaternion (6e-8 relative) on ~1e-3 m: ~1e-10 m
    np.testing.assert_allclose(out[:, -2:].double().numpy(), want, rtol=0, atol=1e-9)


# ------------------------------------------------------------------ blow-ups (these perturb the env: keep last)


def _corrupt_and_step(env, value):
    ensure_fresh(env)
    mark_stepped(env)
    z = torch.zeros(E, 6)
    env.step(z)
    total = env.physics_resets_total
    v = env._state_views(env.state_0)
    hqd = env.scene.held_qd_start
    # the solver integrates joint_qd (body_qd is derived), so corrupt the peg's free-joint velocity in world 1
    v["joint_qd"][1, hqd:hqd + 6] = value
    obs, rew, dones, extras = env.step(z)
    return total, obs, rew, dones, extras


def _check_only_world_1_reset(env, total, obs, rew, dones, extras):
    np.testing.assert_array_equal(env.episode_length_buf.numpy(), [2, 0, 2, 2])
    assert extras["log"]["/physics_resets"] == 1.0
    assert env.physics_resets_total == total + 1
    np.testing.assert_array_equal(dones.numpy(), [False, True, False, False])
    assert float(rew[1]) == 0.0
    v = env._state_views(env.state_0)
    assert torch.isfinite(v["body_q"]).all() and torch.isfinite(v["joint_q"]).all()
    assert torch.isfinite(obs["policy"]).all()
    _check_peg_in_hand(env)


def test_forge_held_mass_and_dead_zone_randomization(peg_env):
    """Forge (`forge_env_cfg.py`, `forge_events.py`): held mass nominal +- 5 g per reset with inertia scaled alike and passed to
    MuJoCo-Warp; the dead zone drawn again every 30 control steps (2 s), only in those worlds."""
    import newton
    import warp as wp

    env = peg_env
    saved = env.cfg
    E = env.num_envs
    mask = torch.tensor([True, False, True, False])
    try:
        env.cfg = dataclasses.replace(saved, randomize_dynamics=True)
        env._randomize_held_mass(mask)
        idx = env.held_idx.numpy()
        mass = env.body_mass.double().numpy()[idx]
        nominal = env.held_mass_nominal.double().numpy()
        m = mask.numpy()
        assert np.all(np.abs(mass[m] - nominal[m]) <= 0.005 + 1e-7) and np.all(mass[m] != nominal[m])
        np.testing.assert_array_equal(mass[~m], nominal[~m])
        inertia = env.body_inertia.double().numpy()[idx]
        inertia_nominal = env.held_inertia_nominal.double().numpy()
        for w in np.nonzero(m)[0]:
            # float32 scaling of the inertia by mass / nominal: 2 roundings (<= 1.2e-7 relative); rtol 1e-5 bounds
            # it, atol 1e-12 (kg m^2) covers the zero off-diagonal entries
            np.testing.assert_allclose(inertia[w], inertia_nominal[w] * mass[w] / nominal[w], rtol=1e-5, atol=1e-12)
        # one float32 reciprocal: <= u32/2 = 3e-8 relative
        np.testing.assert_allclose(env.body_inv_mass.double().numpy()[idx], 1.0 / mass, rtol=1e-6)
        solver_masses = wp.to_torch(env.solver.mjw_model.body_mass).double().numpy().ravel()
        for w in np.nonzero(m)[0]:  # the solver got the new masses
            assert np.min(np.abs(solver_masses - mass[w])) < 1e-7

        if bool((env.episode_length_buf != 0).any()):
            env.reset()
        env.dead_zone.fill_(0.123)
        env.episode_length_buf[:] = torch.tensor([29, 10, 59, 0])
        env.step(torch.zeros(E, 6))
        dz = env.dead_zone.double().numpy()
        for w, redrawn in enumerate([True, False, True, False]):
            if redrawn:
                assert not np.allclose(dz[w], 0.123)
                ratio_w = dz[w] / np.array([5.0, 5, 5, 1, 1, 1])
                assert 0.0 <= ratio_w[0] <= 1.0 and np.allclose(ratio_w, ratio_w[0])  # one U(0,1) per world
            else:
                np.testing.assert_allclose(dz[w], 0.123)
    finally:
        env.cfg = saved
        env.body_mass[env.held_idx] = env.held_mass_nominal
        env.body_inv_mass[env.held_idx] = 1.0 / env.held_mass_nominal
        env.body_inertia[env.held_idx] = env.held_inertia_nominal
        env.body_inv_inertia[env.held_idx] = torch.linalg.inv(env.held_inertia_nominal)
        env.solver.notify_model_changed(newton.ModelFlags.BODY_INERTIAL_PROPERTIES)
        env.reset()  # Factory gains and no dead zone again


def test_blowup_resets_only_that_world(peg_env):
    env = peg_env
    total, obs, rew, dones, extras = _corrupt_and_step(env, 1.0e3)  # 1 km/s: thrown out of the hand
    _check_only_world_1_reset(env, total, obs, rew, dones, extras)
    # and the world runs normally afterwards
    for k in range(2):
        obs, rew, dones, extras = env.step(torch.zeros(E, 6))
        assert extras["log"]["/physics_resets"] == 0.0
        np.testing.assert_array_equal(env.episode_length_buf.numpy(), [3 + k, 1 + k, 3 + k, 3 + k])


# Regression: a NaN world used to keep NaN in MuJoCo-Warp's qacc_warmstart and blow up again.
def test_nan_blowup_world_recovers(peg_env):
    env = peg_env
    total, obs, rew, dones, extras = _corrupt_and_step(env, float("nan"))
    _check_only_world_1_reset(env, total, obs, rew, dones, extras)
    obs, rew, dones, extras = env.step(torch.zeros(E, 6))
    assert extras["log"]["/physics_resets"] == 0.0, "world 1 blew up again on the step after its reset"
    np.testing.assert_array_equal(env.episode_length_buf.numpy(), [3, 1, 3, 3])
    # a full reset (all worlds) afterwards is finite too (it used to return NaN observations for world 1)
    obs = env.reset()["policy"]
    assert torch.isfinite(obs).all() and torch.isfinite(env._state_views(env.state_0)["body_q"]).all()
    env._test_fresh = True


def _snapshot_everything(env):
    """Brute force, independent of the env's own bookkeeping: a copy of every Warp array of both
    states, the control and the solver's data, and of every torch tensor the env holds."""
    import warp as wp

    arrays = []
    holders = [env.state_0, env.state_1, env.control, getattr(env.solver, "mjw_data", None)]
    for h in holders:
        if h is None:
            continue
        names = [f.name for f in dataclasses.fields(h)] if dataclasses.is_dataclass(h) else list(vars(h))
        for name in names:
            a = getattr(h, name, None)
            if isinstance(a, wp.array) and a.size:
                arrays.append((a, wp.clone(a)))
    tensors = [(t, t.clone()) for t in vars(env).values() if isinstance(t, torch.Tensor)]
    return arrays, tensors, env.generator.get_state(), env.state_0, env.state_1


def _restore_everything(env, snap):
    import warp as wp

    arrays, tensors, gen, s0, s1 = snap
    env.state_0, env.state_1 = s0, s1
    for live, saved in arrays:
        wp.copy(live, saved)
    for live, saved in tensors:
        live.copy_(saved)
    env.generator.set_state(gen)


def _held_in_tcp(env):
    """Held part position in the TCP frame (E, 3), float64."""
    tcp, rot = tcp_frames(env)
    peg, _ = held_frames(env)
    return np.einsum("eji,ej->ei", rot, peg - tcp)


def test_blowup_reset_settles_that_world_and_leaves_the_others_untouched(peg_env):
    """A world reset after a blow-up settles its grasp like every other reset (the part no longer
    slides in the hand once the episode runs), and the settle does not advance the other worlds:
    their trajectories are bitwise those of a branch in which nothing blew up."""
    env = ensure_fresh(peg_env)
    mark_stepped(env)
    z = torch.zeros(E, 6)
    env.step(z)
    snap = _snapshot_everything(env)
    reference = []
    for _ in range(3):
        env.step(z)
        reference.append(body_q(env))
    _restore_everything(env, snap)

    hqd = env.scene.held_qd_start
    env._state_views(env.state_0)["joint_qd"][1, hqd:hqd + 6] = 1.0e3  # world 1 blows up in the next step
    obs, rew, dones, extras = env.step(z)
    assert extras["log"]["/physics_resets"] == 1.0 and dones.tolist() == [False, True, False, False]
    got = [body_q(env)]
    start = _held_in_tcp(env)[1]
    for _ in range(2):
        env.step(z)
        got.append(body_q(env))
    bpw = env.scene.bodies_per_world
    others = np.concatenate([np.arange(w * bpw, (w + 1) * bpw) for w in (0, 2, 3)])
    # bitwise: both branches run here, in one process on one machine, from one snapshot (across CPUs the
    # trajectories differ in their last bits, but never between these two branches)
    for ref, now in zip(reference, got):
        np.testing.assert_array_equal(now[others], ref[others])
    # the reset world's grasp has settled: over the next 12 control steps (0.8 s, zero action) the part
    # moves in the hand by well under the 2.3 mm an unsettled grasp showed (docs/log/benchmarks.md)
    for _ in range(10):
        env.step(z)
    drift = np.linalg.norm(_held_in_tcp(env)[1] - start)
    assert drift < 3e-4, drift
    env.reset()
    env._test_fresh = True


def test_reset_ik_failures_are_counted_and_logged(peg_env):
    """A hand target out of the arm's reach: the IK cannot converge, the world is counted (total
    and the step's log), and its episode still runs."""
    env = ensure_fresh(peg_env)
    task = env.task
    total = env.ik_failures_total
    try:
        env.task = dataclasses.replace(task, hand_init_height=2.0)  # 2 m above the socket: unreachable
        env.reset()
        assert env.ik_failures_total == total + E
        mark_stepped(env)
        z = torch.zeros(E, 6)
        obs, _, _, extras = env.step(z)
        assert extras["log"]["/ik_failures"] == 0.0  # no reset in this step
        hqd = env.scene.held_qd_start
        env._state_views(env.state_0)["joint_qd"][2, hqd:hqd + 6] = 1.0e3
        obs, _, dones, extras = env.step(z)
        assert dones.tolist() == [False, False, True, False]
        assert extras["log"]["/ik_failures"] == 1.0 and env.ik_failures_total == total + E + 1
        assert torch.isfinite(obs["policy"]).all()
    finally:
        env.task = task
        env.reset()
        env._test_fresh = True
    assert env.ik_failures_total == total + E + 1  # the reachable reset converged everywhere
