"""A synthetic run for trying and testing the viewer without SUMO or MuJoCo.

``FakeRun`` builds a grid of signalised four-way junctions (two lanes each way plus
sidewalks) and moves agents along straight corridors through it; ``FakePublisher`` puts
its step messages, physics states (one or more instances) and static data (queryable) on
Zenoh with the real key layout and liveliness tokens, so ``sumoco view`` cannot tell it
from a real run. Run it by hand next to ``sumoco view``::

    python -m sumoco.viewer.synthetic --listen tcp/127.0.0.1:7447 --grid 3 --agents 1000
    sumoco view --connect tcp/127.0.0.1:7447 --run synthetic
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from typing import Any

import numpy as np

from protocol.codec import encode
from protocol.keys import Keys
from protocol.messages import (
    AgentBatch,
    AgentClass,
    JunctionTable,
    TlsLinks,
    LaneTable,
    PhysicsAgents,
    PhysicsState,
    StaticData,
    StepMessage,
    TrafficLights,
    VType,
)

log = logging.getLogger(__name__)

LANE_W = 3.2  # [m] vehicle lane width
WALK_W = 2.0  # [m] sidewalk width
VTYPES = [VType("car", "passenger"), VType("taxi", "taxi"), VType("bus", "bus"),
          VType("bike", "bicycle"), VType("ped", "pedestrian")]
SIZES = np.array([[4.5, 1.8], [4.6, 1.8], [12.0, 2.5], [1.8, 0.65], [0.3, 0.5]], np.float32)  # [m]
# TLS program: 8 links (W, S, E, N approaches x 2 lanes), 30 s cycle.
TLS_PHASES = [(12.0, "GGrrGGrr"), (3.0, "yyrryyrr"), (12.0, "rrGGrrGG"), (3.0, "rryyrryy")]


class FakeRun:
    """Geometry and motion of the synthetic run (pure functions of time)."""

    def __init__(self, grid: int = 1, n: int = 50, run: str = "synthetic", seed: int = 0,
                 spacing: float = 200.0, stub: float = 100.0, dt: float = 0.1) -> None:
        self.grid, self.n, self.run, self.dt = grid, n, run, dt
        self.D, self.L0 = spacing, stub
        self.h = 2 * LANE_W + WALK_W  # junction half size [m]
        rng = np.random.default_rng(seed)
        self._build_network()
        # Agents: ~5 % pedestrians on sidewalk tracks, the rest on lane tracks.
        n_ped = max(1, n // 20) if n >= 10 else 0
        cls = rng.choice([0, 1, 2, 3], size=n - n_ped, p=[0.75, 0.08, 0.07, 0.10])
        self.cls = np.concatenate([cls, np.full(n_ped, 4)]).astype(np.uint8)
        veh_tracks = np.flatnonzero(~self.track_walk)
        walk_tracks = np.flatnonzero(self.track_walk)
        self.track = np.concatenate([veh_tracks[np.arange(n - n_ped) % len(veh_tracks)],
                                     walk_tracks[np.arange(n_ped) % len(walk_tracks)]])
        # Evenly spread along each track so footprints never overlap; one speed per track.
        self.u0 = np.zeros(n)
        for t in np.unique(self.track):
            idx = np.flatnonzero(self.track == t)
            self.u0[idx] = (np.arange(len(idx)) + rng.uniform(0, 0.3)) * self.span / len(idx)
        track_speed = np.where(self.track_walk, 1.3, rng.uniform(7.0, 13.0, len(self.track_walk)))
        self.speed = track_speed[self.track].astype(np.float32)
        self.ids = [f"{VTYPES[c].id}{i}" for i, c in enumerate(self.cls)]
        self.length = SIZES[self.cls, 0]
        self.width = SIZES[self.cls, 1]

    # ------------------------------------------------------------------ network
    def _build_network(self) -> None:
        G, D, L0, h = self.grid, self.D, self.L0, self.h
        self.u_min, self.u_max = -L0, (G - 1) * D + L0
        self.span = self.u_max - self.u_min
        # Piece boundaries along every corridor: stub, (junction, link)*, junction, stub.
        b = [self.u_min]
        for k in range(G):
            b += [k * D - h, k * D + h]
        b.append(self.u_max)
        self.bounds_u = np.array(b)
        ids, edges, widths, allow, shapes, lens = [], [], [], [], [], []
        tracks = []  # (base xy, axis, travel dir, lateral offset right of travel, walk?)
        for orient in ("h", "v"):
            axis = np.array([1.0, 0.0]) if orient == "h" else np.array([0.0, 1.0])
            for c in range(G):
                base = np.array([0.0, c * D]) if orient == "h" else np.array([c * D, 0.0])
                for d in (1, -1):
                    for k in range(2):
                        tracks.append((base, axis, d, (2 - k - 0.5) * LANE_W, False, f"{orient}{c}{'p' if d > 0 else 'm'}", k))
                    tracks.append((base, axis, d, 2 * LANE_W + WALK_W / 2, True, f"{orient}{c}{'p' if d > 0 else 'm'}w", 0))
        self.track_walk = np.array([t[4] for t in tracks])
        n_pieces = len(self.bounds_u) - 1
        self.track_lane = np.full((len(tracks), n_pieces), -1, np.int32)
        self.track_base = np.array([t[0] for t in tracks])
        self.track_axis = np.array([t[1] for t in tracks])
        self.track_dir = np.array([t[2] for t in tracks], float)
        self.track_off = np.array([t[3] for t in tracks])
        for ti, (base, axis, d, off, walk, name, k) in enumerate(tracks):
            t = axis * d
            right = np.array([t[1], -t[0]])
            for p in range(n_pieces):
                in_junction = p % 2 == 1
                if walk and in_junction:
                    continue  # sidewalks end at the junction (crossings are left out)
                u0, u1 = self.bounds_u[p], self.bounds_u[p + 1]
                a, z = (u0, u1) if d > 0 else (u1, u0)
                pts = np.array([base + a * axis + off * right, base + z * axis + off * right])
                lane_name = (f":J{p // 2}_{name}_{k}" if in_junction else f"{name}{p // 2}_{k}")
                self.track_lane[ti, p] = len(ids)
                ids.append(lane_name)
                edges.append(lane_name.rsplit("_", 1)[0])
                widths.append(WALK_W if walk else LANE_W)
                allow.append(["pedestrian"] if walk else ["passenger", "taxi", "bus", "bicycle"])
                shapes.append(pts)
                lens.append(abs(u1 - u0))
        off = np.concatenate([[0], np.cumsum([len(s) for s in shapes])]).astype(np.uint32)
        self.lanes = LaneTable(ids, edges, np.array(widths, np.float32), np.array(lens, np.float32),
                               allow, off, np.concatenate(shapes).astype(np.float32))
        jids, jshapes = [], []
        for i in range(G):
            for j in range(G):
                cx, cy = i * D, j * D
                jids.append(f"J{i}_{j}")
                jshapes.append(np.array([[cx - h, cy - h], [cx + h, cy - h], [cx + h, cy + h], [cx - h, cy + h]]))
        joff = np.arange(len(jids) + 1, dtype=np.uint32) * 4
        self.junctions = JunctionTable(jids, joff, np.concatenate(jshapes).astype(np.float32))

    def static(self) -> StaticData:
        e = self.L0 + self.h
        hi = (self.grid - 1) * self.D
        return StaticData(
            run=self.run, step_length=self.dt, net_offset=(0.0, 0.0), projection="!",
            bounds=(-e, -e, hi + e, hi + e), lanes=self.lanes, junctions=self.junctions,
            vtypes=list(VTYPES), vtype_length=SIZES[:, 0].copy(), vtype_width=SIZES[:, 1].copy(),
            tls_ids=list(self.junctions.ids),
            tls_links=self._tls_links(),
        )

    def _tls_links(self) -> TlsLinks:
        """Each junction's 8 links (state order: east/west-bound lanes 0,1 and 4,5; north/
        south-bound 2,3 and 6,7), each controlling the road lane that ends at it."""
        G, rows = self.grid, []
        for ti in np.flatnonzero(~self.track_walk):
            k = int(ti % 3)  # tracks come in groups: lane 0, lane 1, sidewalk
            horiz = self.track_axis[ti][0] == 1.0
            c = int(round((self.track_base[ti][1] if horiz else self.track_base[ti][0]) / self.D))
            forward = self.track_dir[ti] > 0
            for i in range(G):
                lane = self.track_lane[ti, 2 * i if forward else 2 * i + 2]
                jx, jy = (i, c) if horiz else (c, i)
                link = (0 if horiz else 2) + (0 if forward else 4) + k
                rows.append((jx * G + jy, link, lane))
        a = np.array(rows, np.int64)
        none = np.full(len(a), -1, np.int32)
        return TlsLinks(a[:, 0].astype(np.uint16), a[:, 1].astype(np.uint16), a[:, 2].astype(np.int32), none, none)

    # ------------------------------------------------------------------ motion
    def _pose(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Front-bumper positions (x, y), heading [deg cw from north] and travel vectors at time t."""
        tr = self.track
        s = (self.u0 + self.speed * t) % self.span  # distance travelled along the track
        d = self.track_dir[tr]
        u = np.where(d > 0, self.u_min + s, self.u_max - s)
        axis = self.track_axis[tr]
        tvec = axis * d[:, None]
        right = np.stack([tvec[:, 1], -tvec[:, 0]], axis=1)
        xy = self.track_base[tr] + u[:, None] * axis + self.track_off[tr][:, None] * right
        angle = np.degrees(np.arctan2(tvec[:, 0], tvec[:, 1])) % 360.0
        return xy, angle, tvec, u

    def tls_state(self, t: float) -> tuple[str, int, float]:
        cycle = sum(p[0] for p in TLS_PHASES)
        x = t % cycle
        for i, (dur, state) in enumerate(TLS_PHASES):
            if x < dur:
                return state, i, dur - x
            x -= dur
        return TLS_PHASES[-1][1], len(TLS_PHASES) - 1, 0.0

    def step(self, k: int) -> StepMessage:
        t = k * self.dt
        xy, angle, tvec, u = self._pose(t)
        n = self.n
        lad = np.clip(self.speed * 1.0, 7.0, 10.0)  # SPEC 4 with k_LAD = 1 s
        la = xy + tvec * lad[:, None]
        piece = np.clip(np.searchsorted(self.bounds_u, u, side="right") - 1, 0, len(self.bounds_u) - 2)
        path = np.stack([xy, xy + tvec * 20.0], axis=1).reshape(-1, 2)
        agents = AgentBatch(
            ids=list(self.ids), cls=self.cls.copy(), vtype=self.cls.astype(np.uint16),
            x=xy[:, 0].copy(), y=xy[:, 1].copy(), angle=angle.astype(np.float32),
            speed=self.speed.copy(), accel=np.zeros(n, np.float32), signals=np.zeros(n, np.uint16),
            la_x=la[:, 0].astype(np.float32), la_y=la[:, 1].astype(np.float32),
            length=self.length.copy(), width=self.width.copy(),
            lane=self.track_lane[self.track, piece].astype(np.int32),
            flags=np.where(np.arange(n) == 0, 2, 0).astype(np.uint8),  # agent 0 plays the ego
            path_offsets=(np.arange(n + 1) * 2).astype(np.uint32), path_xy=path.astype(np.float32),
        )
        state, phase, nxt = self.tls_state(t)
        m = len(self.junctions.ids)
        tls = TrafficLights(list(self.junctions.ids), [state] * m, np.full(m, phase, np.int32),
                            np.full(m, nxt, np.float32))
        return StepMessage(self.run, k, t, self.dt, agents, tls, list(VTYPES))

    def physics(self, tick: int, t: float, sumo_step: int, gain: float = 1.0) -> PhysicsState:
        """Physics 'actual' poses: the reference plus a small, smooth tracking error."""
        xy, angle, tvec, _ = self._pose(t)
        n = self.n
        ph = np.arange(n) * 0.7 + t
        lat = (0.35 * gain * np.sin(ph)).astype(np.float32)  # [m] + = left
        lon = (-0.4 * gain + 0.2 * np.cos(ph)).astype(np.float32)  # [m] + = ahead
        left = np.stack([-tvec[:, 1], tvec[:, 0]], axis=1)
        pxy = xy + tvec * lon[:, None] + left * lat[:, None]
        z = np.zeros(n, np.float32)
        agents = PhysicsAgents(
            ids=list(self.ids), cls=self.cls.copy(), mode=np.where(self.cls == 4, 1, 0).astype(np.uint8),
            x=pxy[:, 0].copy(), y=pxy[:, 1].copy(), z=z + 0.5,
            heading=(angle + 3.0 * gain * np.sin(ph)).astype(np.float32) % 360.0,
            roll=z, pitch=z, speed=self.speed.copy(), steer=z, drive=z + 50.0, brake=z,
            err_lon=lon, err_lat=lat,
        )
        return PhysicsState(self.run, tick, t, sumo_step, agents, {"collisions": 0, "placements": n})


class FakePublisher:
    """Publishes a ``FakeRun`` on a Zenoh session in a background thread, in real time."""

    def __init__(self, session: Any, fake: FakeRun, root: str = "sumoco", step_hz: float = 10.0,
                 physics_hz: float = 20.0, instances: tuple[str, ...] = ("paper", "default")) -> None:
        self.session, self.fake = session, fake
        self.keys = Keys(root, fake.run)
        self.step_hz, self.physics_hz, self.instances = step_hz, physics_hz, instances
        self.static_bytes = encode(fake.static())
        self.steps_sent = 0
        self.static_queries = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="fake-run", daemon=True)
        self._decl: list[Any] = []

    def _on_query(self, query: Any) -> None:
        self.static_queries += 1
        query.reply(self.keys.static, self.static_bytes)

    def start(self) -> "FakePublisher":
        s, k = self.session, self.keys
        self._decl.append(s.declare_queryable(k.static, self._on_query))
        self._decl.append(s.liveliness().declare_token(k.sumo_alive))
        self._step_pub = s.declare_publisher(k.step)
        self._phys_pubs = {}
        for inst in self.instances:
            ki = Keys(k.root, k.run, inst)
            self._phys_pubs[inst] = s.declare_publisher(ki.physics_state)
            self._decl.append(s.liveliness().declare_token(ki.physics_alive))
        self._decl += [self._step_pub, *self._phys_pubs.values()]
        self._thread.start()
        return self

    def _loop(self) -> None:
        t0 = time.monotonic()
        next_step, next_phys = 0, 0
        while not self._stop.is_set():
            now = time.monotonic() - t0
            if now >= next_step / self.step_hz:
                self._step_pub.put(encode(self.fake.step(next_step)))
                self.steps_sent += 1
                next_step += 1
            if self.instances and now >= next_phys / self.physics_hz:
                t = next_phys / self.physics_hz * self.step_hz * self.fake.dt  # same clock as steps
                for j, (inst, pub) in enumerate(self._phys_pubs.items()):
                    pub.put(encode(self.fake.physics(next_phys, t, next_step - 1, gain=1.0 + j)))
                next_phys += 1
            wait = min(next_step / self.step_hz,
                       next_phys / self.physics_hz if self.instances else 1e9) - (time.monotonic() - t0)
            if wait > 0:
                self._stop.wait(wait)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for d in reversed(self._decl):
            try:
                d.undeclare()
            except Exception:  # already gone with the session
                pass


def main(argv: list[str] | None = None) -> int:
    from sumoco.config import ZenohConfig
    from sumoco.logs import setup_logging
    from sumoco.transport import open_session

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--listen", default="tcp/127.0.0.1:7447", help="zenoh endpoint to listen on")
    ap.add_argument("--run", default="synthetic")
    ap.add_argument("--root", default="sumoco")
    ap.add_argument("--grid", type=int, default=2, help="junctions per side")
    ap.add_argument("--agents", type=int, default=200)
    ap.add_argument("--hz", type=float, default=10.0, help="step messages per second")
    args = ap.parse_args(argv)
    setup_logging()
    fake = FakeRun(grid=args.grid, n=args.agents, run=args.run)
    with open_session(ZenohConfig(listen=(args.listen,))) as session:
        pub = FakePublisher(session, fake, root=args.root, step_hz=args.hz).start()
        log.info("synthetic run %r: %d agents on %dx%d junctions, listening on %s",
                 args.run, args.agents, args.grid, args.grid, args.listen)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            pub.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
