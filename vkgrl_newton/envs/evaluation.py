"""Policies as the env sees them, and the evaluation loop that reports the thesis metrics.

A policy here has `reset(env)` (called at the start of every evaluation episode) and
`step(env, obs) -> env step result`: it picks its action and drives the env through the matching
entry point (`env.step` for the SAC path, `env.step_pose` for KGRL and the scripted demonstrator).

- `ScriptedPolicy`: the privileged demonstrator (envs/scripted.py).
- `ScriptedDeltaPolicy`: the same demonstrator through the SAC action space (env.actions_for_command).
- `RandomPolicy`, `ZeroPolicy`: uniform in [-1, 1]^D / zeros, through the SAC path.
- `KMPPriorPolicy`: the KMP prior alone, zeta = 0 (KGRL with a silent policy).
- `KMPSearchPolicy`: the prior plus a blind spiral search once the part is blocked, in a floored null
  space, from the observation alone (issue 28's baseline of what the KGRL action space holds).
- `KMPOraclePolicy`: the same, steered by the true lateral error instead of the spiral (privileged).
- `AgentPolicy`: a trained agent, deterministic (tanh of the mean) or sampled, on its method's path.

`evaluate(env, policy, episodes)` runs whole episodes (all worlds together) and returns the
metrics of train/evaluate.py's JSON; `record_video` renders the task camera along the way.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, replace

import math
import time

import numpy as np
import torch
from tqdm import tqdm

__all__ = ["Policy", "ScriptedPolicy", "ScriptedDeltaPolicy", "RandomPolicy", "ZeroPolicy", "KMPPriorPolicy", "KMPSearchPolicy", "KMPCentrePolicy",
           "KMPOraclePolicy", "SearchParams", "spiral_offset", "AgentPolicy", "evaluate", "policy_observation",
           "kgrl_observation", "ORACLE_PUSH_MM", "REST_HEIGHT", "task_search_params", "BASE_CONTROLLERS",
           "base_controller"]


def policy_observation(obs, time_obs: bool = True) -> torch.Tensor:
    """The policy's input from the env's observation TensorDict; without normalized time (column 0)
    for the time ablation of thesis Appendix A.1 (the KMP still follows time)."""
    x = obs["policy"] if not isinstance(obs, torch.Tensor) else obs
    return x if time_obs else x[:, 1:]


def kgrl_observation(x: torch.Tensor, action_path, final: bool = False) -> torch.Tensor:
    """x with the KMP query's phase appended where the action path has the time action
    (KGRLActionPath.query_phase; `final`: where each world's last step left it); x otherwise."""
    phase = action_path.query_phase(final) if action_path is not None and hasattr(action_path, "query_phase") else None
    return x if phase is None else torch.cat([x, phase], -1)


class Policy(ABC):
    """Base of the evaluation policies: `reset` is called at every episode start (nothing to do
    unless the policy keeps per-episode state), `step` drives the env one control step."""

    def reset(self, env) -> None:
        return None

    @abstractmethod
    def step(self, env, obs):
        """One control step: returns what the env's step returns (obs, rewards, dones, extras)."""


class ScriptedPolicy(Policy):
    def __init__(self, seed: int = 0):
        from .scripted import ScriptedInserter

        self.inserter = ScriptedInserter(seed=seed)

    def reset(self, env) -> None:
        self.inserter.reset(env)

    def step(self, env, obs):
        return env.step_pose(*self.inserter.act(env))


class ScriptedDeltaPolicy(ScriptedPolicy):
    """The scripted demonstrator acting through the SAC action space: each control step its pose
    command becomes the actions whose smoothed value commands that pose at the step's first physics
    step (AssemblyEnv.actions_for_command; the delta mapping then follows the TCP through the step,
    so it is not the demonstrator's own controller, and the smoothing lags its fast changes). The
    demonstrator restarts per world where an episode starts (step 0, in `actions`), so it also acts in
    a SAC run's first transitions (SACConfig.prior_rollouts_policy "scripted": RLPD's demonstrations
    in a buffer of their own)."""

    def __init__(self, seed: int = 0):
        super().__init__(seed)
        self._started = False

    def reset(self, env, mask: torch.Tensor | None = None) -> None:
        """The demonstrator restarted in the worlds of `mask` (all when None)."""
        self.inserter.reset(env, mask if self._started else None)
        self._started = True

    def actions(self, env, obs) -> torch.Tensor:
        """(E, D) actions in [-1, 1] for this control step (the SAC action space)."""
        start = env.episode_length_buf == 0
        # one host read a step, only while it acts (a SAC run's first prior_rollouts transitions)
        if not self._started or bool(start.any()):
            self.reset(env, start)
        return env.actions_for_command(*self.inserter.act(env))

    def step(self, env, obs):
        # evaluation: `evaluate` calls reset at every episode start (all worlds together, as ScriptedPolicy;
        # a world reset alone by a blow-up is not restarted here, and its episode is not counted)
        return env.step(env.actions_for_command(*self.inserter.act(env)))


class RandomPolicy(Policy):
    def __init__(self, seed: int = 0):
        self.seed = seed
        self.gen = None

    def reset(self, env) -> None:
        if self.gen is None:
            self.gen = torch.Generator(device=env.tdev).manual_seed(self.seed)

    def step(self, env, obs):
        a = torch.rand(env.num_envs, env.num_actions, device=env.tdev, generator=self.gen) * 2 - 1
        return env.step(a)


class ZeroPolicy(Policy):
    def step(self, env, obs):
        return env.step(torch.zeros(env.num_envs, env.num_actions, device=env.tdev))


class KMPPriorPolicy(Policy):
    """Follows the KMP prior: zeta = 0 at every step (the KGRL path with a zero action)."""

    def __init__(self, action_path):
        self.path = action_path

    def step(self, env, obs):
        return self.path.step(torch.zeros(env.num_envs, self.path.action_dim, device=env.tdev))


@dataclass(frozen=True)
class SearchParams:
    """KMPSearchPolicy's settings (mm, control steps). Defaults: session 15's `arch_settle`
    (docs/log/benchmarks.md, "the gap is information"), +0.203 over the prior on PegInsert Factory 4D."""

    blocked_mm: float = 15.0  # blocked: the TCP this far above the prior's final height ...
    stall_steps: int = 15  # ... having descended less than stall_mm over this many steps ...
    stall_mm: float = 0.3
    n_min: int = 60  # ... at this step or later
    press_mm: float = 1.0  # searching: z commanded this far below the TCP (the prior presses ~20 mm)
    pitch_mm: float = 1.2  # the spiral's growth per turn: under twice the chamfer's catch (~0.8 mm a side)
    speed_mm: float = 0.3  # along the spiral, per control step
    track: float = 1.0  # the command leads the wanted point by this times the TCP's lag
    settle_mm: float = 0.3  # dropped this far: x, y frozen, z back to the prior's
    reach_floor_mm: float = 4.0  # KMPSearchPolicy.with_floors: the null space's reach floors
    reach_floor_z_mm: float = 25.0  # (kmp.tables.with_reach_floor) on x, y and z, so that the search fits in it


def spiral_offset(k: torch.Tensor, pitch: float, speed: float) -> torch.Tensor:
    """(..., 2) offset (m) of an Archimedean spiral r = b theta (b = pitch / 2 pi) after k steps at
    `speed` m per step along it, using arc ~ b theta^2 / 2 (exact as theta grows; the first turn runs
    a little fast)."""
    b = pitch / (2 * math.pi)
    th = torch.sqrt(2 * speed * k / b)
    return b * th.unsqueeze(-1) * torch.stack((torch.cos(th), torch.sin(th)), -1)


class KMPSearchPolicy(Policy):
    """The KMP prior (a = 0) until the held part is blocked, then a blind search in the null space.

    It reads only what a proprioceptive KGRL policy observes: the TCP relative to the observed target
    frame and the episode's step. Blocked: the TCP stays `blocked_mm` above the prior's final height and
    stalls (SearchParams). From then on, per world: z is commanded `press_mm` below the TCP (a light
    press: the prior's ~20 mm press keeps a resting peg from sliding), and x, y follow an Archimedean
    spiral around where the TCP was blocked; once the TCP drops `settle_mm`, x, y are frozen and z goes
    back to the prior's. The wanted eta is reached through the null space on x, y, z with the yaw action
    0 (solving for yaw too swings it to +-1: G couples it with x, y), clipped to the action path's
    reach: `with_floors` gives it floors of its own (a deviation from the thesis's null space; a = 0 is
    still the prior). Per-world state restarts where an episode starts (step 0), so it also acts in
    training (SACConfig.prior_rollouts_policy "search")."""

    def __init__(self, action_path, params: SearchParams | None = None):
        self.params = params or SearchParams()
        self.path = action_path
        env = action_path.env
        dev = env.tdev
        self.mean = self.path.tables.mean.to(dev, torch.float64)  # (N + 1, 6): eta = m[n] + G[n] zeta
        self.gain3 = self.path.tables.gain.to(dev, torch.float64)[:, :3, :3]
        self.scale3 = self.path.scale[:3].to(torch.float64)
        self.seat_z = float(self.mean[-1, 2])  # the prior's final TCP height over the target frame (seated)
        E = env.num_envs
        self.z_hist = torch.zeros(E, env.max_episode_length + 1, dtype=torch.float64, device=dev)
        self.since = torch.full((E,), -1, dtype=torch.long, device=dev)  # step found blocked (-1: not yet)
        self.z_blocked = torch.zeros(E, dtype=torch.float64, device=dev)
        self.centre = torch.zeros(E, 2, dtype=torch.float64, device=dev)
        self.found = torch.zeros(E, dtype=torch.bool, device=dev)  # dropped while searching
        self.held = torch.zeros(E, 2, dtype=torch.float64, device=dev)  # the x, y wanted when it dropped

    @classmethod
    def with_floors(cls, tables, env, params: SearchParams | None = None) -> "KMPSearchPolicy":
        """The search in an action path over `tables` with the params' reach floors (train/evaluate.py)."""
        p = params or SearchParams()
        return cls(cls.floored_path(tables, env, p), p)

    @staticmethod
    def floored_path(tables, env, p: SearchParams):
        """The KGRLActionPath over `tables` with p's reach floors (every with_floors)."""
        from .kgrl_action import KGRLActionPath

        return KGRLActionPath(tables, env, reach_floor=1e-3 * p.reach_floor_mm, reach_floor_z=1e-3 * p.reach_floor_z_mm)

    def actions(self, env, obs) -> torch.Tensor:
        """(E, D) actions in [-1, 1] for this control step (the KGRL action space)."""
        p = self.params
        rel = policy_observation(obs)[:, 1:4].to(torch.float64)  # TCP - observed target frame (m)
        n = env.episode_length_buf.long()
        start = n == 0  # a new episode in this world
        self.since.masked_fill_(start, -1)
        self.found.masked_fill_(start, False)
        rows = torch.arange(rel.shape[0], device=rel.device)
        self.z_hist[rows, n] = rel[:, 2]
        stalled = (self.z_hist[rows, (n - p.stall_steps).clamp(min=0)] - rel[:, 2]) < p.stall_mm * 1e-3
        high = (rel[:, 2] - self.seat_z) > p.blocked_mm * 1e-3
        new = (self.since < 0) & (n >= max(p.n_min, p.stall_steps)) & stalled & high
        self.since = torch.where(new, n, self.since)
        self.z_blocked = torch.where(new, rel[:, 2], self.z_blocked)
        self.centre = torch.where(new.unsqueeze(-1), rel[:, :2], self.centre)
        on = self.since >= 0  # (no early return when none is: that would read the host every step)
        step = n.clamp(max=self.mean.shape[0] - 1)
        m = self.mean[step, :3]
        want = torch.cat([self._search_xy(env, rel, n), (rel[:, 2] - p.press_mm * 1e-3).unsqueeze(-1)], -1)
        drop = on & ~self.found & ((self.z_blocked - rel[:, 2]) > p.settle_mm * 1e-3)
        self.held = torch.where(drop.unsqueeze(-1), want[:, :2], self.held)
        self.found |= drop
        want = torch.where(self.found.unsqueeze(-1), torch.cat([self.held, self._settled_z(env, rel, m)], -1), want)
        self._last = (want, step, on)  # (KMPOraclePolicy's yaw)
        # (E, 3): x, y, z. solve_ex without its error check: the same LU solve as linalg.solve, without the host sync
        # that solve's check costs on CUDA every step (the tables' gains are well conditioned, ~1e2)
        zeta = torch.linalg.solve_ex(self.gain3[step], (want - m).unsqueeze(-1), check_errors=False)[0].squeeze(-1)
        a = torch.zeros(rel.shape[0], env.num_actions, device=env.tdev)
        a[:, :3] = torch.where(on.unsqueeze(-1), (zeta / self.scale3).clamp(-1.0, 1.0), 0.0).to(a.dtype)
        return a

    def _search_xy(self, env, rel: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        """(E, 2) float64 x, y of the commanded eta while searching: the spiral around where the TCP was
        blocked, led by `track` times the TCP's lag."""
        p = self.params
        wanted = self.centre + spiral_offset((n - self.since).to(torch.float64), p.pitch_mm * 1e-3, p.speed_mm * 1e-3)
        return wanted + p.track * (wanted - rel[:, :2])

    def _settled_z(self, env, rel: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        """(E, 1) z of the commanded eta once the part has dropped: the prior's."""
        return m[:, 2:]

    def step(self, env, obs):
        return self.path.step(self.actions(env, obs))


# issue 28's oracle (docs/results/kgrl_reach_28/search_probe.py "oracle"): the search's blocked test, press and
# floors, settling once the TCP has dropped 1 mm, and x, y steered by the true lateral error, 1.5 x per step
ORACLE_PARAMS = SearchParams(settle_mm=1.0)
ORACLE_GAIN = 1.5


class KMPOraclePolicy(KMPSearchPolicy):
    """Privileged: KMPSearchPolicy with the spiral replaced by the true lateral error e of the held part's
    origin from its target (env.held_pose() - env.target_base_w, x and y: no policy observes it). Once
    blocked, the wanted x, y of eta is the TCP's own minus `gain` e, every step (issue 28, session 15: 0.820
    on PegInsert Factory 4D, eval seed 10000). The yardstick of what the floored null space can do when
    the information is there (tools/ceiling.py). With `lateral_noise_mm` sigma, e is known only to within a bias
    drawn N(0, sigma^2) per axis per episode: the yardstick of an estimate of the hole that good (x, y only: the
    inside test and push_mm still read the true height)."""

    def __init__(self, action_path, params: SearchParams | None = None, gain: float = ORACLE_GAIN,
                 push_mm: float | None = None, inside_mm: float | None = None, mesh_pitch: float | None = None,
                 lateral_noise_mm: float = 0.0, noise_seed: int = 0, lateral_estimate=None):
        super().__init__(action_path, params or ORACLE_PARAMS)
        # an estimate of the lateral error in place of the truth (envs.camera_latent.LatentLateral: the camera's):
        # called once a control step, env -> (E, 2) float64 m, world x, y of the held part minus the fixed tip
        self.lateral_estimate = lateral_estimate
        if not (math.isfinite(lateral_noise_mm) and lateral_noise_mm >= 0):
            raise ValueError(f"KMPOraclePolicy: lateral_noise_mm={lateral_noise_mm!r}; allowed: a finite number >= 0")
        self.gain = float(gain)
        self.push_mm = push_mm
        self.inside_mm = inside_mm
        self.mesh_pitch = mesh_pitch  # rad: steer the yaw too, to the nearest yaw where the held gear meshes
        # The information ceiling: the lateral error it steers by is off by a bias drawn N(0, sigma^2) per axis at
        # each episode's start and held for the episode (as an estimate of the hole with that error would be: the
        # 1 mm observation noise, a camera latent's). Its own generator: the episodes stay the paired ones, and one
        # seed gives the same standard draws at every sigma.
        self.lateral_noise_mm = float(lateral_noise_mm)
        dev = action_path.env.tdev
        self.bias = torch.zeros(action_path.env.num_envs, 2, dtype=torch.float64, device=dev)  # (E, 2) m, world x, y
        self._noise = torch.Generator(device=dev).manual_seed(int(noise_seed))
        ax = [0, 1, 2, 5]
        self.mean4 = self.mean[:, ax]
        self.gain4 = self.path.tables.gain.to(self.mean.device, torch.float64)[:, ax][:, :, ax]
        self.scale4 = self.path.scale[:4].to(torch.float64)

    @classmethod
    def with_floors(cls, tables, env, params: SearchParams | None = None, gain: float = ORACLE_GAIN,
                    push_mm: float | None = None, inside_mm: float | None = None,
                    mesh_pitch: float | None = None, lateral_noise_mm: float = 0.0,
                    noise_seed: int = 0, lateral_estimate=None) -> "KMPOraclePolicy":
        p = params or ORACLE_PARAMS
        return cls(cls.floored_path(tables, env, p), p, gain, push_mm, inside_mm, mesh_pitch, lateral_noise_mm, noise_seed,
                   lateral_estimate)

    def lateral(self, env) -> torch.Tensor:
        """(E, 2) float64 m, world x, y: the held part's origin minus its target (privileged; with lateral_estimate,
        the estimate instead), plus the episode's bias (lateral_noise_mm; zero without)."""
        if self.lateral_estimate is not None:
            return self.lateral_estimate(env).to(torch.float64) + self.bias
        return (env.held_pose()[0] - env.target_base_w)[:, :2].to(torch.float64) + self.bias

    def mesh_yaw(self, env) -> torch.Tensor:
        """(E,) float64 TCP yaw nearest the current one at which the held gear's teeth face the fixed gears' gaps
        (its yaw relative to the fixed part's a multiple of mesh_pitch; privileged: the demonstrator's rule)."""
        from ..rotations import euler_xyz_from_quat

        yaw = euler_xyz_from_quat(env.tcp_pose()[1].double())[2]
        d = euler_xyz_from_quat(env.held_pose()[1].double())[2] - yaw
        off = torch.atan2(torch.sin(d), torch.cos(d))  # the gear's yaw in the hand
        fixed = env.fixed_yaw.double()
        return fixed + torch.round((yaw + off - fixed) / self.mesh_pitch) * self.mesh_pitch - off

    def actions(self, env, obs) -> torch.Tensor:
        """inside_mm (privileged): a part that went in without being blocked (its true height above seated below
        inside_mm) is taken over as if it had dropped while searching: x, y held where they are (less gain (e + b)),
        z `_settled_z` (with push_mm: pressed to the seat; the prior's seat alone holds some parts above it)."""
        if self.lateral_noise_mm > 0:  # (drawn every step, kept where an episode starts: no host read)
            draw = torch.randn(self.bias.shape, generator=self._noise, dtype=torch.float64, device=self.bias.device)
            start = (env.episode_length_buf == 0).unsqueeze(-1)
            self.bias = torch.where(start, 1e-3 * self.lateral_noise_mm * draw, self.bias)
        self._lateral = self.lateral(env)  # once a step (an estimate renders the camera): _search_xy's, the take-over's
        if self.inside_mm is not None:
            n = env.episode_length_buf.long()
            rel = policy_observation(obs)[:, 1:4].to(torch.float64)
            d = (env.held_pose()[0] - env.target_base_w).to(torch.float64)
            new = (n > 0) & (self.since < 0) & (d[:, 2] < 1e-3 * self.inside_mm)
            self.since = torch.where(new, n, self.since)
            self.found |= new
            self.held = torch.where(new.unsqueeze(-1), rel[:, :2] - self.gain * self._lateral, self.held)
        a = super().actions(env, obs)
        if self.mesh_pitch is None:
            return a
        # the yaw as well (4 x 4 solve on x, y, z, yaw): the eta of the TCP turned to the meshing yaw
        from ..kmp.pose import pose_to_eta
        from ..rotations import quat_from_euler_xyz

        want, step, on = self._last
        goal = self.mesh_yaw(env)
        q = quat_from_euler_xyz(torch.full_like(goal, math.pi), torch.zeros_like(goal), goal)
        rz = pose_to_eta(env.tcp_pose()[0].double(), q, env.target_frame_pos_w.double(), env.task.psi_ref)[:, 5]
        zeta = torch.linalg.solve(self.gain4[step], (torch.cat([want, rz.unsqueeze(-1)], -1)
                                                     - self.mean4[step]).unsqueeze(-1)).squeeze(-1)
        a4 = (zeta / self.scale4).clamp(-1.0, 1.0).to(a.dtype)
        return torch.where(on.unsqueeze(-1), a4, a)

    def _search_xy(self, env, rel: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        return rel[:, :2] - self.gain * self._lateral  # privileged (or the estimate's)

    def _settled_z(self, env, rel: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        """push_mm None: the prior's z (issue 28). Else privileged too: the TCP's z minus the held part's true
        height above seated, minus push_mm (the prior's z is its demonstrations' mean seated TCP height, which
        holds a part with a shorter grasp, or under a higher observed target, above the seat)."""
        if self.push_mm is None:
            return m[:, 2:]
        height = (env.held_pose()[0] - env.target_base_w)[:, 2:].to(torch.float64)
        return rel[:, 2:] - height - 1e-3 * self.push_mm


class KMPCentrePolicy(KMPSearchPolicy):
    """Blind, as KMPSearchPolicy (it reads only the observation): once blocked, the spiral is replaced by steering
    the TCP over the observed target frame, the oracle's rule with the TCP's own x, y relative to that frame (the
    observation) in place of the privileged lateral error; once the part drops, z is commanded `push_mm` below the
    prior's z at that step (the search's settled z, lowered). What a proprioceptive policy can do with what it observes: its lateral error is then the target's
    1 mm observation noise and the part's small offset in the hand (tools/ceiling.py `centre`). With `spiral`, the
    search's spiral instead, centred on the observed target rather than where the TCP was blocked
    (`centre_search`)."""

    def __init__(self, action_path, params: SearchParams | None = None, gain: float = ORACLE_GAIN, push_mm: float = 0.0,
                 spiral: bool = False, lateral_estimate=None):
        super().__init__(action_path, params or ORACLE_PARAMS)
        if spiral and lateral_estimate is not None:
            raise ValueError("KMPCentrePolicy: spiral and lateral_estimate exclude each other (the spiral steers by none)")
        self.gain, self.push_mm, self.spiral = float(gain), float(push_mm), bool(spiral)
        self.lateral_estimate = lateral_estimate  # as KMPOraclePolicy's: steer by it instead of the observed target

    @classmethod
    def with_floors(cls, tables, env, params: SearchParams | None = None, gain: float = ORACLE_GAIN,
                    push_mm: float = 0.0, spiral: bool = False, lateral_estimate=None) -> "KMPCentrePolicy":
        p = params or ORACLE_PARAMS
        return cls(cls.floored_path(tables, env, p), p, gain, push_mm, spiral, lateral_estimate)

    def _search_xy(self, env, rel: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        if self.spiral:  # the search's spiral and lead, about x, y = 0 of the observed target frame
            p = self.params
            wanted = spiral_offset((n - self.since).to(torch.float64), p.pitch_mm * 1e-3, p.speed_mm * 1e-3)
            return wanted + p.track * (wanted - rel[:, :2])
        if self.lateral_estimate is not None:  # the camera's estimate of the held part over the hole
            return rel[:, :2] - self.gain * self.lateral_estimate(env).to(torch.float64)
        return rel[:, :2] - self.gain * rel[:, :2]  # the TCP toward x, y = 0 of the observed target frame

    def _settled_z(self, env, rel: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        return m[:, 2:] - 1e-3 * self.push_mm


# The ceiling oracle's press once the part has dropped: 3 mm under its seat, 0.3 N at Factory's Kp (the demonstrator
# pushes 4-6 mm at 250 N/m); issue 28's oracle went back to the prior's z, whose seat does not press (README).
ORACLE_PUSH_MM = 3.0


def _rest_heights() -> dict:
    from ..assets_usd.dimensions import GEAR_HEIGHT, HOLE_DEPTH, THREAD_PITCH

    # the held origin's height above seated when the part's bottom touches the fixed tip (tools/ceiling.py's
    # CeilingGeometry.rest_height): the peg's 25 mm in the hole, the gear's shaft, the nut's 1.5 pitches
    return {"PegInsert": HOLE_DEPTH, "GearMesh": GEAR_HEIGHT, "NutThread": 1.5 * THREAD_PITCH}


REST_HEIGHT = _rest_heights()


def task_search_params(task: str) -> SearchParams:
    """The ceiling's settings for `task` (tools/ceiling.py's centre controllers): issue 28's oracle, its blocked test
    (15 mm above the prior's seat on PegInsert, 0.6 of the 25 mm the peg travels in the hole) scaled to the task's
    rest height, settling at the search's 0.3 mm drop."""
    return replace(ORACLE_PARAMS, settle_mm=0.3, blocked_mm=round(0.6 * 1e3 * REST_HEIGHT[task], 3))


# --kgrl-base: what a = 0 of a KGRL policy stands for. prior: the KMP prior (the thesis). The others are the ceiling's
# controllers with nothing privileged (docs/results/oracle_noise_40), the policy's action added to theirs (a residual,
# as ResiP): centre_search (blind: the search's spiral about the observed target, 0.406 on PegInsert Factory 4D),
# centre_latent (the camera: steering by the near-hole probe's estimate, --vision-probe-obs's input, 0.883).
BASE_CONTROLLERS = ("prior", "centre_search", "centre_latent")


def base_controller(name: str, action_path, task: str, search_speed_mm: float | None = None,
                    search_press_mm: float | None = None):
    """The controller under a KGRL policy's actions for --kgrl-base `name` in `action_path` (its own reach floors:
    the run's), or None for the prior. centre_latent reads the probe's estimate from the env's vision slot (its last
    LATERAL_DIM entries: the env must carry the probe, --vision-probe-obs). search_speed_mm (centre_search only,
    --kgrl-search-speed): the spiral's speed along its arc, mm per control step, in place of SearchParams'; and
    search_press_mm (--kgrl-search-press): z commanded that far below the TCP while it searches."""
    if name not in BASE_CONTROLLERS:
        raise ValueError(f"kgrl base {name!r}; allowed: {', '.join(BASE_CONTROLLERS)}")
    for field, value, top in (("search_speed_mm", search_speed_mm, 1.0), ("search_press_mm", search_press_mm, 10.0)):
        if value is None:
            continue
        if name != "centre_search":
            raise ValueError(f"{field} is the spiral's of kgrl base 'centre_search', not of {name!r}")
        if not (math.isfinite(value) and 0.0 < value <= top):
            raise ValueError(f"{field}={value!r}; allowed: (0, {top:g}] mm")
    if name == "prior":
        return None
    estimate = None
    if name == "centre_latent":
        from .camera_latent import LATERAL_DIM

        env = action_path.env
        if env.cfg.vision_latent_dim <= LATERAL_DIM or env.vision_source is None \
                or getattr(env.vision_source, "probe", None) is None:
            raise ValueError("kgrl base 'centre_latent' steers by the near-hole probe's estimate: it needs the env's "
                             "camera latent with the probe (--vision-probe-obs)")

        def estimate(env):
            return env.current_vision_latent()[:, -LATERAL_DIM:]
    params = task_search_params(task)
    if search_speed_mm is not None:
        params = replace(params, speed_mm=float(search_speed_mm))
    if search_press_mm is not None:
        params = replace(params, press_mm=float(search_press_mm))
    return KMPCentrePolicy(action_path, params, push_mm=ORACLE_PUSH_MM,
                           spiral=name == "centre_search", lateral_estimate=estimate)


class AgentPolicy(Policy):
    """A trained agent acting deterministically (or with samples of its policy, deterministic=False);
    `action_path` is the KGRLActionPath for kgrl methods."""

    def __init__(self, agent, action_path=None, time_obs: bool = True, deterministic: bool = True,
                 obs_history: int = 0):
        self.agent, self.path, self.time_obs, self.deterministic = agent, action_path, time_obs, deterministic
        self.obs_history, self.history = obs_history, None  # envs.history (made at the first step)

    def step(self, env, obs):
        x = kgrl_observation(policy_observation(obs, self.time_obs), self.path)
        x_raw = x
        if self.obs_history:
            if self.history is None:
                from .history import ObservationHistory

                self.history = ObservationHistory(env.num_envs, x.shape[-1], self.agent.action_dim, self.obs_history,
                                                  x.device)
            x = self.history.stack(x, env.step_index)
        a = self.agent.act(x, deterministic=self.deterministic)
        if self.history is not None:
            self.history.push(x_raw, a)
        return self.path.step(a) if self.path is not None else env.step(a)


def evaluate(env, policy, episodes: int, progress: bool = True, video_frames: list | None = None,
             camera=None, video_worlds: int = 4, desc: str = "evaluate") -> dict:
    """Run `episodes` full episodes of all worlds and return the thesis metrics.

    The env is reset first unless it is at the start of an episode. With `video_frames` (a list)
    and `camera` (sim.camera.TaskCamera), each control step appends one frame: the task camera of
    the first `video_worlds` worlds, tiled left to right (uint8 (H, W * n, 3)).
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    resets0, ik0, overflow0 = env.physics_resets_total, env.ik_failures_total, env.contact_overflows_total
    if bool((env.episode_length_buf != 0).any()):
        env.reset()
    obs = env.get_observations()
    per_episode = []
    steps = 0
    t0 = time.perf_counter()
    bar = tqdm(total=episodes * env.max_episode_length, desc=desc, disable=not progress, unit="step", leave=False)
    for _ in range(episodes):
        policy.reset(env)
        while True:
            if video_frames is not None:
                video_frames.append(_camera_frame(env, camera, video_worlds))
            obs, _, _, extras = policy.step(env, obs)
            steps += 1
            bar.update(1)
            if "episode" in extras:
                per_episode.append(extras["episode"])
                break
    bar.close()
    wall = time.perf_counter() - t0

    def mean(key):
        vals = [(e[key], e["num_episodes"]) for e in per_episode if not math.isnan(e[key])]
        return sum(v * w for v, w in vals) / sum(w for _, w in vals) if vals else float("nan")

    return {
        "success_rate": mean("success_rate"),
        "success_rate_any": mean("success_rate_any"),
        "mean_contact_force": mean("mean_contact_force"),
        "peak_contact_force": max((e["peak_contact_force"] for e in per_episode
                                   if not math.isnan(e["peak_contact_force"])), default=float("nan")),
        "mean_peak_contact_force": mean("mean_peak_contact_force"),
        "time_to_first_success_s": mean("time_to_first_success_s"),
        "mean_episode_reward": mean("episode_reward"),
        "episodes": sum(e["num_episodes"] for e in per_episode),
        "env_steps_per_s": steps * env.num_envs / wall,
        "wall_s": wall,
        "physics_resets": env.physics_resets_total - resets0,
        # worlds whose reset IK did not converge (they ran their episode from the last iterate)
        "ik_failures": env.ik_failures_total - ik0,
        # world-substeps whose contacts overflowed the solver's buffers (SimConfig.nconmax / njmax)
        "contact_overflows": env.contact_overflows_total - overflow0,
        "per_episode": per_episode,
    }


def _camera_frame(env, camera, n: int) -> np.ndarray:
    images = camera.render(env.state_0, *env.hand_pose())
    return np.concatenate(list(images[:n]), axis=1)


def write_video(path, frames: list, fps: float = 15.0) -> None:
    """Frames (uint8 (H, W, 3)) to an animated GIF, written atomically, never overwriting."""
    from PIL import Image

    from .._io import atomic_write

    if not frames:
        raise ValueError("no frames to write")
    images = [Image.fromarray(f) for f in frames]
    atomic_write(path, overwrite=False, suffix=".gif",
                 write=lambda f: images[0].save(f, format="GIF", save_all=True, append_images=images[1:],
                                                duration=int(round(1000.0 / fps)), loop=0))
