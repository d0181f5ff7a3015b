"""Contacts between agents: the contact guard, ghosts, and the collision accounting.

- **Contact guard** (``ContactGuard``): SUMO packs agents closer than any driven body keeps
  to its reference (a bicycle 0.2 m beside a car in the sublane model, a pedestrian 0.15 m
  from a passing motorcycle) and a two-wheeler leans its rider beyond SUMO's upright
  footprint. A pair whose physics footprints come within GUARD_GAP_M (now, or
  GUARD_HORIZON_S ahead) where SUMO's footprints have a gap is carried (kinematic on SUMO's
  poses; placed bodies do not touch each other) for at least GUARD_HOLD_S and until SUMO has
  it GUARD_KEEP_M apart (``carries_contact``, ``carried_contact_ms``).
- **Ghosts** (``ghosts``): a body placed into an occupied spot passes through the others until
  it is GHOST_CLEAR_M clear (``ghost_spawns``, ``ghost_placements``), and so do bodies touching
  where SUMO has them overlap (``ghost_sumo_overlaps``).
- **Collisions** (``CollisionBook``): a contact that began is SUMO's own when its footprints
  overlap there (or SUMO teleported the agent within JUMP_EXCUSE_S), else physics-only
  (``collisions_sumo_reported``, ``collisions_physics_only``).

Pedestrian pairs are never checked (their bodies do not touch each other).
"""

from __future__ import annotations

import numpy as np

from physics_side import models
from physics_side.policies.base import Step, Verdict, log
from physics_side.policies.footprints import (centre, footprint_gap, footprints_overlap, gap_floor, near_pairs,
                                              overlaps_any)
from protocol.frames import wrap_pi
from protocol.messages import AgentMode

GHOST_CLEAR_M = 0.3  # [m] a ghost joins once its body is this far from every other body
JUMP_EXCUSE_S = 2.0  # [s] a collision this soon after SUMO teleported / jumped the agent is SUMO's
SUMO_OVERLAP_M = 0.05  # [m] SUMO footprints this close count as SUMO's own collision
MAX_PENDING_COLLISIONS = 256  # physics-only collisions re-checked at the next sample (bounded)
GUARD_GAP_M = 0.1  # [m] physics footprints this close start a guard
GUARD_HORIZON_S = (0.3, 1.0)  # [s] look-ahead: at least the first, at least a step, at most the second
GUARD_HOLD_S = 1.0  # [s] a guarded pair stays carried at least this long after it was last near
GUARD_KEEP_M = 0.3  # [m] ... and while SUMO has it closer than this
MAX_GUARD_PAIRS = 4096  # active guard pairs (bounded; more are not guarded, logged)
LOG_PAIRS = 5  # pairs named in one log line
PAIR_SLACK = 1e-9  # [1] and [m]: the ghost rule's candidate discs grow by this share and this much, so
# footprints touching corner to corner (at exactly the discs' distance) stay candidates after rounding


def ghosts(cx: np.ndarray, cy: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray,
           ped: np.ndarray, ghost: np.ndarray, placed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ghost, fresh): bodies (centre ``cx``, ``cy`` [m], ``yaw`` [rad], ``length``, ``width``
    [m]) placed this step (``placed``) whose footprint overlaps a live body, or one placed
    before it this step, become ghosts (a motorcycle put on SUMO's pose 2.1 m past its stop
    stood with its rear in a bicycle queued beside it); a ghost (``ghost``: still one from
    before) GHOST_CLEAR_M clear of every other body joins again.

    The rule is sequential (a body placed earlier in the step, or a ghost that joined, counts
    for the next), but only bodies near another have a say: the pairs whose footprints touch
    come from one grid search and one exact test per margin, and the Python loop runs over
    the few bodies in such a pair. (Testing each placed body against every other body took
    0.19 s for 1,000 agents spawned in one step, 1.4 s for 5,000.)"""
    ghost = ghost.copy()
    fresh = np.zeros(len(ghost), bool)
    if not (placed.any() or ghost.any()):
        return ghost, fresh
    (i0, j0), (ic, jc) = _touching(cx, cy, yaw, length, width, ped, placed | ghost)
    # only a body in a touching pair has a say; the rest keep their state (placed) or join (ghosts)
    for i in np.intersect1d(np.flatnonzero(placed), i0):
        js = j0[np.searchsorted(i0, i, "left"):np.searchsorted(i0, i, "right")]  # touching at margin 0
        # live bodies, and those placed before it this step that did not become ghosts
        if (~ghost[js] & (~placed[js] | (js < i))).any():
            ghost[i] = fresh[i] = True
    old_ghosts = ghost & ~fresh
    near = np.zeros(len(ghost), bool)
    near[ic] = True
    ghost[old_ghosts & ~near] = False  # nobody within GHOST_CLEAR_M
    for i in np.flatnonzero(old_ghosts & near):
        js = jc[np.searchsorted(ic, i, "left"):np.searchsorted(ic, i, "right")]  # within GHOST_CLEAR_M
        if not (~ghost[js]).any():
            ghost[i] = False
    return ghost, fresh


def _touching(cx, cy, yaw, length, width, ped, asking):
    """The ordered pairs (i, j), sorted by i, with i one of the bodies ``asking`` (placed or
    ghosts: the only ones the rule decides), whose footprints overlap grown by 0 and by
    GHOST_CLEAR_M, pedestrian pairs left out. Candidates are the pairs whose circumscribed
    discs (grown by GHOST_CLEAR_M and PAIR_SLACK) overlap; each is tested exactly with body i
    as footprint a, as ``overlaps_any`` tests it."""
    # a body with a non-finite pose or size touches nothing (its gaps are NaN): left out of the grid
    ok = np.flatnonzero(np.isfinite(cx) & np.isfinite(cy) & np.isfinite(yaw) & np.isfinite(length) & np.isfinite(width))
    half_diag = 0.5 * np.hypot(length[ok] + 2 * GHOST_CLEAR_M, width[ok] + 2 * GHOST_CLEAR_M)
    a, b = near_pairs(np.asarray(cx[ok], float), np.asarray(cy[ok], float), half_diag * (1 + PAIR_SLACK) + PAIR_SLACK)
    a, b = ok[a], ok[b]
    keep = ~(ped[a] & ped[b]) & (asking[a] | asking[b])
    i = np.concatenate([a[keep], b[keep]])  # both orders: the test is not symmetric to the last bit
    j = np.concatenate([b[keep], a[keep]])
    mine = asking[i]
    i, j = i[mine], j[mine]
    order = np.argsort(i, kind="stable")
    i, j = i[order], j[order]
    args = (cx[i], cy[i], yaw[i], length[i], width[i], cx[j], cy[j], yaw[j], length[j], width[j])
    hit0, hit_clear = footprints_overlap(*args), footprints_overlap(*args, margin=GHOST_CLEAR_M)
    return (i[hit0], j[hit0]), (i[hit_clear], j[hit_clear])


def sumo_overlaps(idx: np.ndarray, h, sumo_len: np.ndarray, sumo_wid: np.ndarray, ped: np.ndarray) -> np.ndarray:
    """Whether each agent of ``idx`` overlaps another agent in SUMO's footprints (length
    ``sumo_len``, width ``sumo_wid`` [m]) at sample ``h`` (front bumper x, y, yaw)."""
    cx, cy = centre(h.x, h.y, h.yaw, sumo_len)
    every = np.arange(len(sumo_len))
    out = np.zeros(len(idx), bool)
    for k, i in enumerate(idx):  # (only agents that touched: a handful per step)
        other = (every != i) & ~(ped & ped[i])
        out[k] = overlaps_any(i, cx, cy, h.yaw, sumo_len, sumo_wid, other, SUMO_OVERLAP_M)
    return out


def _log_physics_only(t: float, agent: str) -> None:
    log.warning("t=%.2f s: %s collided in physics only (SUMO had a gap there)", t, agent)


class CollisionBook:
    """Collisions that began, split into SUMO's own and physics-only. A contact between two
    samples is SUMO's when its footprints overlap at either: one counted physics-only while
    extrapolating waits for the next sample (``recheck``)."""

    def __init__(self) -> None:
        self.pending: list[str] = []

    def began(self, idx: np.ndarray, t: float, sumo: np.ndarray, final: bool, ids: list[str],
              counters: dict[str, int]) -> np.ndarray:
        """Count collisions of agents ``idx`` that began at ``t`` [s], ``sumo`` where SUMO has
        them too; ``final``: the interval's end sample is known (no recheck). Returns SUMO's."""
        counters["collisions_sumo_reported"] += int(sumo.sum())
        counters["collisions_physics_only"] += int((~sumo).sum())
        for i in idx[~sumo]:
            if not final and len(self.pending) < MAX_PENDING_COLLISIONS:
                self.pending.append(ids[i])  # told at the next sample (``recheck``)
            else:
                _log_physics_only(t, ids[i])
        return idx[sumo]

    def recheck(self, index: dict[str, int], t: float, overlaps, ids: list[str],
                counters: dict[str, int]) -> np.ndarray:
        """At a new sample at ``t`` [s]: physics-only collisions of the last interval whose
        agents overlap in SUMO's footprints now (``overlaps(idx)``) were SUMO's (it moved them
        into each other between its samples). Returns those agents' rows."""
        pending, self.pending = self.pending, []
        idx = np.array([index[a] for a in pending if a in index], np.int64)
        for a in pending:
            if a not in index:  # left SUMO at this sample: stays physics only
                _log_physics_only(t, a)
        if not len(idx):
            return idx
        overlap = overlaps(idx)
        moved = int(overlap.sum())
        if moved:
            counters["collisions_physics_only"] -= moved
            counters["collisions_sumo_reported"] += moved
            log.info("%d collision(s) of the last interval were SUMO's: its footprints overlap at t=%.2f s", moved, t)
        for i in idx[~overlap]:
            _log_physics_only(t, ids[i])
        return idx[overlap]


def excused(t: float, jump_t: np.ndarray) -> np.ndarray:
    """A collision at ``t`` [s] within JUMP_EXCUSE_S of SUMO's teleport or jump (``jump_t``) is SUMO's."""
    return (t - jump_t) <= JUMP_EXCUSE_S


class ContactGuard:
    """The pairs the contact guard carries (``detect``): pair of ids -> SUMO time [s] it was last near."""

    def __init__(self) -> None:
        self.pairs: dict[tuple[str, str], float] = {}

    def detect(self, s: Step, v: Verdict) -> np.ndarray:
        """Agents to carry so that a contact SUMO does not have cannot happen: pairs whose
        physics footprints (a two-wheeler's widened by its rider's lean) come within
        GUARD_GAP_M now or GUARD_HORIZON_S ahead (their errors kept, or moving on at their
        velocity) while SUMO's footprints now have a gap; a pair of bodies both placed every
        tick never touches."""
        out = np.zeros(s.n, bool)
        if not s.cfg.contact_guard or s.n < 2:
            self.pairs = {}
            return out
        t = s.ref.t_k
        sx, sy = centre(s.held.x, s.held.y, s.held.yaw, s.sumo_len)
        i, j, pg, sumo_now = _near(s, sx, sy)
        near = (pg < GUARD_GAP_M) & (sumo_now > 2.0 * SUMO_OVERLAP_M)
        ids, told = s.ids, []
        for a, b, g_p, g_s in zip(i[near], j[near], pg[near], sumo_now[near]):
            key = (ids[a], ids[b]) if ids[a] < ids[b] else (ids[b], ids[a])
            if key not in self.pairs:
                if len(self.pairs) >= MAX_GUARD_PAIRS:
                    v.count("guard_pairs_dropped", 1)
                    continue
                told.append(f"{key[0]} and {key[1]} ({g_p:.2f} m apart, SUMO's {g_s:.2f} m)")
            self.pairs[key] = t
        if told:
            log.info("t=%.2f s: %d pair(s) carried to keep clear: %s", t, len(told), "; ".join(told[:LOG_PAIRS]))
        self._hold(s, t, sx, sy, out)
        out &= s.mode == AgentMode.PHYSICAL
        return out

    def _hold(self, s: Step, t: float, sx: np.ndarray, sy: np.ndarray, out: np.ndarray) -> None:
        """Keep the pairs still held (GUARD_HOLD_S, GUARD_KEEP_M) and mark their agents in ``out``."""
        pairs = [(s.index.get(a, -1), s.index.get(b, -1), t0) for (a, b), t0 in self.pairs.items()]
        pairs = [p for p in pairs if p[0] >= 0 and p[1] >= 0]
        if not pairs:
            self.pairs = {}
            return
        a, b, t0 = (np.array(c) for c in zip(*pairs))
        h, L, W = s.held, s.sumo_len, s.sumo_wid
        sumo_now = footprint_gap(sx[a], sy[a], h.yaw[a], L[a], W[a], sx[b], sy[b], h.yaw[b], L[b], W[b])
        stay = ((t - t0) < GUARD_HOLD_S) | (sumo_now < GUARD_KEEP_M)
        a, b, t0 = a[stay], b[stay], t0[stay]
        ids = s.ids
        self.pairs = {(ids[x], ids[y]) if ids[x] < ids[y] else (ids[y], ids[x]): float(z) for x, y, z in zip(a, b, t0)}
        out[a] = True
        out[b] = True


def _near(s: Step, sx: np.ndarray, sy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Candidate pairs (i, j) of the guard with their physics gap [m] (the least of now, ahead
    with the errors kept, ahead at their velocity) and SUMO's gap now [m]."""
    obs, held, L, W = s.obs, s.held, s.length, s.width
    had = s.prev >= 0
    ghost = s.before.ghost
    ped = s.kind == models.KIND_PED
    placed = (s.mode != AgentMode.PHYSICAL) | s.before.carried
    H = min(max(float(s.step_length), GUARD_HORIZON_S[0]), GUARD_HORIZON_S[1])  # (np.clip: ~30 us on a scalar)
    # SUMO's footprints H ahead (its angle turning at its rate)
    ah = s.ref.at(s.horizon + H)
    syaw2 = held.yaw + s.kin_rate * H
    sx2, sy2 = centre(ah.x, ah.y, syaw2, s.sumo_len)
    # the bodies' footprints: a two-wheeler's body (its rider) leaning over reaches height x
    # sin(roll) sideways, less what its half-width comes in
    lean = np.abs(obs.roll)
    extra = np.where(s.kind == models.KIND_BIKE,
                     np.maximum(s.height * np.sin(lean) - 0.5 * W * (1.0 - np.cos(lean)), 0.0), 0.0)
    side = 0.5 * extra * np.sign(obs.roll)  # (+ roll: right side down)
    px = np.where(had, obs.fx - 0.5 * L * np.cos(obs.yaw) + side * np.sin(obs.yaw), sx)
    py = np.where(had, obs.fy - 0.5 * L * np.sin(obs.yaw) - side * np.cos(obs.yaw), sy)
    pyaw = np.where(had, obs.yaw, held.yaw)
    pw = W + extra
    v = np.maximum(np.hypot(obs.vx, obs.vy), np.abs(held.speed))
    r = 0.5 * np.hypot(np.maximum(L, s.sumo_len), np.maximum(pw, s.sumo_wid)) + v * H + GUARD_GAP_M
    i, j = near_pairs(px, py, r)
    ok = ~(ped[i] & ped[j]) & ~ghost[i] & ~ghost[j] & ~(placed[i] & placed[j])
    i, j = i[ok], j[ok]
    if not len(i):
        return i, j, np.zeros(0), np.zeros(0)

    # the bodies now and ahead: with their errors kept, or moving on at their velocity
    kx, ky, kyaw = sx2 + px - sx, sy2 + py - sy, syaw2 + wrap_pi(pyaw - held.yaw)
    lx, ly, lyaw = px + obs.vx * H, py + obs.vy * H, pyaw + obs.yaw_rate * H
    # Only pairs that may come within GUARD_GAP_M are measured exactly (the disc test above
    # takes every pair within the distance both may drive in H: most are far apart).
    half_l, corner = 0.5 * np.maximum(L, pw), 0.5 * np.hypot(L, pw)
    least = np.minimum(gap_floor(px, py, i, j, half_l, corner),
                       np.minimum(gap_floor(kx, ky, i, j, half_l, corner), gap_floor(lx, ly, i, j, half_l, corner)))
    may = least < GUARD_GAP_M
    i, j = i[may], j[may]

    def gaps(ax, ay, ah_, al, aw):
        return footprint_gap(ax[i], ay[i], ah_[i], al[i], aw[i], ax[j], ay[j], ah_[j], al[j], aw[j])

    sumo_now = gaps(sx, sy, held.yaw, s.sumo_len, s.sumo_wid)
    pg = np.minimum(gaps(px, py, pyaw, L, pw), np.minimum(gaps(kx, ky, kyaw, L, pw), gaps(lx, ly, lyaw, L, pw)))
    # SUMO's footprints this close are its own collision; only now counts (ahead they are our
    # extrapolation: a motorcycle SUMO stops within a step from 15 m/s runs on into its leader
    # there, SUMO's next sample does not)
    return i, j, pg, sumo_now


def detect_guard(s: Step, v: Verdict) -> None:
    """Carry both agents of every guarded pair (never the agents physics owns under two-way coupling)."""
    v.guard = s.guard.detect(s, v)
    v.carry(v.guard & ~s.authoritative)


__all__ = [
    "CollisionBook", "ContactGuard", "detect_guard", "excused", "ghosts", "sumo_overlaps",
]
