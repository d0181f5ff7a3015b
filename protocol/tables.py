"""What a receiver keeps between steps: the vehicle-type table of the current static version.

Since protocol 1.2 a step carries its vType table only when the table changed (SPEC.md
3.1, 3.2); every step carries the static version ``sv`` it refers to. ``StaticTracker``
fills the table into steps that do not carry it and says when the receiver must query
the static data again (a late joiner, or a change it missed).
"""

from __future__ import annotations

from dataclasses import replace

from protocol.messages import StaticData, StepMessage, VType


class StaticTracker:
    """The newest vType table seen, from steps or static data, and its static version."""

    def __init__(self) -> None:
        self.version: int | None = None
        """Static version of ``vtypes`` (None: nothing seen yet)."""
        self.vtypes: list[VType] | None = None
        self.stale = False
        """True after a step referred to a static version this tracker does not have:
        query the static data (and feed it to ``on_static``)."""
        self.misses = 0
        """Steps that arrived without a usable table."""

    def on_static(self, static: StaticData) -> None:
        """Static data from the queryable (a reply may be older than the newest step)."""
        if self.version is None or static.version >= self.version or self.stale:
            self.version = static.version
            self.vtypes = list(static.vtypes)
            self.stale = False

    def resolve(self, msg: StepMessage) -> StepMessage:
        """``msg`` with its vType table: its own, or the kept one of the same version.

        When neither is at hand the message comes back with ``vtypes`` None and ``stale``
        is set (the receiver then decides per agent from ``cls``, ``length``, ``width``).
        """
        if msg.vtypes is not None:
            self.version = msg.static_version
            self.vtypes = msg.vtypes
            self.stale = False
            return msg
        if self.vtypes is not None and self.version == msg.static_version:
            return replace(msg, vtypes=self.vtypes)
        self.stale = True
        self.misses += 1
        return msg
