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

# Joint and actuator names of each kind of model, in the order the tables use them.
_STEER_JOINTS = {M.KIND_CAR: ("steer_fl", "steer_fr"), M.KIND_BIKE: ("steer_f", "steer_f"), M.KIND_PED: ()}
_SPIN_JOINTS = {
    M.KIND_CAR: ("spin_fl", "spin_fr", "spin_rl", "spin_rr"),
    M.KIND_BIKE: ("spin_f", "spin_f", "spin_r", "spin_r"),  # two brake columns per wheel
    M.KIND_PED: (),
}
# first three actuators of a slot: (steer left, steer right | aux 0, drive, aux 1)
_ACTUATORS = {
    M.KIND_CAR: ("steer_fl", "steer_fr", "drive"),
    M.KIND_BIKE: ("steer", "drive", "stab"),
    M.KIND_PED: ("fx", "fy", "tz"),
}
# qpos width of each MuJoCo joint type (free, ball, slide, hinge)
_JOINT_NQ = np.array([7, 4, 1, 1])


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
    """Columns of ``SlotTables`` for every pool, built per pool with numpy.

    Each slot is one attached copy of its pool's template, so its bodies, joints, dofs
    and actuators are consecutive and every slot of a pool has the same layout: the
    addresses of slot ``i`` are those of slot 0 plus ``i`` strides (checked at the last
    slot by name).
    """
    off_qpos, off_qvel, off_ctrl = offsets
    S = shards
    cols: dict[str, list[np.ndarray]] = {f.name: [] for f in fields(SlotTables)}
    base = np.zeros(max((p.index for p in pools), default=-1) + 1, np.int64)
    g0 = 0
    for pool in pools:
        base[pool.index] = g0
        C = pool.capacity
        if C == 0:
            continue
        spec = pool.spec
        rest = M.rest_pose(spec, timestep)
        acts = _ACTUATORS[spec.kind]
        pre0 = slot_prefix(spec.name, C, 0)
        b0 = m.body(pre0 + "agent").id
        tree0 = int(m.body_treeid[b0])
        j0 = int(m.body_jntadr[b0])
        q0, d0 = int(m.jnt_qposadr[j0]), int(m.jnt_dofadr[j0])
        a0 = m.actuator(pre0 + acts[0]).id
        tree_joints = np.flatnonzero(m.body_treeid[m.jnt_bodyid] == tree0)
        nq_slot = int(_JOINT_NQ[m.jnt_type[tree_joints]].sum())
        nv_slot = int(m.tree_dofnum[tree0])
        nb_slot = int(m.tree_bodynum[tree0])
        rear = spec.kind == M.KIND_CAR and spec.rear_steer_deg > 0
        if rear:
            acts = (*acts, "steer_rl", "steer_rr")
        nu_slot = len(acts)
        rel_act = {n: m.actuator(pre0 + n).id - a0 for n in acts}
        rel_sq = np.array(
            [m.jnt_qposadr[m.joint(pre0 + j).id] - q0 for j in _STEER_JOINTS[spec.kind]],
            np.int64)
        rel_sd = np.array(
            [m.jnt_dofadr[m.joint(pre0 + j).id] - d0 for j in _SPIN_JOINTS[spec.kind]],
            np.int64)
        last = slot_prefix(spec.name, C, C - 1)
        lb = m.body(last + "agent").id
        g_first = m.geom(pre0 + "chassis").id
        ng_slot = (m.geom(last + "chassis").id - g_first) // (C - 1) if C > 1 else 0
        if (lb != b0 + (C - 1) * nb_slot or m.actuator(last + acts[0]).id != a0 + (C - 1) * nu_slot
                or m.jnt_qposadr[m.body_jntadr[lb]] != q0 + (C - 1) * nq_slot):
            raise RuntimeError(f"pool {spec.name}: slots are not laid out with equal strides")
        i = np.repeat(np.arange(C, dtype=np.int64), S)  # slot order: pool, index, shard
        s = np.tile(np.arange(S, dtype=np.int64), C)
        n = C * S
        q = q0 + i * nq_slot
        d = d0 + i * nv_slot
        a = a0 + i * nu_slot
        b = b0 + i * nb_slot
        qb = s * nstate + off_qpos + q
        vb = s * nstate + off_qvel + d
        ub = s * nstate + off_ctrl + a
        neg2 = np.full((n, 2), -1, np.int64)
        rsteer_q, rsteer_u = neg2, neg2
        if rear:
            rel_rq = np.array([m.jnt_qposadr[m.joint(pre0 + j).id] - q0 for j in ("steer_rl", "steer_rr")], np.int64)
            rsteer_q = qb[:, None] + rel_rq[None, :]
            rsteer_u = ub[:, None] + np.array([rel_act["steer_rl"], rel_act["steer_rr"]])[None, :]
        if spec.kind == M.KIND_CAR:
            steer_q = qb[:, None] + rel_sq[None, :]
            steer_u = ub[:, None] + np.array([rel_act["steer_fl"], rel_act["steer_fr"]])[None, :]
            drive_u = ub + rel_act["drive"]
            aux_u = neg2
            share = [spec.brake_front / 2] * 2 + [(1 - spec.brake_front) / 2] * 2
            drive_share = [0.25] * 4 if spec.awd else [0.0, 0.0, 0.5, 0.5]
        elif spec.kind == M.KIND_BIKE:
            steer_q = qb[:, None] + rel_sq[None, :]
            steer_u = np.repeat((ub + rel_act["steer"])[:, None], 2, axis=1)
            drive_u = ub + rel_act["drive"]
            aux_u = np.stack([ub + rel_act["stab"], np.full(n, -1, np.int64)], axis=1)
            share = [spec.brake_front] * 2 + [1 - spec.brake_front] * 2
            drive_share = [0.0, 0.0, 1.0, 1.0]  # (one rear wheel in both columns)
        else:
            steer_q, steer_u = neg2, neg2.copy()
            drive_u = ub + rel_act["fx"]
            aux_u = np.stack([ub + rel_act["fy"], ub + rel_act["tz"]], axis=1)
            share = [0.0] * 4
            drive_share = [0.0] * 4
        if len(rel_sd):
            spin_fl = (s * m.nv + d)[:, None] + rel_sd[None, :]
            spin_v = vb[:, None] + rel_sd[None, :]
        else:
            spin_fl = np.full((n, 4), -1, np.int64)
            spin_v = np.full((n, 4), -1, np.int64)
        px, py = park_position(pool.index, i)

        def full(v: float) -> np.ndarray:
            return np.full(n, v, np.float64)

        def whole(v: int) -> np.ndarray:
            return np.full(n, v, np.int64)

        part = dict(
            pool=whole(pool.index), shard=s, index=i, kind=whole(spec.kind), cls=whole(int(spec.cls)),
            qpos=qb, nq=whole(nq_slot), qvel=vb, nv=whole(nv_slot), ctrl=ub, nu=whole(nu_slot), qpos0=q, dof=d,
            steer_q=steer_q, steer_u=steer_u, drive_u=drive_u, aux_u=aux_u, spin_fl=spin_fl, spin_v=spin_v,
            brake_share=np.tile(np.asarray(share, np.float64), (n, 1)),
            drive_share=np.tile(np.asarray(drive_share, np.float64), (n, 1)),
            traction_control=whole(int(spec.traction_control)),
            tree=s * m.ntree + (tree0 + i), body=(s * m.nbody + b) * 6 + 3,
            geom=s * m.ngeom + g_first + i * ng_slot, geom_model=g_first + i * ng_slot, park_x=px, park_y=py,
            length=full(spec.length), width=full(spec.width), height=full(spec.height), front=full(spec.front_offset), wheelbase=full(spec.wheelbase),
            rear_axle=full(spec.rear_axle), track=full(spec.track), r_wheel=full(spec.wheel_radius),
            m_eff=full(spec.effective_mass), mass=full(spec.total_mass),
            max_steer=full(math.radians(spec.max_steer_deg)), rsteer_q=rsteer_q, rsteer_u=rsteer_u,
            max_rsteer=full(math.radians(spec.rear_steer_deg) if rear else 0.0),
            max_drive=full(spec.max_drive if spec.kind != M.KIND_PED else spec.ped_max_force),
            max_brake=full(spec.max_brake), drive_grip=full(spec.drive_grip), tyre_mu=full(spec.tyre_mu), stab_max=full(spec.stab_max),
            roll_stiffness=full(spec.roll_stiffness), rest_z=full(rest.z),
            rest_pitch=full(rest.pitch),
        )
        for k, v in part.items():
            cols[k].append(v)
        g0 += n
    return SlotTables(**{k: _concat(k, v) for k, v in cols.items()}), base


_WIDTH = {"steer_q": 2, "steer_u": 2, "rsteer_q": 2, "rsteer_u": 2, "aux_u": 2, "spin_fl": 4, "spin_v": 4, "brake_share": 4, "drive_share": 4}
_FLOAT = {
    "brake_share", "drive_share", "park_x", "park_y", "length", "width", "height", "front", "wheelbase", "rear_axle", "track", "r_wheel", "m_eff",
    "mass", "max_steer", "max_rsteer", "max_drive", "max_brake", "drive_grip", "tyre_mu", "stab_max", "roll_stiffness", "rest_z",
    "rest_pitch",
}


def _concat(name: str, parts: list[np.ndarray]) -> np.ndarray:
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
