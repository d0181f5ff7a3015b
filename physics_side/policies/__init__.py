"""The rules that reconcile SUMO's motion with physics, in the order they apply.

SUMO moves agents in ways no body can drive (teleports, sideways hops, a U-turn on the spot,
a bicycle packed 0.2 m beside a car); physics drives bodies SUMO never sees (one that fell
over, ran wide, or touches a neighbour). Each rule is one module behind one interface
(``base``): ``Fleet.apply_step`` builds a ``Step`` and runs the detect-phase entries of
``POLICIES`` in order, each claiming agents in a ``Verdict`` (placed for a cause, first
claim wins; carried; may roll back); then it acts on the verdict. Sample-phase entries
decide how the step's reference is built (``Fleet`` calls them while syncing); tick-phase
entries act after each MuJoCo step.

A carried agent is shown kinematic on SUMO's poses (``carry_pose``) until its release; a
placed agent is put on SUMO's pose once. Every entry names the ``summary.json`` counters
(``counters.*``) it moves.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

from physics_side.policies import carry, contacts, placement, sync
from physics_side.policies.base import Cause, Previous, Step, Verdict
from physics_side.policies.state import PolicyState


class Policy(NamedTuple):
    """One rule of the table."""

    name: str
    phase: str
    """"sample" (builds the reference), "detect" (claims agents, in table order) or "tick"."""
    trigger: str
    action: str
    release: str
    counters: tuple[str, ...]
    """``summary.json`` ``counters.*`` it moves."""
    detect: Callable[[Step, Verdict], None] | None = None
    """Detect phase: claims agents of the ``Step`` in the ``Verdict``."""


POLICIES: tuple[Policy, ...] = (
    Policy("retype", "sample", "vType or wire class changed (vehicle.setType)",
           "park, spawn in the new type's model", "-", ("retyped", "placements_spawn")),
    Policy("stale", "sample",
           f"resync, or the previous sample older than max({sync.STALE_MIN_S} s, {sync.STALE_STEPS} steps) or ahead",
           "no previous sample (no turn rate, drift or hop)", "-", ("resyncs",)),
    Policy("drift", "sample", "SUMO moves the sample off its lane's centre line slower than max_side_speed",
           "the reference drifts sideways with it", "a sample back on the centre line", ()),
    Policy("hop", "sample", "slow at both samples, moved sideways beyond sideways_jump_m and max_side_speed",
           "interpolated from the new sample; placed (jump)", "-", ()),
    Policy("pedestrian_hop", "sample", f"a pedestrian moved {sync.PED_HOP_M} m further than it walks",
           "interpolated from the new sample; placed (jump)", "-", ()),
    Policy("spawn", "detect", "new agent (or retyped)", "place at SUMO's pose", "-",
           ("placements_spawn",), sync.detect_spawn),
    Policy("manoeuvre", "detect",
           f"path ahead beyond {carry.INFEASIBLE_MARGIN} of the reach or of the grip's share (heavy vehicles "
           f"{carry.HEAVY_GRIP_SHARE}, cars {carry.CAR_GRIP_SHARE} braked, motorcycles "
           f"{carry.MOTORCYCLE_GRIP_SHARE}); SUMO turning it {carry.INFEASIBLE_RATE_MARGIN} x faster than full "
           f"lock; inserted {carry.SPAWN_OFF_DEG} deg off its path",
           "carry: kinematic on SUMO's poses, gliding onto them",
           f"path within {carry.INFEASIBLE_RELEASE} of reach and grip, body straight on it, SUMO turning it within its "
           f"steering; two-wheelers below {carry.GUARD_BIKE_RELEASE_ALAT} m/s^2 of SUMO's turn",
           ("carries_infeasible", "carried_infeasible_ms"), carry.detect_manoeuvre),
    Policy("contact_guard", "detect",
           f"physics footprints within {contacts.GUARD_GAP_M} m (now or ahead) where SUMO's have a gap",
           "carry both of the pair",
           f"{contacts.GUARD_HOLD_S} s after last near and SUMO {contacts.GUARD_KEEP_M} m apart",
           ("carries_contact", "carried_contact_ms", "guard_pairs_dropped"), contacts.detect_guard),
    Policy("roll_back", "detect", "stopped past a standing reference",
           f"roll back to it (two-wheelers only with the way {carry.RIDER_BACK_CLEAR_M} m clear)", "at the reference",
           (), carry.detect_roll_back),
    Policy("jump", "detect", "AgentFlag.JUMPED, a hop or a pedestrian hop (physical agents)",
           "place at SUMO's new pose", "-", ("placements_jump",), sync.detect_jump),
    Policy("slide", "detect", "slow, SUMO sliding it sideways: beyond sideways_slide_m off, or standing",
           "place; a standing one carried along the slide", "the sample back on its lane's centre line",
           ("placements_jump",), sync.detect_slide),
    Policy("flip", "detect", "roll or pitch beyond flip_deg", "place upright at SUMO's pose", "-",
           ("placements_flip",), placement.detect_flip),
    Policy("divergence", "detect", "further than divergence_m from the reference", "place at SUMO's pose", "-",
           ("placements_divergence",), placement.detect_divergence),
    Policy("ghost", "tick", "placed into an occupied spot, or touching where SUMO's footprints overlap",
           "no agent contact (a ghost)", f"{contacts.GHOST_CLEAR_M} m clear of every body",
           ("ghost_spawns", "ghost_placements", "ghost_sumo_overlaps")),
    Policy("collision", "tick", "a contact between upright bodies began",
           f"count: SUMO's own (its footprints overlap, or a jump within {contacts.JUMP_EXCUSE_S} s) or physics-only",
           "-", ("collisions_sumo_reported", "collisions_physics_only")),
)
"""Every rule, in the order it applies (the descriptions quote the rules' own constants)."""

DETECT: tuple[Policy, ...] = tuple(p for p in POLICIES if p.phase == "detect")
"""The detect-phase rules ``Fleet.apply_step`` runs, in table order."""

COUNTERS: tuple[str, ...] = tuple(dict.fromkeys(c for p in POLICIES for c in p.counters))
"""Every counter the rules move (``Fleet.counters``)."""

__all__ = ["COUNTERS", "DETECT", "POLICIES", "Cause", "Policy", "PolicyState", "Previous", "Step", "Verdict"]
