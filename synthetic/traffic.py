"""Synthetic traffic for benchmarks, tests and the viewer's demo feed (no SUMO, no MuJoCo).

- ``synthetic_step``: a StepMessage of n random but plausible agents (codec and transport
  benchmarks);
- ``circle_traffic``: cars on concentric circular lanes with their path ahead (physics
  benchmarks and daemon tests);
- ``FakeRun``: a grid of signalised junctions with agents moving through it, its static
  data and physics states (the viewer's demo feed, ``synthetic.feed``).

Pure functions of their arguments (seeded); this module imports only ``protocol``.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from protocol.frames import yaw_to_sumo_angle
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

def synthetic_step(n: int, seed: int = 0, path_points: int = 0, step: int = 1) -> StepMessage:
    """A StepMessage of ``n`` plausible agents (ids like SUMO's randomTrips ids)."""
    rng = np.random.default_rng(seed)
    f32 = np.float32
    ids = [f"veh{i}" for i in range(n)]
    x = rng.uniform(0, 2000, n)
    y = rng.uniform(0, 2000, n)
    off = np.arange(n + 1, dtype=np.uint32) * path_points
    xy = (rng.uniform(0, 2000, (n * path_points, 2))).astype(f32)
    agents = AgentBatch(
        ids=ids,
        cls=rng.integers(0, len(AgentClass), n).astype(np.uint8),
        vtype=np.zeros(n, np.uint16),
        x=x, y=y,
        angle=rng.uniform(0, 360, n).astype(f32),
        speed=rng.uniform(0, 15, n).astype(f32),
        accel=rng.uniform(-3, 3, n).astype(f32),
        signals=rng.integers(0, 16, n).astype(np.uint16),
        la_x=(x + 7).astype(f32), la_y=(y + 1).astype(f32),
        length=np.full(n, 5.0, f32), width=np.full(n, 1.8, f32),
        lane=rng.integers(0, 500, n).astype(np.int32),
        flags=np.zeros(n, np.uint8),
        path_offsets=off if path_points else np.zeros(0, np.uint32),
        path_xy=xy if path_points else np.zeros((0, 2), f32),
    )
    return StepMessage("bench", step, step * 0.1, 0.1, agents, TrafficLights.empty(),
                       [VType("DEFAULT_VEHTYPE", "passenger")])



LANE_R0 = 300.0  # [m] radius of the innermost circular lane
LANE_GAP = 4.0  # [m] between lanes
CAR_GAP = 22.0  # [m] arc length between cars on a lane
PATH_POINTS = 12  # vertices of each path ahead
PATH_LENGTH = 25.0  # [m] path ahead (LAD_max + margin)


def _lanes(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Lane and position index of each of n cars: lanes filled in turn, CAR_GAP apart."""
    lane = np.zeros(n, np.int64)
    slot = np.zeros(n, np.int64)
    i, k = 0, 0
    while i < n:
        cap = int(2 * np.pi * (LANE_R0 + LANE_GAP * k) // CAR_GAP)
        m = min(cap, n - i)
        lane[i:i + m] = k
        slot[i:i + m] = np.arange(m)
        i += m
        k += 1
    return lane, slot


def circle_traffic(n: int, step: int, step_s: float = 0.1, speed: float = 10.0,
                   cls: AgentClass = AgentClass.PASSENGER, run: str = "bench", id_prefix: str = "veh",
                   centre: tuple[float, float] = (1000.0, 1000.0)) -> StepMessage:
    """Step ``step`` of ``n`` agents driving counter-clockwise on concentric circular lanes.

    Lanes (radius LANE_R0 + k * LANE_GAP) are filled with cars CAR_GAP apart; every agent
    keeps constant speed ``speed`` [m/s].
    """
    lane, slot = _lanes(n)
    R = LANE_R0 + LANE_GAP * lane
    t = step * step_s
    th = (slot * CAR_GAP + speed * t) / R  # angle on the circle (ccw)
    x = centre[0] + R * np.cos(th)
    y = centre[1] + R * np.sin(th)
    yaw = th + np.pi / 2
    ds = np.linspace(0.0, PATH_LENGTH, PATH_POINTS)
    pth = th[:, None] + ds[None, :] / R[:, None]
    pxy = np.stack([centre[0] + R[:, None] * np.cos(pth), centre[1] + R[:, None] * np.sin(pth)], axis=-1)
    la = th + 7.0 / R
    f32 = np.float32
    batch = AgentBatch(
        ids=[f"{id_prefix}{k}" for k in range(n)], cls=np.full(n, int(cls), np.uint8), vtype=np.zeros(n, np.uint16),
        x=x, y=y, angle=yaw_to_sumo_angle(yaw).astype(f32), speed=np.full(n, speed, f32), accel=np.zeros(n, f32),
        signals=np.zeros(n, np.uint16), la_x=(centre[0] + R * np.cos(la)).astype(f32),
        la_y=(centre[1] + R * np.sin(la)).astype(f32), length=np.full(n, 5.0, f32), width=np.full(n, 1.8, f32),
        lane=lane.astype(np.int32), flags=np.full(n, 8 if step == 0 else 0, np.uint8),
        path_offsets=(np.arange(n + 1) * PATH_POINTS).astype(np.uint32), path_xy=pxy.reshape(-1, 2).astype(f32),
    )
    vt = [VType("car", "passenger")]
    return StepMessage(run, step, t, step_s, batch, TrafficLights.empty(), vt)




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

    def signals(self, k: int) -> np.ndarray:
        """SUMO signal bits of step k: brake lights on a sixth of the vehicles (changing every
        2 s), left (2) / right (1) blinkers on a ninth each; none for pedestrians."""
        i = np.arange(self.n)
        sig = np.where((i + k // 20) % 6 == 0, 8, 0) | np.where(i % 9 == 1, 2, 0) | np.where(i % 9 == 2, 1, 0)
        return np.where(self.cls == 4, 0, sig).astype(np.uint16)

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
            speed=self.speed.copy(), accel=np.zeros(n, np.float32), signals=self.signals(k),
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
