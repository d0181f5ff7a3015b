"""The policies' state from one SUMO step to the next, as ``control.ControlState`` keeps the
controllers': per agent (rows of the fleet's agents; ``previous`` realigns it to a new
step's order) and the stateful parts (the guarded pairs, the collisions waiting for the
next sample)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from physics_side.policies import carry
from physics_side.policies.base import Previous, Step, Verdict, realign, realign_mask
from physics_side.policies.carry_pose import POSE_DIMS, start_glide
from physics_side.policies.contacts import CollisionBook, ContactGuard, excused, ghosts, sumo_overlaps
from physics_side.reference import Reference


class PolicyState:
    """Per-agent state of the policies and their stateful parts (see module docstring)."""

    def __init__(self) -> None:
        self.ghost = np.zeros(0, bool)  # without agent contact until clear (``contacts.ghosts``)
        self.carried = np.zeros(0, bool)  # carried for a manoeuvre or a contact
        self.guarded = np.zeros(0, bool)  # ... the carry is the contact guard's
        self.sliding = np.zeros(0, bool)  # carried along SUMO's sideways slide while standing
        self.rolls_back = np.zeros(0, bool)  # may roll back to its standing reference (``carry.rolls_back``)
        self.jump_t = np.zeros(0)  # [s] SUMO time of its last teleport or jump placement
        self.kin_off = np.zeros((0, POSE_DIMS))  # each carry's offset from SUMO's pose at its start (x, y, yaw)
        self.kin_age = np.zeros(0)  # [s] since each carry started (inf: none)
        self.chord_end: np.ndarray | None = None  # carried chords' fix [rad] at the step's end (``carry_pose``)
        self.guard = ContactGuard()
        self.collisions = CollisionBook()

    def previous(self, prev: np.ndarray) -> Previous:
        """The state of the previous step for agents at rows ``prev`` of it (-1: none)."""
        self.chord_end = None  # (once per SUMO step)
        return Previous(carried=realign_mask(self.carried, prev), guarded=realign_mask(self.guarded, prev),
                        sliding=realign_mask(self.sliding, prev), ghost=realign_mask(self.ghost, prev),
                        jump_t=realign(self.jump_t, prev, -np.inf))

    def settle_carries(self, s: Step, v: Verdict, start_yaw: Callable[[], np.ndarray]) -> None:
        """This step's carries (manoeuvre or contact; never agents physics owns), each one that
        began gliding from where its body is (``start_yaw()``: the carried angle there), counted
        in ``v``; slides and roll-backs as decided."""
        was = s.before.carried
        now = (v.manoeuvre | v.guard) & ~s.authoritative
        self.carried = now
        began = now & ~was
        # a carry the guard started stays the guard's while the manoeuvre keeps it
        contact = now & (v.guard | (was & s.before.guarded))
        self.guarded = contact
        yaw0 = start_yaw() if began.any() else None
        self.kin_off, self.kin_age = start_glide(s.prev, was, began, s.obs, s.held, yaw0, self.kin_off, self.kin_age)
        self.sliding, self.rolls_back = v.sliding, v.rolls_back
        carry.count(v, s, now, began, contact)

    def settle_ghosts(self, s: Step, cx: np.ndarray, cy: np.ndarray, yaw: np.ndarray, length: np.ndarray,
                      width: np.ndarray, ped: np.ndarray, placed: np.ndarray) -> np.ndarray:
        """Ghosts after this step's placements (``placed``; bodies' centres ``cx``, ``cy`` [m],
        ``yaw`` [rad], ``length``, ``width`` [m] after them); returns the new ghosts (bool)."""
        ghost = s.before.ghost & ~s.is_new
        if not s.n:
            self.ghost = ghost
            return np.zeros(0, bool)
        self.ghost, fresh = ghosts(cx, cy, yaw, length, width, ped, ghost, placed)
        return fresh

    def settle_jumps(self, s: Step, jumped: np.ndarray) -> None:
        """SUMO's teleports and this step's jump placements (``jumped``) are at the sample's time."""
        self.jump_t = s.before.jump_t
        self.jump_t[jumped] = s.t

    def make_ghosts(self, idx: np.ndarray) -> None:
        """Agents ``idx`` become ghosts (touching where SUMO has them overlap, they pass through
        each other as in SUMO: pushing them apart knocked them into third agents)."""
        self.ghost = self.ghost.copy()
        self.ghost[idx] = True

    def collisions_began(self, began: np.ndarray, ref: Reference, newest: Reference, sumo_len: np.ndarray,
                         sumo_wid: np.ndarray, ped: np.ndarray, ids: list[str], counters: dict[str, int]) -> np.ndarray:
        """Count the collisions that ``began`` (``contacts.CollisionBook``): SUMO's where its
        footprints (``sumo_len``, ``sumo_wid`` [m]) overlap at the interval's start (``ref``)
        or, interpolating, its end sample (``newest``), or after a jump. Returns SUMO's."""
        t, idx = ref.t_k, np.flatnonzero(began)
        sumo = excused(t, self.jump_t[idx]) | sumo_overlaps(idx, ref.held(), sumo_len, sumo_wid, ped)
        final = newest is not ref  # interpolating: the interval's end sample is known
        if final:
            sumo |= sumo_overlaps(idx, newest.held(), sumo_len, sumo_wid, ped)
        return self.collisions.began(idx, t, sumo, final, ids, counters)

    def recheck_collisions(self, newest: Reference, sumo_len: np.ndarray, sumo_wid: np.ndarray, ped: np.ndarray,
                           index: dict[str, int], ids: list[str], counters: dict[str, int]) -> np.ndarray:
        """``contacts.CollisionBook.recheck`` at the sample ``newest``; returns the agents that were SUMO's."""
        held = newest.held()
        return self.collisions.recheck(index, newest.t_k, lambda idx: sumo_overlaps(idx, held, sumo_len, sumo_wid, ped),
                                       ids, counters)


__all__ = ["PolicyState"]
