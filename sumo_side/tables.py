"""The SUMO side's static tables that can change during a run: vehicle types, tls links.

Both are versioned (protocol 1.2, SPEC.md 3.2): every change increments ``version``, steps
carry ``sv`` and the vType table travels in the step where it changes.

The vType table is bounded. Indexes are u16 on the wire, and SUMO creates a private copy of
a vType for every vehicle whose size or speed factor is set individually (``veh@type``), so
a long run can meet an unbounded number of types. Types that no agent uses and that SUMO
no longer knows are dropped and their index is reused; when the table is full anyway, a
new type borrows the index of a type with the same vClass (counted in ``overflow``)
instead of failing the run.
"""

from __future__ import annotations

import heapq
import logging

import numpy as np

from protocol.messages import VCLASS_TO_AGENT_CLASS, AgentClass, TlsLinks, VType

log = logging.getLogger(__name__)

#: u16 indexes on the wire.
MAX_VTYPES = 65_535
#: An unused row (a dropped type whose index is free) on the wire.
UNUSED = VType("", "")


class VTypeTable:
    """vType id -> index, with vClass, agent class, length and width per index (bounded)."""

    def __init__(self, api, capacity: int = MAX_VTYPES) -> None:
        self._api = api
        self.capacity = int(capacity)
        self.index: dict[str, int] = {}
        self.types: list[VType] = []
        self._free: list[int] = []  # heap of free indexes below len(types)
        self.cls = np.zeros(0, np.uint8)
        self.length = np.zeros(0, np.float32)
        self.width = np.zeros(0, np.float32)
        self.version = 0
        """Increments with every added or dropped type."""
        self.overflow = 0
        """Types that found the table full and borrowed another type's index."""
        self.dropped = 0
        self._live_after_collect = 0

    @property
    def live(self) -> int:
        return len(self.index)

    def _grow(self, size: int) -> None:
        if size > len(self.cls):
            extra = max(size, 2 * len(self.cls), 16) - len(self.cls)
            self.cls = np.concatenate([self.cls, np.full(extra, AgentClass.OTHER, np.uint8)])
            self.length = np.concatenate([self.length, np.zeros(extra, np.float32)])
            self.width = np.concatenate([self.width, np.zeros(extra, np.float32)])

    def add(self, type_id: str) -> int:
        i = self.index.get(type_id)
        if i is not None:
            return i
        vt = self._api.vehicletype
        vclass = vt.getVehicleClass(type_id)
        if self._free:
            i = heapq.heappop(self._free)
        elif len(self.types) < self.capacity:
            i = len(self.types)
            self.types.append(UNUSED)
            self._grow(i + 1)
        else:
            return self._borrow(type_id, vclass)
        self.index[type_id] = i
        self.types[i] = VType(type_id, vclass)
        self.cls[i] = int(VCLASS_TO_AGENT_CLASS.get(vclass, AgentClass.OTHER))
        self.length[i] = vt.getLength(type_id)
        self.width[i] = vt.getWidth(type_id)
        self.version += 1
        return i

    def _borrow(self, type_id: str, vclass: str) -> int:
        self.overflow += 1
        if self.overflow == 1 or self.overflow % 1000 == 0:
            log.warning("vehicle-type table full (%d types): %r shares the index of a %s type "
                        "(%d so far)", self.capacity, type_id, vclass, self.overflow)
        for k, t in enumerate(self.types):
            if t.vclass == vclass:
                return k
        return 0

    def indices(self, type_ids) -> np.ndarray:
        """Index of every type id (new ones are added) [int64]."""
        ids = tuple(type_ids)
        try:
            return np.fromiter(map(self.index.__getitem__, ids), np.int64, len(ids))
        except KeyError:
            return np.fromiter(map(self.add, ids), np.int64, len(ids))

    def collect(self, in_use: np.ndarray, force: bool = False) -> int:
        """Drop types no agent uses (``in_use``: indexes of this step's agents) that SUMO no
        longer knows; when still near the capacity, drop every unused one. Runs only when
        the table has grown well beyond its size after the last collection (or ``force``).
        Returns the number dropped."""
        live = self.live
        if not force and live <= max(2 * self._live_after_collect, self._live_after_collect + 256) \
                and live < self.capacity:
            return 0
        used = np.zeros(len(self.types), bool)
        if len(in_use):
            used[np.asarray(in_use, np.int64)] = True
        known = set(self._api.vehicletype.getIDList())
        tight = live >= self.capacity - 256
        drop = [t for t, i in self.index.items() if not used[i] and (tight or t not in known)]
        for t in drop:
            i = self.index.pop(t)
            self.types[i] = UNUSED
            self.length[i] = self.width[i] = 0.0
            self.cls[i] = AgentClass.OTHER
            heapq.heappush(self._free, i)
        while self.types and self.types[-1] is UNUSED and self._free:  # shrink from the end
            last = len(self.types) - 1
            self.types.pop()
            self._free.remove(last)
        heapq.heapify(self._free)
        if drop:
            self.version += 1
            self.dropped += len(drop)
            log.debug("vehicle-type table: dropped %d unused types, %d left", len(drop), self.live)
        self._live_after_collect = self.live
        return len(drop)


class TlsTable:
    """Active program per traffic light; the link table is re-read when a program changes."""

    def __init__(self, api, tls_ids: list[str], links_of) -> None:
        """``links_of(tls_ids)`` builds the ``TlsLinks`` of these lights."""
        self._api = api
        self.ids = list(tls_ids)
        self._links_of = links_of
        self.links: TlsLinks = links_of(self.ids)
        self.programs: list[str] = [api.trafficlight.getProgram(t) for t in self.ids]
        self.version = 0
        """Increments when the link table changes."""
        self.switches = 0
        """Program switches seen."""

    def update(self, programs: list[str]) -> bool:
        """This step's program per light; True when the link table changed."""
        if programs == self.programs:
            return False
        self.switches += sum(a != b for a, b in zip(programs, self.programs))
        self.programs = list(programs)
        links = self._links_of(self.ids)
        if _same_links(links, self.links):
            return False
        self.links = links
        self.version += 1
        return True


def _same_links(a: TlsLinks, b: TlsLinks) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("tls", "link", "from_lane", "to_lane", "via_lane"))
