"""The physics stepper: one control step of the assembly scene, eager or as one captured Warp graph.

One physics step (1/120 s) = `substeps` x (Newton's Jacobian and mass matrix of the robots, the
OSC kernel, Newton's collision pipeline, the solver step), then the contact-force reduction on
the gripper group. One control step = `decimation` physics steps; on the SAC path each physics
step first moves the TCP command by the smoothed action (kernels/delta_command.py), on the pose
path (KGRL) the command is held.

Graph mode (`graph=True`, the default of EnvConfig): a control step is recorded once with
`wp.ScopedCapture` (Warp's CPU capture on a CPU, replayed in C++; a CUDA graph on CUDA, on Warp's
stream, which waits for torch's stream before each run and torch's for it after, so the torch work
before and after stays ordered: not yet run on a GPU) and replayed with
`wp.capture_launch`. The first unit of each kind (a control step of the SAC path, one of the pose
path, a settle step) runs eagerly, so kernels compile and any one-time set-up of the solver or the
pipeline happens outside the recording; recording executes nothing, the replays do. A capture
holds raw pointers, so:
- a graph records an even number of state swaps (decimation x substeps; a settle graph takes two
  physics steps when substeps is odd), so every replay starts from `state_0`'s buffers;
- before each replay the stepper compares the pointers of every Warp array it launches on (states,
  control, contacts, its buffers, the solver's model and data) with those at capture time and
  captures again when one was reallocated (`captures` counts them);
- no host read, torch op or Python side effect happens inside: the env does those before and
  after (`AssemblyEnv.step`).
Eager mode runs the very same launches one by one; it is the tests' reference (bitwise equal) and
the only mode with a per-stage time split (`profile`).

The stepper knows no rewards, tasks or episodes: it owns the simulation objects and the buffers
its kernels read and write (the env holds torch views of the same memory).
"""

from __future__ import annotations

import dataclasses
import time

import torch
import warp as wp

import newton

from ..kernels.contact_forces import contact_force_reduce, contact_force_update
from ..kernels.delta_command import delta_command
from ..kernels.osc import osc_torques
from .scene import Scene, make_solver

__all__ = ["PhysicsStepper", "ControllerBuffers", "ForceBuffers", "ActionBuffers", "PROFILE_STAGES"]

PROFILE_STAGES = ("kinematics_osc", "collision", "solver", "contact_forces")


@dataclasses.dataclass
class ControllerBuffers:
    """What the OSC kernel reads (command, gains, dead zone, posture) and writes (TCP state, wrench), per world."""

    cmd_pos_w: wp.array  # (E,) vec3
    cmd_quat_w: wp.array  # (E,) quat xyzw
    kp: wp.array  # (E,) vec6
    kd: wp.array  # (E,) vec6
    dead_zone: wp.array  # (E,) vec6
    q_null: wp.array  # (7,) float32
    torque_limit: wp.array  # (7,) float32
    kp_null: float
    kd_null: float
    tcp_pos_w: wp.array  # (E,) vec3, out
    tcp_quat_w: wp.array  # (E,) quat, out
    tcp_twist_w: wp.array  # (E,) spatial_vector, out
    wrench_w: wp.array  # (E,) vec6, out


@dataclasses.dataclass
class ForceBuffers:
    """Contact-force accumulators on the gripper group (kernels/contact_forces.py), per world."""

    interaction_force_w: wp.array  # (E,) vec3
    force_smoothed_w: wp.array  # (E,) vec3
    force_norm_sum: wp.array  # (E,) float32
    force_peak: wp.array  # (E,) float32
    force_count: wp.array  # (E,) int32


@dataclasses.dataclass
class ActionBuffers:
    """Inputs of Factory's delta-pose mapping (kernels/delta_command.py) and its first command of the step."""

    actions: wp.array  # (E, D) float32, the smoothed action
    pos_scale: wp.array  # (E,) vec3
    rot_scale: wp.array  # (E,) vec3
    target_frame_pos_w: wp.array  # (E,) vec3
    first_pos_w: wp.array  # (E,) vec3, out
    first_quat_w: wp.array  # (E,) quat, out
    pos_bound: float
    max_tilt: float
    unidirectional_yaw: bool


@wp.kernel
def overflow_accumulate_kernel(
    overflow: wp.array(dtype=wp.int32),  # (E,) SolverMuJoCo's overflow bitmask of the last substep
    overflow_substeps: wp.array(dtype=wp.int32),  # (E,) substeps with any overflow bit, accumulated
    overflow_bits: wp.array(dtype=wp.int32),  # (E,) OR of every bit seen
):
    """Count a world's substeps whose contacts or constraint rows overflowed their buffers (MuJoCo-Warp's
    nconmax / njmax, Newton's rigid_contact_max): the solver resets its bitmask every step, this keeps it."""
    w = wp.tid()
    bits = overflow[w]
    if bits != 0:
        overflow_substeps[w] = overflow_substeps[w] + 1
        overflow_bits[w] = overflow_bits[w] | bits


class PhysicsStepper:
    """Owns the two states, control, solver, collision pipeline, contacts and Jacobian / mass-matrix
    buffers of a scene; runs physics steps and control steps (module docstring)."""

    def __init__(self, scene: Scene, controller: ControllerBuffers, forces: ForceBuffers,
                 actions: ActionBuffers | None = None, graph: bool = True):
        self.scene, self.model, self.device = scene, scene.model, scene.device
        self.substeps, self.substep_dt = scene.config.substeps, scene.config.substep_dt
        self.decimation = scene.config.decimation
        self.collide_every_substep = scene.config.collide_every_substep
        self.controller, self.forces, self.actions = controller, forces, actions
        self.graph = bool(graph)
        self.solver, self.pipeline = make_solver(scene)
        self.contacts = self.pipeline.contacts()
        kinds = {newton.solvers.SolverBase.ObservableKind.CONTACT_F}
        overflow_kind = getattr(getattr(self.solver, "ObservableKind", None), "OVERFLOW", None)
        if overflow_kind is not None and overflow_kind in getattr(self.solver, "SUPPORTED_OBSERVABLES", ()):
            kinds.add(overflow_kind)  # MuJoCo-Warp reports capacity overflows per world and substep
        self.observables = self.solver.observables(kinds, contacts=self.contacts)
        E = scene.num_worlds
        self.overflow_substeps = wp.zeros(E, dtype=wp.int32, device=self.device)
        self.overflow_bits = wp.zeros(E, dtype=wp.int32, device=self.device)
        self.state_0, self.state_1 = self.model.state(), self.model.state()
        self.control = self.model.control()
        m, E = self.model, scene.num_worlds
        self.jacobian = wp.zeros((m.articulation_count, 6 * m.max_joints_per_articulation, m.max_dofs_per_articulation),
                                 dtype=wp.float32, device=self.device)
        self.mass_matrix = wp.zeros((m.articulation_count, m.max_dofs_per_articulation, m.max_dofs_per_articulation),
                                    dtype=wp.float32, device=self.device)
        self.joint_f_2d = self.control.joint_f.reshape((E, scene.dofs_per_world))
        # Newton's temporaries, allocated once (else every call allocates them inside the capture)
        self.joint_S_s = wp.zeros(m.joint_dof_count, dtype=wp.spatial_vector, device=self.device)
        self.body_I_s = wp.zeros(m.body_count, dtype=wp.spatial_matrix, device=self.device)
        # graphs by kind ("delta", "pose", "settle"), each with the array pointers it was captured on
        # and the links that reached them (_walk)
        self._graphs: dict[str, tuple[object, tuple]] = {}
        self.captures = 0  # how many graphs were recorded (first replay and reallocations)
        self._warm: set[str] = set()  # kinds whose first unit already ran eagerly
        # opt-in per-stage time split of eager steps: name -> seconds (None costs nothing)
        self.profile: dict[str, float] | None = None
        self._tick_t = 0.0
        # CUDA: the physics runs on Warp's stream of the device (a graph cannot be captured on torch's
        # legacy default stream); each run waits for the torch work queued before it and torch's
        # stream waits for the run, so torch reads and writes of the shared buffers stay ordered
        self._cuda = wp.get_device(self.device).is_cuda
        if self._cuda:
            self._torch_device = wp.device_to_torch(self.device)

    # ------------------------------------------------------------------------------------------
    # one physics step, eager (the reference; also what a graph records)

    def physics_step(self, collect_forces: bool = True) -> None:
        """One 1/120 s physics step: `substeps` x (Jacobian, mass matrix, OSC, collision, solver),
        then (collect_forces) the contact reduction. Swaps the states once per substep."""
        sc, m, c = self.scene, self.model, self.controller
        self._tick(None)
        for k in range(self.substeps):
            s0 = self.state_0
            newton.eval_jacobian(m, s0, self.jacobian, joint_S_s=self.joint_S_s, mask=sc.robot_articulation_mask)
            newton.eval_mass_matrix(m, s0, self.mass_matrix, J=self.jacobian, body_I_s=self.body_I_s,
                                    joint_S_s=self.joint_S_s, mask=sc.robot_articulation_mask)
            osc_torques(
                jacobian=self.jacobian, mass_matrix=self.mass_matrix, robot_articulation=sc.robot_articulation,
                hand_link=sc.hand_link, arm_dof_start=0, body_q=s0.body_q, body_qd=s0.body_qd, body_com=m.body_com,
                hand_body=sc.hand_body, tcp_offset_hand=sc.tcp_offset_hand,
                joint_q=s0.joint_q.reshape((sc.num_worlds, sc.coords_per_world)),
                joint_qd=s0.joint_qd.reshape((sc.num_worlds, sc.dofs_per_world)), arm_q_start=0, arm_qd_start=0,
                target_pos_w=c.cmd_pos_w, target_quat_w=c.cmd_quat_w, kp=c.kp, kd=c.kd, dead_zone=c.dead_zone,
                q_null=c.q_null, kp_null=c.kp_null, kd_null=c.kd_null, torque_limit=c.torque_limit,
                tcp_pos_w=c.tcp_pos_w, tcp_quat_w=c.tcp_quat_w, tcp_twist_w=c.tcp_twist_w, wrench_w=c.wrench_w,
                joint_f=self.joint_f_2d,
            )
            self._tick("kinematics_osc")
            if k == 0 or self.collide_every_substep:
                self.pipeline.collide(s0, self.contacts)
                self._tick("collision")
            self.solver.step(s0, self.state_1, self.control, self.contacts, self.substep_dt,
                             observables=self.observables)
            overflow = getattr(self.observables, "overflow", None)
            if overflow is not None:
                wp.launch(overflow_accumulate_kernel, dim=sc.num_worlds, inputs=[overflow],
                          outputs=[self.overflow_substeps, self.overflow_bits], device=self.device)
            self._tick("solver")
            self.state_0, self.state_1 = self.state_1, self.state_0
        if collect_forces:
            f = self.forces
            contact_force_reduce(
                contact_count=self.contacts.rigid_contact_count, contact_shape0=self.contacts.rigid_contact_shape0,
                contact_shape1=self.contacts.rigid_contact_shape1, contact_f=self.observables.contact_f,
                shape_group=sc.gripper_group, shape_world=m.shape_world, interaction_force_w=f.interaction_force_w)
            contact_force_update(
                interaction_force_w=f.interaction_force_w, force_smoothed_w=f.force_smoothed_w,
                force_norm_sum=f.force_norm_sum, force_sample_count=f.force_count, force_peak=f.force_peak)
            self._tick("contact_forces")

    def delta_command(self, record_first: bool) -> None:
        """Move the TCP command by the smoothed action from the current TCP pose (Factory's mapping)."""
        a, sc = self.actions, self.scene
        if a is None:
            raise RuntimeError("this stepper was built without ActionBuffers: the delta-action path is off")
        delta_command(
            body_q=self.state_0.body_q, hand_body=sc.hand_body, tcp_offset_hand=sc.tcp_offset_hand,
            actions=a.actions, pos_scale=a.pos_scale, rot_scale=a.rot_scale, target_frame_pos_w=a.target_frame_pos_w,
            pos_bound=a.pos_bound, max_tilt=a.max_tilt, unidirectional_yaw=a.unidirectional_yaw,
            record_first=record_first, cmd_pos_w=self.controller.cmd_pos_w, cmd_quat_w=self.controller.cmd_quat_w,
            first_pos_w=a.first_pos_w, first_quat_w=a.first_quat_w)

    # ------------------------------------------------------------------------------------------
    # control steps and settles, eager or replayed

    def control_step(self, delta_actions: bool) -> None:
        """`decimation` physics steps with contact forces; with `delta_actions` each starts with
        the delta-command kernel (the first records its command), else the command is held."""
        self._run("delta" if delta_actions else "pose", lambda: self._control_step_eager(delta_actions), 1)

    def settle(self, physics_steps: int) -> None:
        """`physics_steps` physics steps without contact forces (the reset's grip settle)."""
        per_graph = 1 if self.substeps % 2 == 0 else 2  # an even number of state swaps per graph
        replays, rest = divmod(physics_steps, per_graph)
        if replays:
            self._run("settle", lambda: [self.physics_step(collect_forces=False) for _ in range(per_graph)], replays)
        for _ in range(rest):
            self.physics_step(collect_forces=False)

    def _control_step_eager(self, delta_actions: bool) -> None:
        for i in range(self.decimation):
            if delta_actions:
                self.delta_command(record_first=i == 0)
            self.physics_step()

    def _run(self, kind: str, body, replays: int) -> None:
        if not self._cuda:
            self._run_on_stream(kind, body, replays)
            return
        warp_stream = wp.get_stream(self.device)  # the current one: a caller's wp.ScopedStream is honoured
        torch_stream = torch.cuda.current_stream(self._torch_device)
        warp_stream.wait_stream(wp.stream_from_torch(torch_stream))
        self._run_on_stream(kind, body, replays)
        torch_stream.wait_stream(wp.stream_to_torch(warp_stream))

    def _run_on_stream(self, kind: str, body, replays: int) -> None:
        if not self.graph or self.profile is not None:
            for _ in range(replays):
                body()
            return
        if kind not in self._warm:
            # the first unit runs eagerly: kernels compile and any one-time work of the solver or the
            # pipeline (lazy allocations, first-step set-up) happens outside the recording
            self._warm.add(kind)
            body()
            replays -= 1
            if replays == 0:
                return
        # after the eager unit (it may have allocated lazily). Per replay the check is cheap: the links
        # of the last walk still hold the same objects; only if one changed is the walk redone and
        # the arrays' pointers compared (an object replaced by another holding the same arrays keeps
        # the graph)
        entry = self._graphs.get(kind)
        if entry is not None and not self._unchanged(entry[2]):
            pointers, links = self._walk()
            entry = self._graphs[kind] = (entry[0], entry[1], links) if pointers == entry[1] else None
        if entry is None:
            pointers, links = self._walk()
            with wp.ScopedDevice(self.device):
                with wp.ScopedCapture(device=self.device) as cap:
                    body()
            self.captures += 1
            entry = self._graphs[kind] = (cap.graph, pointers, links)
            # recording executes nothing (a CUDA graph and Warp's CPU capture alike): every replay follows
        for _ in range(replays):
            wp.capture_launch(entry[0])

    _HOLDERS = ("state_0", "state_1", "control", "contacts", "observables", "controller", "forces", "actions",
                "jacobian", "mass_matrix", "joint_f_2d", "joint_S_s", "body_I_s", "overflow_substeps",
                "overflow_bits", "model", "pipeline", "solver")

    def _walk(self) -> tuple[tuple, list]:
        """The device pointers of the Warp arrays a step launches on, in a fixed order: those held by
        the states, control, contacts, observables, the stepper's buffers, the model, the collision
        pipeline and the solver (MuJoCo-Warp's model and data included), walked recursively through
        their attributes, lists and dicts (depth 4, each object once); and every (container, key,
        child) link the walk went through, for `_unchanged`."""
        ptrs, links = [], []
        seen: set[int] = set()

        def walk(obj, depth: int) -> None:
            if isinstance(obj, wp.array):
                ptrs.append(obj.ptr)
                return
            if id(obj) in seen or depth == 0 or obj is None or isinstance(obj, (str, bytes, int, float, torch.Tensor)):
                return
            seen.add(id(obj))
            if isinstance(obj, (list, tuple)):
                items = enumerate(obj)
            elif isinstance(obj, dict):
                items = obj.items()
            elif hasattr(obj, "__dict__"):
                items = vars(obj).items()
            else:
                return
            for key, child in items:
                if isinstance(child, wp.array) or hasattr(child, "__dict__") or isinstance(child, (list, dict)):
                    links.append((obj, key, child))
                walk(child, depth - 1)

        for name in self._HOLDERS:
            child = getattr(self, name)
            links.append((self, name, child))
            walk(child, 4)
        return tuple(ptrs), links

    @staticmethod
    def _unchanged(links: list) -> bool:
        """Every link still holds the very object it held (a cheap identity check; arrays never move)."""
        for container, key, child in links:
            now = container[key] if isinstance(container, (list, tuple, dict)) else getattr(container, key, None)
            if now is not child:
                return False
        return True

    def invalidate(self) -> None:
        """Drop the recorded graphs (the next step captures again)."""
        self._graphs.clear()

    # ------------------------------------------------------------------------------------------
    # diagnostics

    def _tick(self, stage: str | None) -> None:
        if self.profile is None:
            return
        wp.synchronize_device(self.device)
        now = time.perf_counter()
        if stage is not None:
            self.profile[stage] = self.profile.get(stage, 0.0) + now - self._tick_t
        self._tick_t = now
