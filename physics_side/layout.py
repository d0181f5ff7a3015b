"""Model building for the physics world: pools of slots, the pooled spec, compile, index tables.

A *layout* is one compiled world: the ground plus, per pool (one agent model bucket),
``capacity`` pre-allocated slots, parked far from the network and asleep, in each of
``shards`` simulations of the same model (``mujoco.batch.Batch``). ``compile_layout``
builds it; ``SlotTables`` maps every slot number (0..G-1, pool by pool, slot by slot,
shard by shard) to its flat indices in the batch state and its physical parameters.
The per-tick world (``world.PhysicsWorld``) only reads these tables.

Slot ``i`` of pool ``p`` in shard ``s`` has the slot number ``base[p] + i * shards + s``;
``carry_over`` maps slots of an old layout to the same (pool, shard, index) in a new one,
so live agents keep their state when pools grow.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, fields
from typing import NamedTuple

import mujoco
import mujoco.batch
import numpy as np

from physics_side import models as M

log = logging.getLogger(__name__)

# Parking lot where unused slots sleep. Far from any SUMO network (whose coordinates are
# >= 0 after netconvert's offset): each pool parks on its own line along +x, slots
# PARK_SPACING apart, so parked agents never touch.
PARK_ORIGIN = (-50_000.0, -50_000.0)
PARK_SPACING = 25.0  # [m] > the longest bucket (18 m bus)
# Compiling is superlinear in the trees of one model (MuJoCo's compile-time constants,
# e.g. each body's inverse weight, cost O(nbody * nv)): 256 car slots compile in ~0.2 s
# of CPU, 1,024 in ~3 s, 4,096 not in a minute. Worlds beyond this many slots per
# simulation use more simulations of the same model instead (one compile).
SLOTS_PER_SIM = 256
# Arena per simulation: measured ~100 B * slots^2 with every slot awake on the ground
# (26 MB at 512 slots); twice that plus a floor. MuJoCo's default heuristic reserved
# 1.8 GB for 512 slots.
ARENA_FLOOR = 16 << 20  # [bytes]
ARENA_PER_SLOT2 = 200  # [bytes / slot^2]

# Coordinates of the slots' joints in the batch state (``world`` reads them by these widths).
FREE_NQ = 7  # a vehicle's freejoint qpos: position (3) and unit quaternion w, x, y, z (4)
FREE_NV = 6  # its qvel: linear velocity (3, world frame), angular velocity (3, body frame)
FREE_POS = 3  # where the quaternion starts in a freejoint's qpos (after the position)
FREE_QUAT = 4  # quaternion components w, x, y, z
FREE_WZ = 5  # the angular velocity about the body's z axis in a freejoint's qvel
PED_NQ = 3  # a pedestrian's qpos (and qvel): slide x, slide y, yaw hinge
STEER_COLUMNS = 2  # left and right steer columns (a bicycle's one steer twice)
BRAKE_COLUMNS = 4  # spin / brake columns fl, fr, rl, rr (a two-wheeler's wheels twice each)
CFRC_WIDTH = 6  # cfrc_ext per body: torque (3), then force (3)
CFRC_FORCE = 3  # where the force starts in a body's cfrc_ext

# MuJoCo keeps a qpos address per joint, not a width: a free joint holds a position and a
# quaternion, a ball joint a quaternion, a slide or hinge joint one coordinate. Indexed by
# ``mjtJoint`` (0..3).
_QPOS_PER_JOINT = {
    mujoco.mjtJoint.mjJNT_FREE: FREE_NQ, mujoco.mjtJoint.mjJNT_BALL: 4,
    mujoco.mjtJoint.mjJNT_SLIDE: 1, mujoco.mjtJoint.mjJNT_HINGE: 1,
}
_JOINT_NQ = np.array([n for _, n in sorted((int(t), n) for t, n in _QPOS_PER_JOINT.items())])


class _KindLayout(NamedTuple):
    """Names of the template joints and actuators behind each slot-table column of one kind of
    model (``models.car_template`` / ``bike_template`` / ``ped_template``); None: no such
    element, the column holds -1."""

    actuators: tuple[str, ...]
    """The slot's actuators in model order (the first is the slot's first actuator)."""
    steer_joints: tuple[str | None, ...]
    """Left, right steer hinge."""
    spin_joints: tuple[str, ...]
    """Spin hinge of each brake column fl, fr, rl, rr (pedestrians: none)."""
    steer_act: tuple[str | None, ...]
    """Left, right steer actuator."""
    drive_act: str
    """Drive (pedestrian: force x)."""
    aux_act: tuple[str | None, ...]
    """Bicycle: stabiliser; pedestrian: force y, torque z."""


_KINDS = {
    M.KIND_CAR: _KindLayout(
        actuators=("steer_fl", "steer_fr", "drive"), steer_joints=("steer_fl", "steer_fr"),
        spin_joints=("spin_fl", "spin_fr", "spin_rl", "spin_rr"), steer_act=("steer_fl", "steer_fr"),
        drive_act="drive", aux_act=(None, None)),
    M.KIND_BIKE: _KindLayout(
        actuators=("steer", "drive", "stab"), steer_joints=("steer_f", "steer_f"),
        spin_joints=("spin_f", "spin_f", "spin_r", "spin_r"), steer_act=("steer", "steer"),
        drive_act="drive", aux_act=("stab", None)),
    M.KIND_PED: _KindLayout(
        actuators=("fx", "fy", "tz"), steer_joints=(None, None), spin_joints=(),
        steer_act=(None, None), drive_act="fx", aux_act=("fy", "tz")),
}
_REAR_STEER = ("steer_rl", "steer_rr")  # a car's rear steer hinges and their actuators (after the drive)


@dataclass(frozen=True)
class Pool:
    """One bucket's slots in every shard's model."""

    index: int
    """Stable pool number (parking row block)."""
    spec: M.AgentSpec
    capacity: int
    """Slots per shard."""


def park_position(pool_index: int, slot: int | np.ndarray) -> tuple:
    """Parking spot [m] of slot ``slot`` of pool ``pool_index`` (stable when pools grow)."""
    x = PARK_ORIGIN[0] + np.asarray(slot, np.float64) * PARK_SPACING
    y = np.full_like(x, PARK_ORIGIN[1] - pool_index * PARK_SPACING)
    if np.ndim(x) == 0:
        return float(x), float(y)
    return x, y


def slot_prefix(pool_name: str, capacity: int, i: int) -> str:
    """Name prefix of slot ``i`` of a pool of ``capacity`` slots (see ``build_world_spec``)."""
    start = 0
    for k in range(capacity.bit_length() - 1, -1, -1):
        if capacity >> k & 1:
            if i < start + (1 << k):
                path = format(i - start, f"0{k}b") if k else ""
                return f"{pool_name}#{k}/" + path.replace("0", "a").replace("1", "b")
            start += 1 << k
    raise IndexError(f"slot {i} of a pool of {capacity}")


def _blocks(template: mujoco.MjSpec, capacity: int) -> list[mujoco.MjSpec]:
    """Specs of 1, 2, 4, ... slots up to ``capacity``, each two copies of the previous one.

    One attach per doubling copies the block once, so ``n`` slots cost O(n) (an attach
    per slot into the growing world is O(world) each: a 1,024-slot pool took ~16 s).
    """
    blocks = [template]
    while 1 << len(blocks) <= capacity:
        prev = blocks[-1]
        half = 1 << (len(blocks) - 1)
        s = mujoco.MjSpec()
        s.compiler.degree = False
        s.copy_during_attach = True
        s.attach(prev, frame=s.worldbody.add_frame(pos=[0.0, 0.0, 0.0]), prefix="a")
        s.attach(prev, frame=s.worldbody.add_frame(pos=[half * PARK_SPACING, 0.0, 0.0]), prefix="b")
        blocks.append(s)
    return blocks


def build_world_spec(pools: list[Pool], timestep: float) -> mujoco.MjSpec:
    """The world spec: ground plus ``capacity`` parked, initially sleeping copies per pool.

    A pool of ``capacity`` slots is the blocks of its binary digits (2^k slots each, from
    ``_blocks``) side by side; slot ``i`` is the subtree named
    ``slot_prefix(name, capacity, i) + "agent"``, its slots in order of ``i``.
    """
    s = mujoco.MjSpec()
    s.copy_during_attach = True
    M.set_world_options(s, timestep)
    M.add_ground(s)
    for p in pools:
        if p.capacity == 0:
            continue
        t = M.template(p.spec)
        # Parked slots start asleep: no cost until spawned (the world wakes them by
        # switching their tree's sleep policy to "never").
        t.body("agent").sleep = mujoco.mjtSleepPolicy.mjSLEEP_INIT
        blocks = _blocks(t, p.capacity)
        x0, y0 = park_position(p.index, 0)
        start = 0
        for k in range(p.capacity.bit_length() - 1, -1, -1):
            if p.capacity >> k & 1:
                f = s.worldbody.add_frame(pos=[x0 + start * PARK_SPACING, y0, 0.0])
                s.attach(blocks[k], frame=f, prefix=f"{p.spec.name}#{k}/")
                start += 1 << k
    s.memory = arena_bytes(sum(p.capacity for p in pools))
    return s


def arena_bytes(slots: int) -> int:
    """Arena size [bytes] of one simulation of ``slots`` slots (see ``ARENA_PER_SLOT2``)."""
    return ARENA_FLOOR + ARENA_PER_SLOT2 * slots * slots


@dataclass
class SlotTables:
    """Per-slot index tables of one compiled layout (every column has length G = total slots).

    Flat indices point into the batch arrays of all shards (``Layout.state``, the expanded
    ``dof_frictionloss`` / ``tree_sleep_policy``, ``cfrc_ext``); -1 where a kind has no
    such element.
    """

    pool: np.ndarray
    shard: np.ndarray
    index: np.ndarray
    """Slot number inside its pool (same in every shard)."""
    kind: np.ndarray
    """models.KIND_CAR / KIND_BIKE / KIND_PED."""
    cls: np.ndarray
    """AgentClass of the pool's model."""
    qpos: np.ndarray
    """Flat state index of the slot's first qpos."""
    nq: np.ndarray
    qvel: np.ndarray
    """Flat state index of the first dof."""
    nv: np.ndarray
    ctrl: np.ndarray
    """Flat state index of the first actuator."""
    nu: np.ndarray
    qpos0: np.ndarray
    """Model index of the first qpos (for ``model.qpos0``)."""
    dof: np.ndarray
    """Model dof address of the first dof."""
    steer_q: np.ndarray
    """(G, 2) flat qpos index of left/right steer (bicycle: the same twice; pedestrian: -1)."""
    steer_u: np.ndarray
    """(G, 2) flat ctrl index of left/right steer."""
    drive_u: np.ndarray
    """Flat ctrl index of the drive (pedestrian: force x)."""
    aux_u: np.ndarray
    """(G, 2) bicycle: stabiliser, -1; pedestrian: force y, torque z; car: -1."""
    spin_fl: np.ndarray
    """(G, 4) flat index into the expanded dof_frictionloss of the brake columns."""
    spin_v: np.ndarray
    """(G, 4) flat qvel index of the spin dofs."""
    brake_share: np.ndarray
    """(G, 4) share of the total brake torque per brake column."""
    drive_share: np.ndarray
    """(G, 4) share of the total drive torque per spin column (the drive tendon's coefficients)."""
    traction_control: np.ndarray
    """(G,) 1 where the model has traction control (``world.traction_control``)."""
    tree: np.ndarray
    """Flat index into the expanded tree_sleep_policy."""
    body: np.ndarray
    """Flat index of the root body's cfrc_ext force (first of 3)."""
    geom: np.ndarray
    """Flat index into the expanded geom_contype / geom_conaffinity of the body geom
    (chassis, frame, pedestrian box: the one that touches other agents)."""
    geom_model: np.ndarray
    """Model index of that geom (its compiled contype / conaffinity)."""
    park_x: np.ndarray
    """Parking spot x [m] (pedestrian slide joints are relative to it)."""
    park_y: np.ndarray
    length: np.ndarray
    """[m]."""
    width: np.ndarray
    """[m]."""
    height: np.ndarray
    """Top of the body above the ground [m]."""
    front: np.ndarray
    """Body origin -> front bumper [m]."""
    wheelbase: np.ndarray
    rear_axle: np.ndarray
    """Body origin -> rear axle [m] (negative = behind)."""
    track: np.ndarray
    r_wheel: np.ndarray
    m_eff: np.ndarray
    """Mass seen by the drive [kg]."""
    mass: np.ndarray
    """[kg]."""
    max_steer: np.ndarray
    """[rad]."""
    rsteer_q: np.ndarray
    """(n, 2) left/right rear steer qpos of vehicles that steer their rear axle, else -1."""
    rsteer_u: np.ndarray
    """(n, 2) their rear steer ctrl, else -1."""
    max_rsteer: np.ndarray
    """Rear-axle steering limit [rad] (0: a fixed rear axle)."""
    max_drive: np.ndarray
    """[N*m] (pedestrian: [N])."""
    max_brake: np.ndarray
    drive_grip: np.ndarray
    """Force the driven wheels carry [N] (``AgentSpec.drive_grip``)."""
    tyre_mu: np.ndarray
    """Tyre-road friction [1] (``AgentSpec.tyre_mu``)."""
    stab_max: np.ndarray
    roll_stiffness: np.ndarray
    """Gravity's toppling moment per radian of lean [N*m/rad] (``AgentSpec.roll_stiffness``)."""
    rest_z: np.ndarray
    """Settled body height on flat ground [m]."""
    rest_pitch: np.ndarray
    """[rad]."""


@dataclass
class Layout:
    """One compiled pooled world and its batch of ``shards`` simulations."""

    pools: list[Pool]
    shards: int
    model: mujoco.MjModel
    batch: mujoco.batch.Batch
    state: np.ndarray
    """(shards * nstate,) view of the batch state: every qpos/qvel/ctrl write goes here."""
    frictionloss: np.ndarray
    """Flat view of the expanded dof_frictionloss (brakes)."""
    sleep_policy: np.ndarray
    """Flat view of the expanded tree_sleep_policy."""
    cfrc_ext: np.ndarray
    """Bound cfrc_ext of every shard."""
    contype: np.ndarray
    """Flat view of the expanded geom_contype (per shard: ghosts switch their body geom off)."""
    conaffinity: np.ndarray
    """Flat view of the expanded geom_conaffinity."""
    tables: SlotTables
    base: np.ndarray
    """First slot number of each pool (by pool index)."""
    build_s: float
    """Wall time of spec building + compile [s]."""

    @property
    def slots(self) -> int:
        return len(self.tables.pool)


def compile_layout(pools: list[Pool], timestep: float, shards: int, threads: int) -> Layout:
    """Build the world spec of ``pools``, compile it and lay out the slot tables."""
    t0 = time.perf_counter()
    model = build_world_spec(pools, timestep).compile()
    batch = mujoco.batch.Batch(model, shards, nthread=min(threads, shards), persistent=True)
    batch.reset()
    base_ptr = batch.state.ctypes.data
    item = batch.state.itemsize

    def off(name: str) -> int:
        return (batch.bind(name).ctypes.data - base_ptr) // item

    offsets = (off("qpos"), off("qvel"), off("ctrl"))
    tables, base = _build_tables(model, pools, shards, batch.nstate, offsets, timestep)
    dt = time.perf_counter() - t0
    log.info(
        "physics world: %d slots in %d pools x %d shards (nq=%d nv=%d) compiled in %.2f s",
        len(tables.pool), len(pools), shards, model.nq, model.nv, dt,
    )
    return Layout(
        pools=list(pools), shards=shards, model=model, batch=batch, state=batch.state.reshape(-1),
        frictionloss=batch.expand("dof_frictionloss").reshape(-1),
        sleep_policy=batch.expand("tree_sleep_policy").reshape(-1), cfrc_ext=batch.bind("cfrc_ext"),
        contype=batch.expand("geom_contype").reshape(-1), conaffinity=batch.expand("geom_conaffinity").reshape(-1),
        tables=tables, base=base, build_s=dt,
    )


def _build_tables(
    m: mujoco.MjModel, pools: list[Pool], shards: int, nstate: int, offsets: tuple[int, int, int],
    timestep: float,
) -> tuple[SlotTables, np.ndarray]:
    """``SlotTables`` of every slot, pool by pool (``_pool_tables``), and each pool's first
    slot number."""
    base = np.zeros(max((p.index for p in pools), default=-1) + 1, np.int64)
    parts: list[SlotTables] = []
    first = 0
    for pool in pools:
        base[pool.index] = first
        if pool.capacity == 0:
            continue
        stride = _SlotStride.measure(m, pool.spec, pool.capacity)
        parts.append(_pool_tables(m, pool, stride, shards, nstate, offsets, M.rest_pose(pool.spec, timestep)))
        first += pool.capacity * shards
    return SlotTables(**{f.name: _concat(f.name, [getattr(p, f.name) for p in parts]) for f in fields(SlotTables)}), base


@dataclass(frozen=True)
class _SlotStride:
    """Model addresses of slot 0 of a pool and the distance to the next slot.

    Each slot is one attached copy of its pool's template, so its bodies, joints, dofs,
    actuators and geoms are consecutive and every slot of a pool has the same layout: the
    addresses of slot ``i`` are those of slot 0 plus ``i`` strides (``measure`` checks the
    last slot by name).
    """

    kind: _KindLayout
    actuators: tuple[str, ...]
    """The slot's actuators (the kind's, then a steered rear axle's)."""
    body: int
    tree: int
    qpos: int
    dof: int
    actuator: int
    geom: int
    """The body geom (chassis, frame, pedestrian box)."""
    nbody: int
    nq: int
    nv: int
    nu: int
    ngeom: int
    rel_actuator: dict[str, int]
    """Actuator -> index relative to the slot's first actuator."""
    rel_qpos: dict[str, int]
    """Steer joint -> qpos relative to the slot's first qpos."""
    rel_dof: dict[str, int]
    """Spin joint -> dof relative to the slot's first dof."""

    @classmethod
    def measure(cls, m: mujoco.MjModel, spec: M.AgentSpec, capacity: int) -> "_SlotStride":
        kind = _KINDS[spec.kind]
        rear = _rear_steered(spec)
        acts = kind.actuators + (_REAR_STEER if rear else ())
        pre = slot_prefix(spec.name, capacity, 0)
        body = m.body(pre + "agent").id
        tree = int(m.body_treeid[body])
        joint = int(m.body_jntadr[body])
        qpos, dof = int(m.jnt_qposadr[joint]), int(m.jnt_dofadr[joint])
        act = m.actuator(pre + acts[0]).id
        geom = m.geom(pre + "chassis").id
        tree_joints = np.flatnonzero(m.body_treeid[m.jnt_bodyid] == tree)
        steer = [j for j in kind.steer_joints if j is not None] + list(_REAR_STEER if rear else ())
        last = slot_prefix(spec.name, capacity, capacity - 1)
        k = capacity - 1
        stride = cls(
            kind=kind, actuators=acts, body=body, tree=tree, qpos=qpos, dof=dof, actuator=act, geom=geom,
            nbody=int(m.tree_bodynum[tree]), nq=int(_JOINT_NQ[m.jnt_type[tree_joints]].sum()),
            nv=int(m.tree_dofnum[tree]), nu=len(acts), ngeom=(m.geom(last + "chassis").id - geom) // k if k else 0,
            rel_actuator={a: m.actuator(pre + a).id - act for a in acts},
            rel_qpos={j: int(m.jnt_qposadr[m.joint(pre + j).id]) - qpos for j in steer},
            rel_dof={j: int(m.jnt_dofadr[m.joint(pre + j).id]) - dof for j in kind.spin_joints},
        )
        lb = m.body(last + "agent").id
        if (lb != body + k * stride.nbody or m.actuator(last + acts[0]).id != act + k * stride.nu
                or m.jnt_qposadr[m.body_jntadr[lb]] != qpos + k * stride.nq):
            raise RuntimeError(f"pool {spec.name}: slots are not laid out with equal strides")
        return stride


def _rear_steered(spec: M.AgentSpec) -> bool:
    """A car-like model that steers its rear axle too."""
    return spec.kind == M.KIND_CAR and spec.rear_steer_deg > 0


def _pool_tables(
    m: mujoco.MjModel, pool: Pool, stride: _SlotStride, shards: int, nstate: int, offsets: tuple[int, int, int],
    rest: M.RestPose,
) -> SlotTables:
    """The rows of one pool's slots, in slot order: by index in the pool, then by shard."""
    index = np.repeat(np.arange(pool.capacity, dtype=np.int64), shards)
    shard = np.tile(np.arange(shards, dtype=np.int64), pool.capacity)
    spec = pool.spec
    n = len(index)
    park_x, park_y = park_position(pool.index, index)
    return SlotTables(
        pool=np.full(n, pool.index, np.int64), shard=shard, index=index, kind=np.full(n, spec.kind, np.int64),
        cls=np.full(n, int(spec.cls), np.int64), park_x=park_x, park_y=park_y,
        **_state_columns(m, stride, index, shard, nstate, offsets),
        **_share_columns(spec, n),
        **_physical_columns(spec, rest, n),
    )


def _state_columns(
    m: mujoco.MjModel, stride: _SlotStride, index: np.ndarray, shard: np.ndarray, nstate: int,
    offsets: tuple[int, int, int],
) -> dict[str, np.ndarray]:
    """Flat indices into the batch state and the expanded model arrays of each slot."""
    off_qpos, off_qvel, off_ctrl = offsets
    n = len(index)
    q = stride.qpos + index * stride.nq
    d = stride.dof + index * stride.nv
    qpos = shard * nstate + off_qpos + q
    qvel = shard * nstate + off_qvel + d
    ctrl = shard * nstate + off_ctrl + (stride.actuator + index * stride.nu)
    kind = stride.kind

    def at(first: np.ndarray, rel: dict[str, int], names: tuple[str | None, ...]) -> np.ndarray:
        """(n, len(names)) ``first`` + each name's relative index; -1 where the name is None."""
        return np.stack([first + rel[a] if a is not None else np.full(n, -1, np.int64) for a in names], axis=1)

    rear = len(stride.actuators) > len(kind.actuators)
    spin = kind.spin_joints or (None,) * BRAKE_COLUMNS
    model_dof = shard * m.nv + d
    geom = stride.geom + index * stride.ngeom
    return dict(
        qpos=qpos, nq=np.full(n, stride.nq, np.int64), qvel=qvel, nv=np.full(n, stride.nv, np.int64), ctrl=ctrl,
        nu=np.full(n, stride.nu, np.int64), qpos0=q, dof=d,
        steer_q=at(qpos, stride.rel_qpos, kind.steer_joints), steer_u=at(ctrl, stride.rel_actuator, kind.steer_act),
        drive_u=ctrl + stride.rel_actuator[kind.drive_act], aux_u=at(ctrl, stride.rel_actuator, kind.aux_act),
        spin_fl=at(model_dof, stride.rel_dof, spin), spin_v=at(qvel, stride.rel_dof, spin),
        rsteer_q=at(qpos, stride.rel_qpos, _REAR_STEER if rear else (None, None)),
        rsteer_u=at(ctrl, stride.rel_actuator, _REAR_STEER if rear else (None, None)),
        tree=shard * m.ntree + (stride.tree + index),
        body=(shard * m.nbody + (stride.body + index * stride.nbody)) * CFRC_WIDTH + CFRC_FORCE,
        geom=shard * m.ngeom + geom, geom_model=geom,
    )


def _share_columns(spec: M.AgentSpec, n: int) -> dict[str, np.ndarray]:
    """Each brake column's share of the brake torque and of the drive torque (the drive
    tendon's coefficients, ``models.car_template``); heavy vehicles' traction control."""
    if spec.kind == M.KIND_CAR:
        brake = [spec.brake_front / 2] * 2 + [(1 - spec.brake_front) / 2] * 2
        driven = M.driven_wheels(spec)
        drive = [1.0 / len(driven) if w in driven else 0.0 for w in M.CAR_WHEELS]
    elif spec.kind == M.KIND_BIKE:  # one wheel in two columns each: the front brake share twice
        brake = [spec.brake_front] * 2 + [1 - spec.brake_front] * 2
        drive = [0.0, 0.0, 1.0, 1.0]  # the rear wheel, driven alone
    else:
        brake = drive = [0.0] * BRAKE_COLUMNS
    return dict(
        brake_share=np.tile(np.asarray(brake, np.float64), (n, 1)),
        drive_share=np.tile(np.asarray(drive, np.float64), (n, 1)),
        traction_control=np.full(n, int(spec.traction_control), np.int64),
    )


def _physical_columns(spec: M.AgentSpec, rest: M.RestPose, n: int) -> dict[str, np.ndarray]:
    """The model's physical parameters, one row per slot."""

    def full(v: float) -> np.ndarray:
        return np.full(n, v, np.float64)

    return dict(
        length=full(spec.length), width=full(spec.width), height=full(spec.height), front=full(spec.front_offset),
        wheelbase=full(spec.wheelbase), rear_axle=full(spec.rear_axle), track=full(spec.track),
        r_wheel=full(spec.wheel_radius), m_eff=full(spec.effective_mass), mass=full(spec.total_mass),
        max_steer=full(math.radians(spec.max_steer_deg)),
        max_rsteer=full(math.radians(spec.rear_steer_deg) if _rear_steered(spec) else 0.0),
        max_drive=full(spec.max_drive if spec.kind != M.KIND_PED else spec.ped_max_force),
        max_brake=full(spec.max_brake), drive_grip=full(spec.drive_grip), tyre_mu=full(spec.tyre_mu),
        stab_max=full(spec.stab_max), roll_stiffness=full(spec.roll_stiffness), rest_z=full(rest.z),
        rest_pitch=full(rest.pitch),
    )


_WIDTH = {
    "steer_q": STEER_COLUMNS, "steer_u": STEER_COLUMNS, "rsteer_q": STEER_COLUMNS, "rsteer_u": STEER_COLUMNS,
    "aux_u": STEER_COLUMNS, "spin_fl": BRAKE_COLUMNS, "spin_v": BRAKE_COLUMNS, "brake_share": BRAKE_COLUMNS,
    "drive_share": BRAKE_COLUMNS,
}
_FLOAT = {
    "brake_share", "drive_share", "park_x", "park_y", "length", "width", "height", "front", "wheelbase", "rear_axle", "track", "r_wheel", "m_eff",
    "mass", "max_steer", "max_rsteer", "max_drive", "max_brake", "drive_grip", "tyre_mu", "stab_max", "roll_stiffness", "rest_z",
    "rest_pitch",
}


def _concat(name: str, parts: list[np.ndarray]) -> np.ndarray:
    """One column over all pools (typed and shaped even without pools)."""
    dtype = np.float64 if name in _FLOAT else np.int64
    if not parts:
        w = _WIDTH.get(name)
        return np.zeros((0, w) if w else 0, dtype)
    return np.concatenate(parts).astype(dtype, copy=False)


def carry_over(old: Layout, new: Layout, slots: np.ndarray) -> np.ndarray:
    """Slot numbers in ``new`` of the same (pool, shard, index) as ``slots`` of ``old``."""
    t = old.tables
    slots = np.asarray(slots, np.int64)
    return new.base[t.pool[slots]] + t.index[slots] * new.shards + t.shard[slots]


__all__ = [
    "Layout", "PARK_ORIGIN", "PARK_SPACING", "Pool", "SlotTables", "build_world_spec",
    "SLOTS_PER_SIM", "arena_bytes", "carry_over", "compile_layout", "park_position", "slot_prefix",
]
