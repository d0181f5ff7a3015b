"""A bounded hand-over queue from Zenoh's callback threads to a daemon's main loop.

Zenoh runs subscriber callbacks on its own threads; libsumo and MuJoCo run on the main
thread only. Everything received goes through a queue whose size is bounded in items and,
optionally, in bytes, so a flood of messages (a broken or hostile peer) costs a bounded
amount of memory. When full, the **oldest** item is dropped and counted: the newest
message is the one worth keeping for steps, acknowledgements and liveliness changes.
"""

from __future__ import annotations

import collections
import threading
from typing import Callable, Generic, TypeVar

T = TypeVar("T")


class DropOldest(Generic[T]):
    """Thread-safe FIFO of at most ``maxlen`` items and ``max_bytes`` bytes (``size(item)``).

    ``put`` never blocks (it runs on Zenoh's thread); ``get`` waits up to ``timeout`` [s].
    ``dropped`` counts items dropped to make room, ``refused`` items larger than
    ``max_bytes`` on their own.
    """

    def __init__(self, maxlen: int, max_bytes: int | None = None,
                 size: Callable[[T], int] | None = None) -> None:
        if maxlen < 1 or (max_bytes is not None and max_bytes < 1):
            raise ValueError(f"DropOldest: maxlen and max_bytes must be >= 1, got {maxlen}, {max_bytes}")
        self.maxlen = maxlen
        self.max_bytes = max_bytes
        self._size = size or (lambda item: len(item))  # type: ignore[arg-type]
        self._items: collections.deque[tuple[T, int]] = collections.deque()
        self._bytes = 0
        self._cond = threading.Condition()
        self.dropped = 0
        self.refused = 0

    def put(self, item: T) -> bool:
        """Append ``item``; False if it alone exceeds ``max_bytes`` (then it is not queued)."""
        n = self._size(item) if self.max_bytes is not None else 0
        with self._cond:
            if self.max_bytes is not None and n > self.max_bytes:
                self.refused += 1
                return False
            while self._items and (len(self._items) >= self.maxlen or
                                   (self.max_bytes is not None and self._bytes + n > self.max_bytes)):
                _, old = self._items.popleft()
                self._bytes -= old
                self.dropped += 1
            self._items.append((item, n))
            self._bytes += n
            self._cond.notify()
        return True

    def get(self, timeout: float = 0.0) -> T | None:
        """The oldest item, waiting up to ``timeout`` [s] for one; None if there is none."""
        with self._cond:
            if not self._items and timeout > 0:
                self._cond.wait(timeout)
            if not self._items:
                return None
            item, n = self._items.popleft()
            self._bytes -= n
            return item

    def __len__(self) -> int:
        return len(self._items)

    @property
    def nbytes(self) -> int:
        """Bytes queued now (0 without a byte bound)."""
        return self._bytes


class LatestPerKey(Generic[T]):
    """Thread-safe newest item per key, at most ``max_keys`` keys; ``drain`` takes them all.

    For messages where only the newest per sender matters (acknowledgements: a step index
    that only grows; liveliness: up or down): a flood on one key replaces that key's item
    and cannot push another key's item out, and a flood of new keys cannot crowd out the
    ``reserved`` ones. ``replaced`` counts items overwritten before
    they were taken, ``refused`` items for a new key when ``max_keys`` keys are held.
    """

    def __init__(self, max_keys: int, reserved: frozenset[str] = frozenset()) -> None:
        if max_keys < 1:
            raise ValueError(f"LatestPerKey: max_keys must be >= 1, got {max_keys}")
        self.max_keys = max_keys
        self.reserved = reserved  # keys always taken (the ones a daemon waits for), beyond max_keys
        self._items: dict[str, T] = {}
        self._cond = threading.Condition()
        self.replaced = 0
        self.refused = 0

    def put(self, key: str, item: T) -> bool:
        with self._cond:
            if key in self._items:
                self.replaced += 1
            elif len(self._items) >= self.max_keys and key not in self.reserved:
                self.refused += 1
                return False
            self._items[key] = item
            self._cond.notify()
        return True

    def drain(self, timeout: float = 0.0) -> dict[str, T]:
        """Every held item (and forget them), waiting up to ``timeout`` [s] for one."""
        with self._cond:
            if not self._items and timeout > 0:
                self._cond.wait(timeout)
            items, self._items = self._items, {}
            return items

    def __len__(self) -> int:
        return len(self._items)
