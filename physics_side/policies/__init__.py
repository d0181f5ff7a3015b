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
    Policy("stale", "sample", "resync, or the previous sample older than max(1 s, 2.5 steps) or ahead",
           "no previous sample (no turn rate, drift, hop)", "-", ("resyncs",)),
    Policy("drift", "sample", "SUMO's sideways motion off the lane's centre line below max_side_speed",
           "the reference drifts sideways with it", "a sample back on the centre line", ()),
    Policy("hop", "sample", "slow at both samples, moved sideways beyond sideways_jump_m / max_side_speed",
           "interpolation starts from the new sample; placed (jump)", "-", ()),
    Policy("pedestrian_hop", "sample", "pedestrian moved PED_HOP_M further than it walks",
           "interpolation starts from the new sample; placed (jump)", "-", ()),
    Policy("spawn", "detect", "new agent (or retyped)", "place at SUMO's pose", "-",
           ("placements_spawn",), sync.detect_spawn),
    Policy("manoeuvre", "detect",
           "path ahead beyond reach or grip share (heavy 0.6, car 1.2 braked, motorcycle 1.4); "
           "SUMO's turn rate beyond full lock; inserted moving 20 deg off its path",
           "carry (kinematic, gliding onto SUMO's pose)",
           "path within 0.75 of reach and grip, body straight on it, SUMO turning within steering; "
           "two-wheelers below 2 m/s^2 of SUMO's turn",
           ("carries_infeasible", "carried_infeasible_ms"), carry.detect_manoeuvre),
    Policy("contact_guard", "detect", "physics footprints within 0.1 m (now or ahead) where SUMO's have a gap",
           "carry both of the pair", "1 s after last near and SUMO 0.3 m apart",
           ("carries_contact", "carried_contact_ms", "guard_pairs_dropped"), contacts.detect_guard),
    Policy("roll_back", "detect", "stopped past a standing reference",
           "roll back to it (two-wheelers only with a clear way back)", "at the reference", (),
           carry.detect_roll_back),
    Policy("jump", "detect", "AgentFlag.JUMPED, a hop or a pedestrian hop (physical agents)",
           "place at SUMO's new pose", "-", ("placements_jump",), sync.detect_jump),
    Policy("slide", "detect", "slow and sliding sideways: beyond sideways_slide_m off, or standing",
           "place; a standing one carried along the slide", "the slide ends (sample on its centre line)",
           ("placements_jump",), sync.detect_slide),
    Policy("flip", "detect", "roll or pitch beyond flip_deg", "place upright at SUMO's pose", "-",
           ("placements_flip",), placement.detect_flip),
    Policy("divergence", "detect", "further than divergence_m from the reference", "place at SUMO's pose", "-",
           ("placements_divergence",), placement.detect_divergence),
    Policy("ghost", "tick", "placed into an occupied spot, or touching where SUMO's footprints overlap",
           "no agent contact (ghost)", "GHOST_CLEAR_M clear of every body",
           ("ghost_spawns", "ghost_placements", "ghost_sumo_overlaps")),
    Policy("collision", "tick", "a contact between upright bodies began",
           "count: SUMO's own (its footprints overlap, or a jump within 2 s) or physics-only",
           "-", ("collisions_sumo_reported", "collisions_physics_only")),
)
"""Every rule, in the order it applies."""

DETECT: tuple[Policy, ...] = tuple(p for p in POLICIES if p.phase == "detect")
"""The detect-phase rules ``Fleet.apply_step`` runs, in table order."""

COUNTERS: tuple[str, ...] = tuple(dict.fromkeys(c for p in POLICIES for c in p.counters))
"""Every counter the rules move (``Fleet.counters``)."""

__all__ = ["COUNTERS", "DETECT", "POLICIES", "Cause", "Policy", "Previous", "Step", "Verdict"]
