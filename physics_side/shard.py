"""Physics shards: ``sumoco physics --shard i/k`` simulates one spatial partition of the agents.

The plane is cut into square tiles (``TILE_M``); each tile belongs to one of the living
shards (a hash of the tile, so every shard computes the same map without talking).
Agents near each other are in the same tile and so in the same shard. An agent keeps its
shard while it is within ``HALO_M`` of a tile of that shard, so an agent driving along a
tile edge does not hop between processes. Each shard is its own physics instance
(``<instance>.<i>of<k>``): it publishes the state of its agents and acknowledges every
step; the SUMO side waits for all of them in lockstep.

When a shard's liveliness token disappears, the others drop it from the living set:
its tiles go to the survivors at the next step, which spawn its agents at their SUMO
pose (the SUMO side stops waiting for it as soon as it notices the same token).
"""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np

from physics_side.kinematics import concat_ranges
from protocol.errors import ConfigError
from protocol.messages import AgentBatch

TILE_M = 250.0  # [m] edge of a partition tile
HALO_M = 30.0  # [m] an agent keeps its shard this far beyond the shard's tiles
# Spatial hash of a tile (Teschner et al. 2003: large primes, XOR), so neighbouring tiles
# spread over the shards; non-negative in 31 bits
HASH_PRIME_X = 73856093
HASH_PRIME_Y = 19349663
HASH_MASK = 0x7FFFFFFF
_SHARD_NAME = re.compile(r"^(?P<base>.+)\.(?P<i>\d+)of(?P<k>\d+)$")


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/k"`` -> (i, k) with 0 <= i < k."""
    try:
        i, k = (int(v) for v in text.split("/"))
    except ValueError:
        raise ConfigError(f"--shard: expected i/k (e.g. 0/2), got {text!r}") from None
    if not 0 <= i < k:
        raise ConfigError(f"--shard: expected 0 <= i < k, got {text!r}")
    return i, k


def shard_instance(base: str, index: int, count: int) -> str:
    """Physics instance name of shard ``index`` of ``count``."""
    return f"{base}.{index}of{count}"


def shard_of_instance(name: str) -> tuple[str, int, int] | None:
    """(base, index, count) of a shard instance name, None for a plain instance."""
    m = _SHARD_NAME.match(name)
    if m is None:
        return None
    return m["base"], int(m["i"]), int(m["k"])


def subset(batch: AgentBatch, rows: np.ndarray) -> AgentBatch:
    """The agents ``rows`` of ``batch`` (paths included), in that order."""
    rows = np.asarray(rows, np.int64)
    cols = {k: getattr(batch, k)[rows] for k in (
        "cls", "vtype", "x", "y", "angle", "speed", "accel", "signals", "la_x", "la_y", "length", "width", "lane",
        "flags")}
    off = np.asarray(batch.path_offsets, np.int64)
    if len(off) == batch.n + 1 and batch.n:
        counts = off[rows + 1] - off[rows]
        new_off = np.concatenate([[0], np.cumsum(counts)]).astype(batch.path_offsets.dtype)
        xy = batch.path_xy[concat_ranges(off[rows], counts)]
    else:
        new_off, xy = batch.path_offsets, batch.path_xy
    return replace(batch, ids=[batch.ids[i] for i in rows], path_offsets=new_off, path_xy=xy, **cols)


class ShardFilter:
    """Which agents of a step shard ``index`` of ``count`` simulates (see module docstring)."""

    def __init__(self, index: int, count: int, tile_m: float = TILE_M, halo_m: float = HALO_M):
        self.index = int(index)
        self.count = int(count)
        self.tile_m = float(tile_m)
        self.halo_m = float(halo_m)
        self.living = list(range(self.count))
        self._owner: dict[str, int] = {}
        self.takeovers = 0  # agents taken over from a lost shard

    def _tile_owner(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        tx = np.floor(x / self.tile_m).astype(np.int64)
        ty = np.floor(y / self.tile_m).astype(np.int64)
        h = ((tx * HASH_PRIME_X) ^ (ty * HASH_PRIME_Y)) & HASH_MASK
        return np.asarray(self.living, np.int64)[h % len(self.living)]

    def owners(self, batch: AgentBatch) -> np.ndarray:
        """Shard of every agent of ``batch`` (updates the sticky assignment)."""
        x, y = np.asarray(batch.x, np.float64), np.asarray(batch.y, np.float64)
        own = self._tile_owner(x, y)
        prev = np.fromiter((self._owner.get(a, -1) for a in batch.ids), np.int64, batch.n)
        alive = np.isin(prev, self.living)
        near = np.zeros(batch.n, bool)
        h = self.halo_m
        for dx, dy in ((h, 0.0), (-h, 0.0), (0.0, h), (0.0, -h), (h, h), (-h, -h), (h, -h), (-h, h)):
            near |= self._tile_owner(x + dx, y + dy) == prev
        keep = alive & near
        own = np.where(keep, prev, own)
        self.takeovers += int(((prev >= 0) & ~alive & (own == self.index)).sum())
        self._owner = dict(zip(batch.ids, own.tolist()))
        return own

    def rows(self, batch: AgentBatch) -> np.ndarray:
        """Rows of ``batch`` this shard simulates."""
        return np.flatnonzero(self.owners(batch) == self.index)

    def set_alive(self, index: int, up: bool) -> bool:
        """A sibling shard came or went; True if the living set changed."""
        if index == self.index or not 0 <= index < self.count:
            return False
        if up and index not in self.living:
            self.living = sorted([*self.living, index])
            # A sibling that comes back (restarted) knows no sticky assignments: every shard
            # drops its own too, so all decide by tile alone and no agent is simulated twice
            # (kept in a survivor's halo while the newcomer takes it by tile).
            self._owner = {}
            return True
        if not up and index in self.living:
            self.living.remove(index)
            return True
        return False


__all__ = ["HALO_M", "TILE_M", "ShardFilter", "parse_shard", "shard_instance", "shard_of_instance", "subset"]
