"""The ceiling of each task (issue 40): privileged and blind controllers on the paired evaluation episodes,
each loss explained.

    python -m vkgrl_newton.tools.ceiling --task PegInsert --episodes-per-world 8 --num-envs 16 \
        --json docs/results/ceiling_40/PegInsert.json

Controllers (Factory, 4D, the same seeded episodes: results.paired.seed_evaluation with the eval seed, as
every run's final evaluation):
- `scripted`: the privileged scripted demonstrator (envs/scripted.py) through `step_pose`;
- `oracle`: the privileged oracle in the floored null space (envs.evaluation.KMPOraclePolicy): steered by the
  true lateral error once blocked, and once the part drops (or is found inside the fixed part without having been
  blocked), pressed ORACLE_PUSH_MM below its true seat; GearMesh: the yaw too, to where the teeth mesh;
- `oracle28`: issue 28's oracle as measured there (after the drop, the prior's z);
- `prior`: the KMP prior, a = 0 (train/evaluate.py --policy kmp_prior);
- `prior_push`: the prior with its seat lowered PRIOR_PUSH_MM (blind; what a demonstration of the push would give);
- `search`: the blind spiral search in the floored null space (--policy kmp_search);
- `centre`: blind too (envs.evaluation.KMPCentrePolicy): the oracle's steering and settle with the TCP's observed x, y
  over the observed target in place of the true lateral error, then pressed ORACLE_PUSH_MM below the prior's z;
- `centre_search`: the same with the search's spiral about the observed target in place of the steering.
- `oracle_latent`: the oracle with the lateral error read from the camera in place of the truth (its z rules stay
  privileged, as with --oracle-lateral-noise-mm): the quick preset's VAE latent through the near-hole probe
  (prepare.vision.load_or_make_probe: an MLP fitted on every near-hole frame of the VAE's own image set), turned into
  the world by the camera's pose (envs.camera_latent.LatentLateral), exactly what --vision-probe-obs gives the
  policy. What a policy that reads this latent as well as the probe does could reach, beside the oracle rows of
  known error.
- `centre_latent`: `centre` steering by that estimate instead of the observed target: nothing privileged at run
  time (the vision controller).
`--perturb-kp-ulp K` moves every OSC gain K float32 ulps up at every episode start (nothing else changes):
how many outcomes a last-bit difference flips (the Intel / AMD question of issue 40).
`--oracle-lateral-noise-mm SIGMA`: the oracle knows the lateral error only to within a per-episode N(0, SIGMA^2) bias
per axis (its draws seeded by --seed, which also seeds the env and the demonstrator) (the information ceiling: SIGMA 1 is Factory's observation noise on the target, a camera latent's error
near the hole is ~0.2-0.6 mm).
`--demos-kp-ulp K` records the prior's demonstrations anew with the same K-ulp move (into --cache-dir, which must
not hold them yet), fits the prior to them and evaluates it: what a last-bit difference in the *recording*, which
each machine does for itself on an empty cache, does to the prior.

Per episode it records the held part's lateral error to its target (xy) and height above seated (final and
minimum), its pose in the TCP frame at the start and the end (offset, tilt), the peak contact force, the
first success, and `classify`'s failure category. `classify` and its thresholds are pure (no torch, no
physics): tests/test_ceiling.py checks them on constructed records.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

from .._io import output_path_error
from ..cli_types import EVAL_SEED_BITS, nonnegative_float, nonnegative_int, positive_int, seed_error
from ..assets_usd.dimensions import (BOLT_CORE_RADIUS, BOLT_TIP_HEIGHT, GEAR_BASE_HEIGHT, GEAR_BORE_APOTHEM, GEAR_HEIGHT,
                                     GEAR_SHAFT_RADIUS, GEAR_TEETH, GEAR_TOOTH_CLEARANCE, HOLE_CHAMFER, HOLE_DEPTH, HOLE_DIAMETER,
                                     NUT_BORE_APOTHEM, PEG_DIAMETER, THREAD_BOLT_TOP, THREAD_CAPSULE_RADIUS,
                                     THREAD_NUT_RADIUS, THREAD_PITCH)

__all__ = ["CATEGORIES", "CeilingGeometry", "CEILING_GEOMETRY", "classify", "SEAT_HAIR", "REST_BAND", "BLOWN_OFFSET",
           "DESCENT", "DESCENT_STEPS", "PRESS_MIN", "CONTROLLERS", "LATENT_CONTROLLERS", "latent_lateral", "pushed_prior",
           "main"]

CATEGORIES = ("success", "seated_then_lost", "seated_but_test_missed", "tilted_or_slipped_in_grasp",
              "time_out_inserting", "held_above_seat", "jammed_in_hole", "jammed_on_chamfer", "time_out_searching",
              "other")
CONTROLLERS = ("scripted", "oracle", "oracle28", "prior", "prior_push", "search", "centre", "centre_search",
               "oracle_latent", "centre_latent")
LATENT_CONTROLLERS = ("oracle_latent", "centre_latent")  # need the camera, the quick VAE and its probe

# A seated part the success test misses "by a hair": MuJoCo's soft contact lets a part sink or stand off by up to
# ~0.2 mm (reference/peg_grip_cpu_facts.md: wall and bottom penetration <= 0.21 mm), so a part within 0.25 mm of
# the test's thresholds (height and centring) is seated as far as this simulation can tell.
SEAT_HAIR = 0.00025  # m
# Resting on the fixed part's entry: the held part within this of the height where it touches the fixed tip
# (the contact gap is 0.5-1 mm: shapes interact within the gap, SimConfig), else it is above it, not touching.
REST_BAND = 0.001  # m
# Still going in when time ran out: the part descended more than this over the episode's last DESCENT_STEPS control
# steps (2/3 s; a part pressed into a jam moves less than the soft contact's ~0.2 mm).
DESCENT = 0.0005  # m
DESCENT_STEPS = 10
# Held above the seat by the command: the controller's final TCP command is less than this below the TCP (Factory's
# Kp 100 N/m: under 0.1 N of push), i.e. it commands the part where it is; a jam has the command well below.
PRESS_MIN = 0.001  # m
# The held part this far from where the grasp put it (TCP frame) has left the hand (the env's blow-up test
# is 0.5 m; a part dragged out of the fingers is gone long before).
BLOWN_OFFSET = 0.010  # m


@dataclass(frozen=True)
class CeilingGeometry:
    """What classify needs of a task, in metres (from assets_usd.dimensions and envs.assembly_env.TASK_GEOMETRY;
    the tool checks the success thresholds against the env's at run time).

    catch: the lateral error of the held part's axis from the target's that the entry still guides in (radial
      clearance plus the lead-in). A part resting on the entry within it and not going in is jammed; beyond it,
      it rests on the face beside the entry. A change of the in-hand offset (TCP frame) beyond it moves a
      part that the controller aims by the TCP out of the entry: tilted or slipped.
    rest_height: the held origin's height above seated when the part's bottom touches the fixed tip.
    entry_depth: the lead-in's depth below the tip: a part lower than rest_height - entry_depth is inside.
    success_z, success_xy: the env's success test (TASK_GEOMETRY).
    """

    catch: float
    rest_height: float
    entry_depth: float
    success_z: float
    success_xy: float


CEILING_GEOMETRY = {
    # the peg: 0.057 mm radial clearance + the 0.75 mm 45-degree chamfer; its bottom at the tip is 25 mm above seated
    "PegInsert": CeilingGeometry(catch=(HOLE_DIAMETER - PEG_DIAMETER) / 2 + HOLE_CHAMFER, rest_height=HOLE_DEPTH,
                                 entry_depth=HOLE_CHAMFER, success_z=0.04 * HOLE_DEPTH, success_xy=0.0025),
    # the gear: 0.2 mm bore play on the shaft + 0.5 mm tooth flank clearance (the teeth must enter the fixed gears'
    # gaps; the shaft's round top leads the bore further, the teeth do not); 20 mm of shaft under the bore
    "GearMesh": CeilingGeometry(catch=(GEAR_BORE_APOTHEM - GEAR_SHAFT_RADIUS) + GEAR_TOOTH_CLEARANCE,
                                rest_height=GEAR_HEIGHT, entry_depth=0.001, success_z=0.05 * GEAR_HEIGHT,
                                success_xy=0.0025),
    # the nut: its thread ridge (r 7.25 mm) against the bolt core (r 7.0 mm, a round top leading it on): 0.25 mm
    # of play + the 1.5 mm lead-in under the tip before the bolt thread starts; seated = 1.5 pitches down
    "NutThread": CeilingGeometry(catch=(THREAD_NUT_RADIUS - THREAD_CAPSULE_RADIUS - BOLT_CORE_RADIUS)
                                 + (BOLT_TIP_HEIGHT - THREAD_BOLT_TOP), rest_height=1.5 * THREAD_PITCH,
                                 entry_depth=BOLT_TIP_HEIGHT - THREAD_BOLT_TOP, success_z=0.375 * THREAD_PITCH,
                                 success_xy=0.0025),
}
_ = (GEAR_BASE_HEIGHT, NUT_BORE_APOTHEM)  # (named in the docs above; the gear origin is its plate's bottom level)


def classify(rec: dict) -> str:
    """The failure category of one episode record (a dict with the tool's per-episode keys, lengths in mm):
    "task", "success" (at the last step), "success_any", "height_final_mm", "lateral_final_mm",
    "offset_change_xy_mm", "blown" (optional). First match wins, in CATEGORIES' order:

    - success: the success test holds at the episode's last step;
    - seated_then_lost: it held at some step, not at the last;
    - other: the world blew up, a value is not finite, or the part left the hand (BLOWN_OFFSET);
    - seated_but_test_missed: height and centring within SEAT_HAIR of the test's thresholds, or within them
      (NutThread: then the yaw condition failed);
    - tilted_or_slipped_in_grasp: the part's origin moved in the TCP frame by more than the catch (x, y), and the
      part was aimed within the catch (its lateral error when it first reached the tip's level, "landing_lateral_mm",
      or at the end): a part pressed onto the face beside the entry also shifts in the self-centring grasp (the
      in-hand noise's +-3 mm, which the grasp settle leaves in part), but there the miss came first;
    - time_out_inserting: below the rest band and still descending (DESCENT over the last DESCENT_STEPS steps);
    - held_above_seat: inside (below the entry's foot), not seated, and the final command presses less than
      PRESS_MIN ("press_final_mm": TCP z - commanded z): the controller holds the part there;
    - jammed_in_hole: below the entry (inside the fixed part), not seated, pressed;
    - jammed_on_chamfer: resting on the entry (within REST_BAND of rest_height, above the entry's foot) with the
      lateral error within the catch: the entry should have guided it in;
    - time_out_searching: the rest: off the entry on the face (lateral error beyond the catch) or still above the
      fixed part when time ran out.
    """
    g = CEILING_GEOMETRY[rec["task"]]
    if rec["success"]:
        return "success"
    if rec["success_any"]:
        return "seated_then_lost"
    h = rec["height_final_mm"] * 1e-3
    lat = rec["lateral_final_mm"] * 1e-3
    slip = rec["offset_change_xy_mm"] * 1e-3
    if rec.get("blown") or not all(math.isfinite(v) for v in (h, lat, slip)) or slip > BLOWN_OFFSET:
        return "other"
    if h < g.success_z + SEAT_HAIR and lat < g.success_xy + SEAT_HAIR:
        return "seated_but_test_missed"
    landing = rec.get("landing_lateral_mm")
    aimed = lat < g.catch or (landing is not None and math.isfinite(landing) and landing * 1e-3 < g.catch)
    if slip > g.catch and aimed:
        return "tilted_or_slipped_in_grasp"
    descent = rec.get("descent_last_mm", 0.0) * 1e-3
    if h < g.rest_height + REST_BAND and descent > DESCENT:
        return "time_out_inserting"
    if h < g.rest_height - g.entry_depth:
        return "held_above_seat" if rec.get("press_final_mm", math.inf) * 1e-3 < PRESS_MIN else "jammed_in_hole"
    if h < g.rest_height + REST_BAND and lat < g.catch:
        return "jammed_on_chamfer"
    return "time_out_searching"


def category_counts(records: list[dict]) -> dict:
    out = {c: 0 for c in CATEGORIES}
    for r in records:
        out[r["category"]] += 1
    return out


# ---------------------------------------------------------------------------------------------------------------
# the measurement (torch, the env: imported inside)


class _Recorder:
    """Per-world episode measurements, read every control step and at the reset that ends the episode."""

    def __init__(self, env, task: str):
        import torch

        self.env, self.task, self.torch = env, task, torch
        self.records: list[dict] = []
        self.round = 0
        self.active = False
        self.blown = torch.zeros(env.num_envs, dtype=torch.bool)
        geo = CEILING_GEOMETRY[task]
        self.rest_height = geo.rest_height

    def _pose(self):
        """(lateral (E,), height above seated (E,), offset of the held origin in the TCP frame (E, 3), tilt (E,)
        of the held part's axis from the TCP's (deg; 0 as grasped), TCP yaw (E,) deg, Factory-wrapped)."""
        torch = self.torch
        from ..rotations import euler_xyz_from_quat, quat_conjugate, quat_mul, quat_rotate

        env = self.env
        held_p, held_q = env.held_pose()
        tcp_p, tcp_q = env.tcp_pose()
        d = (held_p - env.target_base_w).double()
        inv = quat_conjugate(tcp_q)
        offset = quat_rotate(inv, held_p - tcp_p).double()
        rel = quat_mul(inv, held_q)  # the held frame in the TCP's; as grasped: 180 degrees about y
        ez = torch.zeros_like(held_p)
        ez[:, 2] = 1.0
        axis = quat_rotate(rel, ez).double()
        tilt = torch.rad2deg(torch.arccos((-axis[:, 2]).clamp(-1.0, 1.0)))
        yaw = torch.remainder(euler_xyz_from_quat(tcp_q)[2].double(), 2 * math.pi)
        yaw = torch.where(yaw > math.radians(235.0), yaw - 2 * math.pi, yaw)
        return d[:, :2].norm(dim=-1), d[:, 2], offset, tilt, torch.rad2deg(yaw)

    def start(self):
        torch = self.torch
        lat, h, off, tilt, _ = self._pose()
        self.off0, self.tilt0 = off.clone(), tilt.clone()
        self.lat_min, self.h_min = lat.clone(), h.clone()
        self.landing = torch.full_like(lat, float("nan"))
        self.h_hist = [h.clone()]
        self.noise0 = (self.env.target_frame_pos_w - self.env.fixed_tip_w).double().clone()  # observation noise
        self.blown.zero_()
        self.active = True

    def step(self):
        torch = self.torch
        lat, h, _, _, _ = self._pose()
        self.lat_min = torch.minimum(self.lat_min, lat)
        self.h_min = torch.minimum(self.h_min, h)
        self.h_hist = (self.h_hist + [h.clone()])[-(DESCENT_STEPS + 1):]
        first = torch.isnan(self.landing) & (h < self.rest_height + REST_BAND)
        self.landing = torch.where(first, lat, self.landing)

    def before_reset(self, mask):
        """Called by the env's reset of `mask`'s worlds: at a time-out the end of the episode (all worlds)."""
        if not self.active:
            return
        env = self.env
        if not bool(mask.all()):  # a blow-up mid-episode resets those worlds alone
            self.blown |= mask.cpu()
            return
        self.step()
        lat, h, off, tilt, yaw = self._pose()
        tcp_z = env.tcp_pose()[0][:, 2].double()
        press = tcp_z - env.cmd_pos_w[:, 2].double()  # the last control step's command (step_pose)
        descent = self.h_hist[0] - h
        E = env.num_envs
        for w in range(E):
            r = {
                "task": self.task, "round": self.round, "world": w, "episode": self.round * E + w,
                "success": bool(env.success[w]), "success_any": bool(env.success_any[w]),
                "first_success_step": int(env.first_success_step[w]), "steps": int(env.episode_length_buf[w]),
                "lateral_final_mm": 1e3 * float(lat[w]), "lateral_min_mm": 1e3 * float(self.lat_min[w]),
                "landing_lateral_mm": 1e3 * float(self.landing[w]),
                "height_final_mm": 1e3 * float(h[w]), "height_min_mm": 1e3 * float(self.h_min[w]),
                "offset_start_mm": [round(1e3 * float(v), 4) for v in self.off0[w]],
                "offset_end_mm": [round(1e3 * float(v), 4) for v in off[w]],
                "offset_change_xy_mm": 1e3 * float((off[w, :2] - self.off0[w, :2]).norm()),
                "tilt_start_deg": float(self.tilt0[w]), "tilt_end_deg": float(tilt[w]),
                "peak_contact_force_n": float(env.force_peak[w]), "tcp_yaw_final_deg": float(yaw[w]),
                "press_final_mm": 1e3 * float(press[w]), "descent_last_mm": 1e3 * float(descent[w]),
                "obs_noise_mm": [round(1e3 * float(v), 4) for v in self.noise0[w]],
                "blown": bool(self.blown[w]),
            }
            for k, v in list(r.items()):
                if isinstance(v, float):
                    r[k] = round(v, 4) if math.isfinite(v) else None
            r["category"] = classify({k: (float("nan") if v is None else v) for k, v in r.items()})
            self.records.append(r)
        self.active = False
        self.round += 1


def _hook(env, recorder: _Recorder) -> None:
    orig = env._reset_worlds

    def reset_worlds(mask):
        recorder.before_reset(mask)
        orig(mask)

    env._reset_worlds = reset_worlds  # this tool's env only


def run_controller(env, policy, rounds: int, eval_seed: int, task: str, perturb_kp_ulp: int = 0) -> tuple[list, float]:
    """The controller on `rounds` x worlds episodes of the eval seed; (records, wall seconds)."""
    from ..results.paired import seed_evaluation

    rec = _Recorder(env, task)
    _hook(env, rec)
    seed_evaluation(env, eval_seed)
    t0 = time.perf_counter()
    obs = env.get_observations()
    try:
        for k in range(rounds):
            policy.reset(env)
            if perturb_kp_ulp:  # every gain (Kd follows from Kp at reset only)
                env.kp.copy_(ulps_up(env.kp, perturb_kp_ulp))
            rec.start()
            while True:
                obs, _, _, extras = policy.step(env, obs)
                if "episode" in extras:
                    break
                rec.step()
            print(f"  round {k + 1}/{rounds}: success {sum(r['success'] for r in rec.records)}/{len(rec.records)}",
                  flush=True)
    finally:
        del env._reset_worlds  # back to the class's method
    return rec.records, time.perf_counter() - t0


def summary(records: list[dict]) -> dict:
    n = len(records)
    return {"episodes": n, "success": sum(r["success"] for r in records) / n,
            "success_any": sum(r["success_any"] for r in records) / n,
            "n_success": sum(r["success"] for r in records), "n_success_any": sum(r["success_any"] for r in records),
            "categories": category_counts(records)}


def ulps_up(t, k: int):
    """`t` moved `k` float32 ulps up, element by element (nextafter toward +inf, k times)."""
    import torch

    for _ in range(k):
        t = torch.nextafter(t, torch.full_like(t, math.inf))
    return t


def record_perturbed_demos(task: str, cache_dir: str, kp_ulp: int, seed: int = 0, num_demos: int = 16,
                           num_envs: int = 16) -> Path:
    """The prior's demonstrations recorded by prepare.prior's own recorder (same seed, worlds and demonstrator),
    every OSC gain `kp_ulp` float32 ulps up at each world's reset, saved where the prior's cache looks for them."""
    from ..prepare.prior import _record_scripted, demos_path_for

    path = demos_path_for(cache_dir, task, num_demos, seed)
    if path.exists():
        raise FileExistsError(f"{path} exists: --demos-kp-ulp records anew, give it an empty --cache-dir")

    def perturb_gains(env):
        orig = env._set_family_gains

        def set_gains(mask):
            orig(mask)
            env.kp[mask] = ulps_up(env.kp[mask], kp_ulp)

        env._set_family_gains = set_gains  # the recording env only

    _record_scripted(task, path, num_demos, num_envs, "cpu", seed, "primitives", print, progress=False,
                     prepare_env=perturb_gains)
    return path


def build(task: str, num_envs: int, cache_dir: str, seed: int = 0):
    """The Factory 4D env and the prior's tables of train/evaluate.py's KMP baselines (run.evaluate's config)."""
    from ..run.build import build_env, prior_tables
    from ..run.evaluate import evaluation_config

    args = argparse.Namespace(task=task, env="factory", action_dim=4, seed=seed, num_envs=num_envs, no_time_obs=False,
                              geometry=None, demos=None, kmp_reference="gmr", device="cpu", cache_dir=cache_dir,
                              eager_physics=False, policy="kmp_prior")
    cfg = evaluation_config(args, None)
    env = build_env(cfg)
    tables, demos = prior_tables(cfg)
    g, c = env.geometry, CEILING_GEOMETRY[task]
    if abs(g.success_z - c.success_z) > 1e-9 or abs(g.success_xy - c.success_xy) > 1e-9:
        raise RuntimeError(f"{task}: the env's success test ({g.success_z}, {g.success_xy}) is not CEILING_GEOMETRY's")
    return env, tables, demos


def latent_lateral(env, task: str, cache_dir: str, fit: str = "images"):
    """The camera's estimate of the lateral error (envs.camera_latent.LatentLateral) and what it came from: the quick
    preset's VAE of `task` and its near-hole probe (prepare.vision.load_or_make_probe), made on first use as a vision
    run with --vision-probe-obs makes them: the same estimate that option gives the policy."""
    from ..envs.camera_latent import LatentLateral
    from ..prepare.vision import VISION_PRESETS, load_or_make_encoder, load_or_make_probe

    preset = VISION_PRESETS["quick"]
    encoder, info = load_or_make_encoder(task, preset, cache_dir, "cpu")
    probe, path, record = load_or_make_probe(task, preset, cache_dir, encoder, fit=fit)
    return LatentLateral(env, encoder, probe), {**info, "probe": str(path), **record}


def make_controller(name: str, env, tables, task: str, seed: int = 0, oracle_lateral_noise_mm: float = 0.0,
                    lateral_estimate=None):
    # (ORACLE_PUSH_MM: the ceiling oracle's press, 3 mm under the seat; task_search_params: the oracle's settings)
    from ..envs.evaluation import (ORACLE_PUSH_MM, KMPCentrePolicy, KMPOraclePolicy, KMPPriorPolicy, KMPSearchPolicy,
                                   ScriptedPolicy, task_search_params)
    from ..envs.kgrl_action import KGRLActionPath

    if name in LATENT_CONTROLLERS and lateral_estimate is None:
        raise ValueError(f"controller {name!r} needs lateral_estimate (latent_lateral)")

    if name == "scripted":
        return ScriptedPolicy(seed=seed)
    if name == "prior":
        return KMPPriorPolicy(KGRLActionPath(tables, env))
    if name == "search":
        return KMPSearchPolicy.with_floors(tables, env)
    if name == "oracle28":  # issue 28's, as it was measured (its blocked test scaled per task)
        return KMPOraclePolicy.with_floors(tables, env, oracle_params(task))
    if name in ("oracle", "oracle_latent"):  # the ceiling's: settles at the search's 0.3 mm drop, then presses the
        # part ORACLE_PUSH_MM below its seat (privileged z too)
        g = CEILING_GEOMETRY[task]
        pitch = 2 * math.pi / GEAR_TEETH["medium"] if task == "GearMesh" else None  # the teeth decide the yaw
        return KMPOraclePolicy.with_floors(tables, env, task_search_params(task),
                                           push_mm=ORACLE_PUSH_MM, inside_mm=1e3 * (g.rest_height - g.entry_depth),
                                           mesh_pitch=pitch, lateral_noise_mm=oracle_lateral_noise_mm,
                                           noise_seed=seed, lateral_estimate=lateral_estimate if name == "oracle_latent" else None)
    if name in ("centre", "centre_search", "centre_latent"):  # the oracle's settle, x, y from the observation (or
        # the camera's estimate); pressed blind
        return KMPCentrePolicy.with_floors(tables, env, task_search_params(task),
                                           push_mm=ORACLE_PUSH_MM, spiral=name == "centre_search",
                                           lateral_estimate=lateral_estimate if name == "centre_latent" else None)
    if name == "prior_push":
        return KMPPriorPolicy(KGRLActionPath(pushed_prior(tables, PRIOR_PUSH_MM * 1e-3), env))
    raise ValueError(f"controller must be one of {CONTROLLERS}, got {name!r}")


# prior_push: the prior with its z lowered this much once it has arrived at its seat: its demonstrations record the
# TCP's seated pose, not the demonstrator's push (4-6 mm), and the in-hand noise is +-3 mm along the part's axis.
PRIOR_PUSH_MM = 5.0


def pushed_prior(tables, push: float):
    """The prior's tables with m[n] z lowered by `push` (m) from its seat on: kmp.tables.with_seat_press, the
    tables of `--kgrl-seat-press`; what the prior would be had the demonstrations recorded the push."""
    from ..kmp.tables import with_seat_press

    return with_seat_press(tables, push)


def oracle_params(task: str):
    """Issue 28's oracle settings; its blocked test (TCP 15 mm above the prior's seated height on PegInsert,
    0.6 of the 25 mm the peg travels in the hole) scaled to each task's travel (rest_height)."""
    from ..envs.evaluation import ORACLE_PARAMS, task_search_params

    # (the blocked test's one definition: envs.evaluation.task_search_params, whose rest heights are CEILING_GEOMETRY's)
    return replace(task_search_params(task), settle_mm=ORACLE_PARAMS.settle_mm)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vkgrl_newton.tools.ceiling", description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="PegInsert", choices=sorted(CEILING_GEOMETRY))
    ap.add_argument("--controllers", nargs="+", default=list(CONTROLLERS), choices=CONTROLLERS)
    ap.add_argument("--episodes-per-world", type=positive_int, default=8)
    ap.add_argument("--num-envs", type=positive_int, default=16)
    ap.add_argument("--eval-seed", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=0, help="the env's construction and the demonstrator's draws")
    ap.add_argument("--perturb-kp-ulp", type=nonnegative_int, default=0,
                    help="OSC gains this many float32 ulps up (sensitivity)")
    ap.add_argument("--demos-kp-ulp", type=nonnegative_int, default=0,
                    help="record the prior's demonstrations with the OSC gains this many ulps up (into an empty "
                         "--cache-dir) and evaluate the prior fitted to them")
    ap.add_argument("--oracle-lateral-noise-mm", type=nonnegative_float, default=0.0, metavar="SIGMA",
                    help="the oracle steers by the lateral error plus a bias drawn N(0, SIGMA^2) mm per axis at each "
                         "episode's start (seeded by --seed): what an estimate of the hole that good allows")
    ap.add_argument("--probe-fit", default="images", choices=("images", "closed_loop"),
                    help="the latent controllers: the near-hole probe's fit (train/run.py's --vision-probe-fit)")
    ap.add_argument("--cache-dir", default="runs/cache")
    ap.add_argument("--json", type=Path, required=True,
                    help="output, a new file (never overwritten; rewritten after each controller of this run)")
    args = ap.parse_args(argv)
    for why in (seed_error("--seed", args.seed), seed_error("--eval-seed", args.eval_seed, EVAL_SEED_BITS),
                output_path_error(args.json, "--json")):  # (checked before the controllers run for minutes)
        if why:
            ap.error(why)

    from ..runtime import configure_warp, cpu_model, processor_name

    configure_warp()
    import torch

    from .._io import atomic_write_text, strict_json

    torch.set_num_threads(1)
    if args.demos_kp_ulp:
        try:
            record_perturbed_demos(args.task, args.cache_dir, args.demos_kp_ulp, args.seed)
        except FileExistsError as e:  # (checked before recording)
            ap.error(f"--demos-kp-ulp {args.demos_kp_ulp}: {e}")
    env, tables, demos = build(args.task, args.num_envs, args.cache_dir, args.seed)
    cpu = cpu_model()
    out = {"task": args.task, "env": "factory", "action_dim": 4, "num_envs": args.num_envs,
           "episodes_per_world": args.episodes_per_world, "eval_seed": args.eval_seed, "seed": args.seed,
           "perturb_kp_ulp": args.perturb_kp_ulp, "demos_kp_ulp": args.demos_kp_ulp,
           "oracle_lateral_noise_mm": args.oracle_lateral_noise_mm, "demos": str(demos), "cpu": cpu,
           "processor": processor_name(),
           "command": "python -m "
           "vkgrl_newton.tools.ceiling " + " ".join(sys.argv[1:] if argv is None else argv),
           "thresholds_mm": {"catch": 1e3 * CEILING_GEOMETRY[args.task].catch,
                             "rest_height": 1e3 * CEILING_GEOMETRY[args.task].rest_height,
                             "entry_depth": 1e3 * CEILING_GEOMETRY[args.task].entry_depth,
                             "seat_hair": 1e3 * SEAT_HAIR, "rest_band": 1e3 * REST_BAND},
           "controllers": {}}
    estimate = None
    if set(args.controllers) & set(LATENT_CONTROLLERS):
        estimate, out["latent"] = latent_lateral(env, args.task, args.cache_dir, args.probe_fit)
        out["probe_fit"] = args.probe_fit
        print(f"{args.task}: the camera's lateral estimate, probe held-out RMSE {out['latent']['held_out_rmse_mm']} mm "
              f"(image axes, {out['latent']['held_out_frames']} frames)", flush=True)
    for name in args.controllers:
        print(f"{args.task} {name}", flush=True)
        policy = make_controller(name, env, tables, args.task, args.seed, args.oracle_lateral_noise_mm,
                                 estimate if name in LATENT_CONTROLLERS else None)
        if estimate is not None:
            estimate.reset_score()  # (each controller's own episodes)
        records, wall = run_controller(env, policy, args.episodes_per_world, args.eval_seed, args.task,
                                       args.perturb_kp_ulp)
        out["controllers"][name] = {**summary(records), "wall_s": round(wall, 1), "records": records}
        if name in LATENT_CONTROLLERS:  # how good the estimate was on the near-hole frames of these episodes (world)
            out["controllers"][name]["estimate_rmse_mm"] = estimate.rmse_mm()
        if name == "oracle":
            import dataclasses

            out["controllers"][name]["params"] = dataclasses.asdict(policy.params)
        s = out["controllers"][name]
        print(f"{args.task} {name}: success {s['n_success']}/{s['episodes']} (any {s['n_success_any']}), "
              f"{s['categories']}, {wall:.0f} s", flush=True)
        atomic_write_text(args.json, strict_json(out, indent=1) + "\n", overwrite=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
