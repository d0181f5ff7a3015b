"""Viewer cameras as interest points of the physics level of detail (SPEC 3.7).

Every connected viewer or renderer puts its camera (the ground point it looks at) on
``<root>/<run>/viewer/<role>/<client>/camera`` at a low rate and holds a liveliness token
on ``.../alive``. Agents within the LOD radius of any camera run full physics. A camera
leaves when its token is deleted (the viewer closed or died) or when it has not been
updated for ``timeout_s``. Zenoh callbacks write, the daemon's main loop reads ``points``.
"""

from __future__ import annotations

import logging
import math
import threading
import time

import numpy as np
import zenoh

from protocol.codec import DecodeLimits, decode_as
from protocol.errors import ProtocolError
from protocol.keys import Keys
from protocol.messages import CameraPose

log = logging.getLogger(__name__)

MAX_CAMERA_BYTES = 1024  # a camera message is ~60 bytes; bigger ones are refused unread
MAX_CAMERAS = 64  # distinct cameras kept in all
#: cameras one identity (the key's ``<role>`` chunk: a certificate's role in the secure profile)
#: holds; one more of that role replaces the role's least recently updated camera
MAX_CAMERAS_PER_ROLE = 16
CAMERA_TIMEOUT_S = 5.0  # [s] without an update a camera is dropped (viewers send at ~2 Hz)
#: [s] with every slot taken, a new camera replaces the least recently updated one when that
#: one has been silent this long (two missed updates at ~2 Hz); otherwise it is refused
CAMERA_IDLE_S = 1.0
REJECT_LOG_PERIOD_S = 1.0  # [s] at most one log line per period about rejected cameras (a flood)
_LIMITS = DecodeLimits(max_agents=1, max_static_rows=16, max_points=1, max_bytes=MAX_CAMERA_BYTES)


class ViewerCameras:
    """The live camera points, keyed by ``<role>/<client>`` (thread-safe)."""

    def __init__(self, max_cameras: int = MAX_CAMERAS, timeout_s: float = CAMERA_TIMEOUT_S,
                 per_role: int = MAX_CAMERAS_PER_ROLE, idle_s: float = CAMERA_IDLE_S) -> None:
        self.max_cameras = int(max_cameras)
        self.per_role = int(per_role)
        self.timeout_s = float(timeout_s)
        self.idle_s = float(idle_s)
        self._lock = threading.Lock()
        self._cams: dict[str, tuple[float, float, float]] = {}  # who -> (x, y, monotonic time)
        self.rejected = 0
        self.refused = 0
        self.evicted = 0  # cameras replaced by a newer one (their role's cap, or idle with every slot taken)
        self._log_t = -math.inf

    def _reject(self, key: str, why: str) -> None:
        self.rejected += 1
        now = time.monotonic()
        if now - self._log_t >= REJECT_LOG_PERIOD_S:
            log.warning("rejected camera on %s (%d so far): %s", key, self.rejected, why)
            self._log_t = now

    def on_camera(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        who = Keys.viewer_of(key)
        if sample.kind != zenoh.SampleKind.PUT:
            self.forget(who)
            return
        size = len(sample.payload)  # checked before the payload is copied out of Zenoh's buffer
        if size > MAX_CAMERA_BYTES:
            return self._reject(key, f"{size} bytes, at most {MAX_CAMERA_BYTES}")
        data = sample.payload.to_bytes()
        try:
            msg = decode_as(data, CameraPose, _LIMITS)
        except ProtocolError as e:
            return self._reject(key, str(e))
        if not who or msg.id != who.split("/")[1]:
            return self._reject(key, f"id {msg.id!r} is not the key's client id")
        self.put(who, msg.x, msg.y)

    def on_alive(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            self.forget(Keys.viewer_of(str(sample.key_expr)))

    def put(self, who: str, x: float, y: float, now: float | None = None) -> bool:
        """Keep camera ``who`` (``<role>/<client>``) at (x, y) [m]. A new camera of a role that
        holds ``per_role`` replaces that role's least recently updated one; with all
        ``max_cameras`` taken it replaces the least recently updated camera if that one is
        idle (``idle_s``), else it is refused (counted). False when refused."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if who not in self._cams:
                role = who.split("/", 1)[0] + "/"
                mine = [w for w in self._cams if w.startswith(role)]
                if len(mine) >= self.per_role:
                    self._evict(min(mine, key=lambda w: self._cams[w][2]))
                elif len(self._cams) >= self.max_cameras:
                    idlest = min(self._cams, key=lambda w: self._cams[w][2])
                    if now - self._cams[idlest][2] < self.idle_s:
                        self.refused += 1
                        return False
                    self._evict(idlest)
            self._cams[who] = (float(x), float(y), now)
        return True

    def _evict(self, who: str) -> None:
        del self._cams[who]
        self.evicted += 1

    def forget(self, who: str) -> None:
        with self._lock:
            if self._cams.pop(who, None) is not None:
                log.info("camera %s left", who)

    def points(self, now: float | None = None) -> np.ndarray:
        """(m, 2) points [m] of the live cameras; stale ones are dropped here."""
        now = time.monotonic() if now is None else now
        with self._lock:
            for who in [w for w, c in self._cams.items() if now - c[2] > self.timeout_s]:
                del self._cams[who]
                log.info("camera %s timed out", who)
            return np.array([c[:2] for c in self._cams.values()], np.float64).reshape(-1, 2)

    def __len__(self) -> int:
        return len(self._cams)


__all__ = ["CAMERA_IDLE_S", "CAMERA_TIMEOUT_S", "MAX_CAMERAS", "MAX_CAMERAS_PER_ROLE", "ViewerCameras"]
