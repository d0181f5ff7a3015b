"""Foxglove 3D scene of a run (``foxglove.SceneUpdate``), for recordings and the live server.

One code path for both: ``ScenePublisher`` turns raw protocol payloads into scene updates
and logs them on a foxglove-sdk channel of a ``foxglove.Context``; the recorder's context
has an MCAP writer as its sink, ``sumoco foxglove`` gives its context a WebSocket server.
Building a scene is per-agent Python (the SDK's message objects), so it runs on a
``LatestWorker`` of its own: the transport thread only hands over bytes, and when scene
building falls behind the oldest pending payloads are dropped (counted), never the
transport.

Shown: the road network as lines, SUMO's reference footprints as translucent boxes,
every physics instance's actual agents as solid boxes, and the look-ahead points as red
spheres (the paper's debugging spheres). Scene frame ``map``: x east, y north, z up, the
SUMO network frame.
"""

from __future__ import annotations

import collections
import logging
import threading
from typing import Callable

import numpy as np

from protocol.codec import DEFAULT_LIMITS, MAX_AGENTS, DecodeLimits, decode, peek
from protocol.errors import ProtocolError
from protocol.frames import front_to_centre, sumo_angle_to_yaw
from protocol.keys import Keys
from protocol.messages import PhysicsState, StaticData, StepMessage

try:  # foxglove-sdk is optional (the `foxglove` extra): replay and report work without it
    import foxglove
    import foxglove.messages as fm
    from foxglove.channels import SceneUpdateChannel
except ImportError:  # pragma: no cover - exercised by the bare-install test
    foxglove = fm = SceneUpdateChannel = None

log = logging.getLogger(__name__)

SCENE_TOPIC = "/scene"
FRAME = "map"
_HEIGHT = np.array([1.5, 1.5, 3.0, 1.7, 1.8, 2.5])  # [m] box height per agent class
_COLORS = {
    "sumo": (0.9, 0.2, 0.2, 0.35),
    "paper": (0.2, 0.4, 0.9, 0.9),
    "default": (0.2, 0.7, 0.3, 0.9),
}
_PEDESTRIAN = 4


def available() -> bool:
    return fm is not None


def _ts(t: float):
    sec = int(t)
    return fm.Timestamp(sec=sec, nsec=int((t - sec) * 1e9))


def _boxes(x, y, angle, length, width, cls, color) -> list:
    yaw = sumo_angle_to_yaw(np.asarray(angle, float))
    length, width = np.asarray(length, float), np.asarray(width, float)
    cx, cy = front_to_centre(np.asarray(x, float), np.asarray(y, float), yaw, length)
    h = _HEIGHT[np.clip(np.asarray(cls, int), 0, len(_HEIGHT) - 1)]
    qz, qw = np.sin(yaw / 2).tolist(), np.cos(yaw / 2).tolist()
    cx, cy, hz, hl = cx.tolist(), cy.tolist(), h.tolist(), (h / 2).tolist()
    ln, wd = length.tolist(), width.tolist()
    col = fm.Color(r=color[0], g=color[1], b=color[2], a=color[3])
    Cube, Pose, V3, Q = fm.CubePrimitive, fm.Pose, fm.Vector3, fm.Quaternion
    return [
        Cube(pose=Pose(position=V3(x=cx[i], y=cy[i], z=hl[i]), orientation=Q(x=0.0, y=0.0, z=qz[i], w=qw[i])),
             size=V3(x=ln[i], y=wd[i], z=hz[i]), color=col)
        for i in range(len(cx))
    ]


def step_scene(msg: StepMessage):
    """SUMO's footprints and look-ahead points of one step (a ``SceneUpdate``)."""
    a = msg.agents
    keep = np.flatnonzero(a.cls != _PEDESTRIAN)
    lx, ly = a.la_x[keep].tolist(), a.la_y[keep].tolist()
    red = fm.Color(r=1.0, g=0.0, b=0.0, a=1.0)
    size = fm.Vector3(x=0.5, y=0.5, z=0.5)
    ident = fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    spheres = [fm.SpherePrimitive(pose=fm.Pose(position=fm.Vector3(x=lx[i], y=ly[i], z=0.3), orientation=ident),
                                  size=size, color=red) for i in range(len(lx))]
    ent = fm.SceneEntity(
        timestamp=_ts(msg.time), frame_id=FRAME, id="sumo",
        cubes=_boxes(a.x, a.y, a.angle, a.length, a.width, a.cls, _COLORS["sumo"]),
        spheres=spheres,
    )
    return fm.SceneUpdate(entities=[ent])


def physics_scene(msg: PhysicsState, instance: str, sizes: dict[str, tuple[float, float]]):
    """One physics instance's agents; ``sizes`` maps agent id -> (length, width) [m] from SUMO."""
    a = msg.agents
    lw = np.array([sizes.get(i, (4.5, 1.8)) for i in a.ids], float).reshape(-1, 2)
    ent = fm.SceneEntity(
        timestamp=_ts(msg.time), frame_id=FRAME, id=f"physics/{instance}",
        cubes=_boxes(a.x, a.y, a.heading, lw[:, 0], lw[:, 1], a.cls,
                     _COLORS.get(instance, (0.5, 0.5, 0.5, 0.9))),
    )
    return fm.SceneUpdate(entities=[ent])


def network_scene(static: StaticData):
    """The lanes as lines of their true width."""
    ln = static.lanes
    lines = []
    grey = fm.Color(r=0.35, g=0.35, b=0.38, a=1.0)
    for i in range(len(ln.ids)):
        pts = ln.shape_xy[ln.shape_offsets[i]:ln.shape_offsets[i + 1]].tolist()
        if len(pts) < 2:
            continue
        lines.append(fm.LinePrimitive(
            type=fm.LinePrimitiveLineType.LineStrip, thickness=float(ln.width[i]), scale_invariant=False,
            points=[fm.Point3(x=p[0], y=p[1], z=0.0) for p in pts], color=grey,
        ))
    # Lifetime 0: the network stays until replaced while the agents' entities update.
    ent = fm.SceneEntity(timestamp=_ts(0.0), frame_id=FRAME, id="network", lines=lines)
    return fm.SceneUpdate(entities=[ent])


class ScenePublisher:
    """Raw protocol payloads in, ``SceneUpdate``s out on ``/scene`` of a foxglove context.

    ``min_period_s`` thins the moving parts per key by simulated time (0: every message);
    the static network is always drawn. ``limits`` bound the decoding of steps and physics
    states (``[run] max_agents`` through ``RunConfig.decode_limits``; by default the largest
    run); static data is decoded with the default limits (its tables are not agents). Not
    thread-safe: feed it from one worker.
    """

    def __init__(self, context=None, min_period_s: float = 0.0, limits: DecodeLimits | None = None) -> None:
        if fm is None:
            raise ModuleNotFoundError("foxglove-sdk is not installed", name="foxglove")
        self.channel = SceneUpdateChannel(SCENE_TOPIC, context=context) if context is not None \
            else SceneUpdateChannel(SCENE_TOPIC)
        self.min_period_s = float(min_period_s)
        self.limits = limits or DecodeLimits.for_agents(MAX_AGENTS)
        self._sizes: dict[str, tuple[float, float]] = {}
        self._last_t: dict[str, float] = {}
        self._offered_t: dict[str, float] = {}
        self.updates = 0
        self.errors = 0
        self.thinned = 0

    @property
    def thinned_keys(self) -> frozenset[str]:
        """Keys whose last update time is kept for thinning."""
        return frozenset(self._last_t)

    @property
    def known_sizes(self) -> int:
        """Agents whose size (from the newest step) the physics scene draws with."""
        return len(self._sizes)

    def offer(self, topic: str, payload: bytes, t: float | None = None) -> bool:
        """Whether ``payload`` is worth queuing for ``feed``: a physics state not due by
        ``min_period_s`` is thinned here, on the producer's thread, from its time field alone.
        Every physics state used to wake the worker and be decoded in full before ``feed``
        thinned it: 90 % of a recording hub's scene work (two 50 Hz instances beside 10 Hz
        steps). Steps and static data always pass (the sizes come from every step). Called
        from one producer thread. ``t``: the message's time when the caller has decoded it
        already (the payload is then not parsed again)."""
        if not self.min_period_s or not topic.endswith("/state"):
            return True
        if t is None:
            try:
                t = peek(payload, ("t",), self.limits).get("t")
            except Exception:  # feed decodes it, counts the error and says why
                return True
        return not isinstance(t, float) or self._due(topic, t, self._offered_t)

    def _due(self, key: str, t: float, book: dict[str, float] | None = None) -> bool:
        """Whether ``key``'s message at ``t`` is drawn, by the last drawn time in ``book``
        (``feed``'s unless given)."""
        book = self._last_t if book is None else book
        last = book.get(key)
        if last is not None and last - 1.0 <= t < last + self.min_period_s - 1e-6:  # back > 1 s: restart
            self.thinned += 1
            return False
        book[key] = t
        return True

    def feed(self, topic: str, payload: bytes, stamp_ns: int | None = None, msg=None) -> bool:
        """Decode one payload and log its scene update; False when nothing was logged.
        ``msg``: the payload as the caller decoded it already (with these limits)."""
        parts = topic.split("/")
        is_step = parts[-2:] == ["sumo", "step"]
        is_static = parts[-2:] == ["sumo", "static"]
        is_physics = len(parts) >= 3 and parts[-3] == "physics" and parts[-1] == "state"
        if not (is_step or is_static or is_physics):
            return False
        try:
            if msg is None:
                msg = decode(payload, DEFAULT_LIMITS if is_static else self.limits)
            if is_static and isinstance(msg, StaticData):
                upd = network_scene(msg)
            elif is_step and isinstance(msg, StepMessage):
                a = msg.agents
                self._sizes = dict(zip(a.ids, zip(a.length.tolist(), a.width.tolist())))
                if not self._due(topic, msg.time):
                    return False
                upd = step_scene(msg)
            elif is_physics and isinstance(msg, PhysicsState):
                if not self._due(topic, msg.time):
                    return False
                upd = physics_scene(msg, Keys.instance_of(topic), self._sizes)
            else:
                raise ProtocolError(f"unexpected {type(msg).__name__}", topic)
        except Exception as e:  # a scene problem must never stop the raw recording or the server
            self.errors += 1
            log.debug("scene update failed for %s: %s", topic, e)
            return False
        if stamp_ns is None:
            self.channel.log(upd)
        else:
            self.channel.log(upd, log_time=stamp_ns)
        self.updates += 1
        return True


class LatestWorker:
    """A thread that handles items from a bounded queue that drops its *oldest* item when full.

    For views (scene building, live servers): the newest data matters, a backlog does not.
    ``put`` never blocks; ``dropped`` counts what was pushed out unhandled.
    """

    def __init__(self, handle: Callable[..., object], maxlen: int = 64, name: str = "latest-worker") -> None:
        self._handle = handle
        self._q: collections.deque = collections.deque(maxlen=maxlen)
        self._cv = threading.Condition()
        self._stop = False
        self.dropped = 0
        self.handled = 0
        self.failed = 0
        self._busy = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, *item) -> None:
        with self._cv:
            if len(self._q) == self._q.maxlen:
                self.dropped += 1
            self._q.append(item)
            self._cv.notify()

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._q and not self._stop:
                    self._busy = False
                    self._cv.notify_all()
                    self._cv.wait()
                if not self._q and self._stop:
                    self._busy = False
                    self._cv.notify_all()
                    return
                item = self._q.popleft()
                self._busy = True
            try:
                self._handle(*item)
                self.handled += 1
            except Exception:  # a bad item is logged and counted, the worker keeps going
                self.failed += 1
                log.exception("worker %s failed on an item", self._thread.name)

    def drain(self, timeout_s: float = 10.0) -> bool:
        """Wait until everything queued is handled; False on timeout."""
        with self._cv:
            return self._cv.wait_for(lambda: not self._q and not self._busy, timeout_s)

    def close(self, timeout_s: float = 10.0) -> None:
        """Handle what is queued, then stop the thread."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        self._thread.join(timeout_s)
