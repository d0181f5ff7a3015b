"""The road network as a glTF 2.0 binary (GLB) that any engine loads as it is.

Built from the network file alone (``sumo_side.netfile``: no libsumo, no sumolib), so it
works in a bare ``pip install sumoco``; the SUMO daemon serves the same bytes through its
static-data queryable. What is in the file (SPEC.md, "Map as glTF"):

- road surfaces per lane with their true widths (asphalt; bicycle and rail lanes in their
  own materials), junction surfaces, sidewalks and walking areas (raised a little),
  pedestrian crossings with zebra stripes;
- lane markings: between lanes of one edge dashed where SUMO lets cars change lanes,
  solid where its ``changeLeft``/``changeRight`` forbid it, solid outer lines, and stop
  lines where a link is signalised or has to yield;
- one node per traffic-light head, named ``tls/<tls id>/<link index>``, over the end of
  the lane that link leaves, so an engine colours it from the step message's ``tls``
  state strings (letter ``link index`` of that light's string).

Frames: SUMO (x east, y north, z up) -> glTF (X east, Y up, Z south): ``X = x - ox``,
``Y = z``, ``Z = -(y - oy)``. ``(ox, oy)`` is the map origin: (0, 0) for networks within
10 km of SUMO's origin, else the centre of the network's bounds rounded to whole
kilometres, so float32 vertices keep millimetres in UTM-sized networks. The root node
``sumoco_map`` carries the origin as its translation and ``scene.extras.sumoco`` repeats
it with the netOffset and projection.
"""

from __future__ import annotations

import hashlib
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import mapbox_earcut
import msgpack
import numpy as np
import pygltflib

from protocol.messages import SCHEMA_VERSION

from sumo_side.netfile import NetGeometry, NetLane, read_net

log = logging.getLogger(__name__)

#: Networks reaching further than this from SUMO's origin get a local map origin [m].
LOCAL_ORIGIN_LIMIT_M = 10_000.0
#: Vehicle class that decides whether a lane boundary is dashed (may change) or solid.
MARKING_CLASS = "passenger"
#: Link states that need a stop line (SUMO letters: minor, equal, stop, all-way stop).
YIELD_STATES = frozenset("m=sw")

# Heights above the road surface [m]: separate layers that lie on top of each other.
Z_JUNCTION = 0.0
Z_LANE = 0.01
Z_SPECIAL_LANE = 0.015
Z_CROSSING = 0.02
Z_MARKING = 0.03
Z_SIDEWALK = 0.12
#: Traffic-light head: box size [m] (width, height, depth) and height of its centre [m].
HEAD_SIZE = (0.45, 1.1, 0.35)
HEAD_HEIGHT = 5.0

DASH_M, GAP_M = 3.0, 6.0  # urban lane-separator rhythm [m]
LINE_M = 0.15  # marking line width [m]
STOP_LINE_M = 0.4  # stop line depth [m]
ZEBRA_M = 0.5  # zebra bar and gap along the walking direction [m]

#: Material name -> (base colour RGBA linear, roughness).
MATERIALS: dict[str, tuple[tuple[float, float, float, float], float]] = {
    "asphalt": ((0.05, 0.055, 0.06, 1.0), 0.95),
    "bike_lane": ((0.30, 0.08, 0.06, 1.0), 0.9),
    "rail": ((0.16, 0.13, 0.10, 1.0), 0.95),
    "sidewalk": ((0.38, 0.37, 0.35, 1.0), 0.9),
    "crossing": ((0.06, 0.065, 0.07, 1.0), 0.95),
    "marking": ((0.85, 0.85, 0.82, 1.0), 0.6),
    "tls_head": ((0.02, 0.02, 0.02, 1.0), 0.5),
}


# ----------------------------------------------------------------------------- 2D geometry


def dedupe(p: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Drop consecutive points closer than ``eps`` [m]."""
    if len(p) < 2:
        return p
    keep = np.ones(len(p), bool)
    keep[1:] = np.hypot(*np.diff(p, axis=0).T) > eps
    return p[keep]


def left_normals(p: np.ndarray) -> np.ndarray:
    """Per-vertex unit-ish normals pointing left of the direction of travel (miter joins).

    A vertex normal is scaled by 1/cos(half the turn) so that offset lines keep their
    distance from the centre line; the scale is capped at 3 for very sharp turns.
    """
    d = np.diff(p, axis=0)
    d /= np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)[:, None]
    seg_n = np.column_stack([-d[:, 1], d[:, 0]])
    n = np.empty_like(p)
    n[0], n[-1] = seg_n[0], seg_n[-1]
    if len(p) > 2:
        mid = seg_n[:-1] + seg_n[1:]
        length = np.hypot(mid[:, 0], mid[:, 1])
        ok = length > 1e-9
        mid[ok] /= length[ok, None]
        mid[~ok] = seg_n[1:][~ok]  # a U-turn on the spot: fall back to the next segment
        cos_half = np.einsum("ij,ij->i", mid, seg_n[1:])
        n[1:-1] = mid / np.maximum(cos_half, 1 / 3)[:, None]
    return n


def offset(p: np.ndarray, dist: float, normals: np.ndarray | None = None) -> np.ndarray:
    """The polyline moved ``dist`` metres to its left (negative: right)."""
    return p + (left_normals(p) if normals is None else normals) * dist


def ribbon(p: np.ndarray, left: float, right: float) -> tuple[np.ndarray, np.ndarray]:
    """A strip from ``right`` m right of ``p`` to ``left`` m left of it.

    Returns vertices (2m, 2) [m] and counter-clockwise triangles (2(m-1), 3).
    """
    n = left_normals(p)
    m = len(p)
    verts = np.empty((2 * m, 2))
    verts[0::2] = p + n * left  # even: left edge
    verts[1::2] = p - n * right  # odd: right edge
    i = np.arange(m - 1)
    li, ri, lj, rj = 2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3
    tris = np.concatenate([np.column_stack([ri, rj, li]), np.column_stack([rj, lj, li])])
    return verts, tris


def cut(p: np.ndarray, s0: float, s1: float, cum: np.ndarray | None = None) -> np.ndarray:
    """The piece of polyline ``p`` between arc lengths ``s0`` and ``s1`` [m]."""
    if cum is None:
        cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])
    inner = p[(cum > s0) & (cum < s1)]
    a = np.array([np.interp(s0, cum, p[:, 0]), np.interp(s0, cum, p[:, 1])])
    b = np.array([np.interp(s1, cum, p[:, 0]), np.interp(s1, cum, p[:, 1])])
    return np.vstack([a, inner, b])


def dashes(p: np.ndarray, dash: float, gap: float, start: float | None = None) -> list[np.ndarray]:
    """Pieces ``dash`` m long every ``dash + gap`` m along ``p``, centred on its length."""
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])
    total = cum[-1]
    period = dash + gap
    if total < dash:
        return []
    if start is None:
        n = int((total - dash) // period) + 1
        start = (total - (n - 1) * period - dash) / 2
    out = []
    s = start
    while s + dash <= total + 1e-9:
        out.append(cut(p, s, min(s + dash, total), cum))
        s += period
    return out


def polygon(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated polygon (earcut): vertices (k, 2) and triangles (t, 3)."""
    p = dedupe(p)
    if len(p) > 3 and np.allclose(p[0], p[-1]):
        p = p[:-1]
    if len(p) < 3:
        return np.zeros((0, 2)), np.zeros((0, 3), np.int64)
    idx = mapbox_earcut.triangulate_float64(p, np.array([len(p)], np.uint32))
    return p, np.asarray(idx, np.int64).reshape(-1, 3)


# ----------------------------------------------------------------------------- layers


@dataclass
class Layer:
    """Flat surfaces of one material at one height, collected from many pieces."""

    name: str
    material: str
    z: float
    verts: list[np.ndarray] = field(default_factory=list)
    tris: list[np.ndarray] = field(default_factory=list)
    count: int = 0

    def add(self, verts: np.ndarray, tris: np.ndarray) -> None:
        if len(tris) == 0:
            return
        self.verts.append(verts)
        self.tris.append(tris + self.count)
        self.count += len(verts)

    def add_ribbon(self, p: np.ndarray, left: float, right: float) -> None:
        p = dedupe(p)
        if len(p) >= 2:
            self.add(*ribbon(p, left, right))

    def arrays(self, origin: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        """glTF positions (float32, n x 3) and triangles (uint32, t x 3), all facing up."""
        v = np.concatenate(self.verts) - np.asarray(origin)  # local first: float64 precision near 0
        t = np.concatenate(self.tris)
        # Every face must face up (+Y): flip the clockwise ones (earcut's and miters' output).
        a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
        cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        flip = cross < 0
        t[flip] = t[flip][:, [0, 2, 1]]
        t = t[np.abs(cross) > 1e-9]  # degenerate slivers add nothing and upset validators
        pos = np.column_stack([v[:, 0], np.full(len(v), self.z), -v[:, 1]])
        return pos.astype(np.float32), t.astype(np.uint32)


@dataclass(frozen=True)
class SignalHead:
    """One traffic-light head: the link ``link`` of light ``tls`` at the end of ``lane``."""

    tls: str
    link: int
    lane: str
    x: float
    """Position over the end of the lane [m, network frame]."""
    y: float
    heading: float
    """Direction of travel at the lane's end [rad, counter-clockwise from east]."""

    @property
    def name(self) -> str:
        return f"tls/{self.tls}/{self.link}"


@dataclass(frozen=True)
class MapMesh:
    """An exported map: the GLB bytes and what is in them."""

    glb: bytes
    sha256: str
    origin: tuple[float, float]
    """Map origin [m, network frame], subtracted from every vertex."""
    layers: dict[str, tuple[int, int]]
    """Layer name -> (vertices, triangles)."""
    heads: int
    """Traffic-light head nodes."""
    seconds: float
    """Time the export took [s]."""

    @property
    def vertices(self) -> int:
        return sum(v for v, _ in self.layers.values())

    @property
    def triangles(self) -> int:
        return sum(t for _, t in self.layers.values())


def map_origin(bounds: tuple[float, float, float, float]) -> tuple[float, float]:
    """(0, 0) near SUMO's origin, else the bounds' centre rounded to whole kilometres [m]."""
    if max(abs(b) for b in bounds) <= LOCAL_ORIGIN_LIMIT_M:
        return (0.0, 0.0)
    return (round((bounds[0] + bounds[2]) / 2, -3), round((bounds[1] + bounds[3]) / 2, -3))


# ----------------------------------------------------------------------------- the network


def _vehicle_lane(ln: NetLane) -> bool:
    return ln.function == "normal" and not ln.pedestrian_only and bool(ln.allow)


def _may_change(perm: frozenset[str] | None) -> bool:
    return perm is None or MARKING_CLASS in perm


def _near(p: np.ndarray, q: np.ndarray) -> float:
    """Distance from the middle point of ``p`` to the nearest vertex of ``q`` [m]."""
    mid = p[len(p) // 2]
    return float(np.min(np.hypot(q[:, 0] - mid[0], q[:, 1] - mid[1])))


def build_layers(net: NetGeometry) -> tuple[dict[str, Layer], list[SignalHead]]:
    """Every surface and marking of ``net`` as flat layers, plus the signal heads."""
    L = {name: Layer(name, mat, z) for name, mat, z in (
        ("junctions", "asphalt", Z_JUNCTION), ("lanes", "asphalt", Z_LANE),
        ("bike_lanes", "bike_lane", Z_SPECIAL_LANE), ("rail_lanes", "rail", Z_SPECIAL_LANE),
        ("sidewalks", "sidewalk", Z_SIDEWALK), ("crossings", "crossing", Z_CROSSING),
        ("markings", "marking", Z_MARKING))}
    for shape in net.junctions.values():
        L["junctions"].add(*polygon(shape))
    edges: dict[str, list[NetLane]] = {}
    for ln in net.lanes:
        half = ln.width / 2
        if ln.function == "walkingarea":
            L["sidewalks"].add(*polygon(ln.shape))
        elif ln.function == "crossing":
            L["crossings"].add_ribbon(ln.shape, half, half)
            for bar in dashes(dedupe(ln.shape), ZEBRA_M, ZEBRA_M):
                L["markings"].add_ribbon(bar, 0.4 * ln.width, 0.4 * ln.width)
        elif ln.pedestrian_only:
            L["sidewalks"].add_ribbon(ln.shape, half, half)
        elif ln.bicycle_only:
            L["bike_lanes"].add_ribbon(ln.shape, half, half)
        elif ln.rail_only:
            L["rail_lanes"].add_ribbon(ln.shape, half, half)
        else:
            L["lanes"].add_ribbon(ln.shape, half, half)
        if _vehicle_lane(ln):
            edges.setdefault(ln.edge, []).append(ln)
    for lanes in edges.values():
        _edge_markings(sorted(lanes, key=lambda ln: ln.index), net.lefthand, L["markings"])
    _stop_lines(net, L["markings"])
    return {k: v for k, v in L.items() if v.count}, _signal_heads(net)


def _edge_markings(lanes: list[NetLane], lefthand: bool, out: Layer) -> None:
    """Lane separators (dashed / solid from the change permissions) and outer lines."""
    shapes = [dedupe(ln.shape) for ln in lanes]
    normals = [left_normals(p) if len(p) >= 2 else None for p in shapes]
    for k in range(len(lanes) - 1):
        a, b, pa, pb = lanes[k], lanes[k + 1], shapes[k], shapes[k + 1]
        if normals[k] is None or len(pb) < 2:
            continue
        edges = [offset(pa, a.width / 2, normals[k]), offset(pa, -a.width / 2, normals[k])]
        line = min(edges, key=lambda e: _near(e, pb))  # the side that faces lane b
        if _may_change(a.change_left) and _may_change(b.change_right):
            for piece in dashes(line, DASH_M, GAP_M):
                out.add_ribbon(piece, LINE_M / 2, LINE_M / 2)
        else:
            out.add_ribbon(line, LINE_M / 2, LINE_M / 2)
    # Outer lines, a little inside the lanes. Lane 0 lies on the driving side's edge:
    # its right edge in right-hand traffic, its left edge in left-hand traffic.
    side = 1.0 if lefthand else -1.0
    for k, sign in ((0, side), (len(lanes) - 1, -side)):
        if normals[k] is not None:
            edge = offset(shapes[k], sign * (lanes[k].width / 2 - 0.25), normals[k])
            out.add_ribbon(edge, LINE_M / 2, LINE_M / 2)


def _stop_lines(net: NetGeometry, out: Layer) -> None:
    """A bar across the end of every lane whose link is signalised or has to yield."""
    done: set[str] = set()
    for c in net.connections:
        if c.from_lane in done or not (c.tls or c.state in YIELD_STATES):
            continue
        ln = net.lane(c.from_lane)
        if ln is None or not _vehicle_lane(ln):
            continue
        done.add(c.from_lane)
        p = dedupe(ln.shape)
        if len(p) < 2:
            continue
        d = p[-1] - p[-2]
        d /= max(float(np.hypot(*d)), 1e-12)
        bar = np.vstack([p[-1] - d * (STOP_LINE_M + 0.2), p[-1] - d * 0.2])
        out.add_ribbon(bar, ln.width / 2 - 0.05, ln.width / 2 - 0.05)


def _signal_heads(net: NetGeometry) -> list[SignalHead]:
    heads: dict[tuple[str, int], SignalHead] = {}
    for c in net.connections:
        if not c.tls or c.link < 0 or (c.tls, c.link) in heads:
            continue
        ln = net.lane(c.from_lane)
        if ln is None:
            continue
        p = dedupe(ln.shape)
        if len(p) < 2:
            continue
        d = p[-1] - p[-2]
        heads[(c.tls, c.link)] = SignalHead(c.tls, c.link, ln.id, float(p[-1, 0]), float(p[-1, 1]),
                                            math.atan2(d[1], d[0]))
    return sorted(heads.values(), key=lambda h: (h.tls, h.link))


# ----------------------------------------------------------------------------- glTF


class _Writer:
    """Accumulates accessors in one binary buffer (4-byte aligned views)."""

    def __init__(self, gltf: pygltflib.GLTF2) -> None:
        self.gltf = gltf
        self.blob = bytearray()

    def accessor(self, data: np.ndarray, kind: str, target: int, minmax: bool = False) -> int:
        raw = np.ascontiguousarray(data).tobytes()
        while len(self.blob) % 4:
            self.blob.append(0)
        self.gltf.bufferViews.append(pygltflib.BufferView(
            buffer=0, byteOffset=len(self.blob), byteLength=len(raw), target=target))
        self.blob.extend(raw)
        ctype = {np.dtype(np.float32): pygltflib.FLOAT, np.dtype(np.uint32): pygltflib.UNSIGNED_INT,
                 np.dtype(np.uint16): pygltflib.UNSIGNED_SHORT}[data.dtype]
        count = data.shape[0] if kind != pygltflib.SCALAR else data.size
        acc = pygltflib.Accessor(bufferView=len(self.gltf.bufferViews) - 1, componentType=ctype,
                                 count=int(count), type=kind)
        if minmax:
            acc.min = [float(v) for v in data.min(axis=0)]
            acc.max = [float(v) for v in data.max(axis=0)]
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    def mesh(self, name: str, pos: np.ndarray, tris: np.ndarray, material: int) -> int:
        normals = np.tile(np.array([0.0, 1.0, 0.0], np.float32), (len(pos), 1))
        idx = tris.reshape(-1).astype(np.uint16 if len(pos) < 65536 else np.uint32)
        prim = pygltflib.Primitive(
            attributes=pygltflib.Attributes(
                POSITION=self.accessor(pos, pygltflib.VEC3, pygltflib.ARRAY_BUFFER, minmax=True),
                NORMAL=self.accessor(normals, pygltflib.VEC3, pygltflib.ARRAY_BUFFER)),
            indices=self.accessor(idx, pygltflib.SCALAR, pygltflib.ELEMENT_ARRAY_BUFFER),
            material=material)
        self.gltf.meshes.append(pygltflib.Mesh(name=name, primitives=[prim]))
        return len(self.gltf.meshes) - 1


def _box(size: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box centred on the origin: positions, normals (flat faces) and triangles."""
    hx, hy, hz = (s / 2 for s in size)
    pos, nor, tris = [], [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sign
            u, v = np.roll(np.eye(3), 1, axis=0)[axis], np.roll(np.eye(3), 2, axis=0)[axis]
            if sign < 0:
                u, v = v, u  # keep the face counter-clockwise seen from outside
            c = n * np.array([hx, hy, hz])
            half = np.array([hx, hy, hz])
            base = len(pos)
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                pos.append(c + a * u * half + b * v * half)
                nor.append(n)
            tris += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return np.array(pos, np.float32), np.array(nor, np.float32), np.array(tris, np.uint16)


def to_glb(net: NetGeometry, layers: dict[str, Layer], heads: list[SignalHead]) -> tuple[bytes, dict, tuple]:
    origin = map_origin(net.bounds)
    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(version="2.0", generator="sumoco map export"))
    w = _Writer(gltf)
    mat_index = {}
    for name, (rgba, rough) in MATERIALS.items():
        mat_index[name] = len(gltf.materials)
        gltf.materials.append(pygltflib.Material(
            name=name, doubleSided=True,
            pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                baseColorFactor=list(rgba), metallicFactor=0.0, roughnessFactor=rough)))
    root = pygltflib.Node(name="sumoco_map", translation=[origin[0], 0.0, -origin[1]])
    gltf.nodes.append(root)
    stats = {}
    for name, layer in layers.items():
        pos, tris = layer.arrays(origin)
        if len(tris) == 0:
            continue
        mesh = w.mesh(name, pos, tris, mat_index[layer.material])
        gltf.nodes.append(pygltflib.Node(name=name, mesh=mesh))
        root.children.append(len(gltf.nodes) - 1)
        stats[name] = (len(pos), len(tris))
    if heads:
        bpos, bnor, btris = _box(HEAD_SIZE)
        prim = pygltflib.Primitive(
            attributes=pygltflib.Attributes(
                POSITION=w.accessor(bpos, pygltflib.VEC3, pygltflib.ARRAY_BUFFER, minmax=True),
                NORMAL=w.accessor(bnor, pygltflib.VEC3, pygltflib.ARRAY_BUFFER)),
            indices=w.accessor(btris.reshape(-1), pygltflib.SCALAR, pygltflib.ELEMENT_ARRAY_BUFFER),
            material=mat_index["tls_head"])
        gltf.meshes.append(pygltflib.Mesh(name="tls_head", primitives=[prim]))
        head_mesh = len(gltf.meshes) - 1
        group = pygltflib.Node(name="tls")
        gltf.nodes.append(group)
        root.children.append(len(gltf.nodes) - 1)
        for h in heads:
            # Face the approaching traffic: local +Z points back along the lane.
            dx, dy = math.cos(h.heading), math.sin(h.heading)
            theta = math.atan2(-dx, dy)
            gltf.nodes.append(pygltflib.Node(
                name=h.name, mesh=head_mesh,
                translation=[h.x - origin[0], HEAD_HEIGHT, -(h.y - origin[1])],
                rotation=[0.0, math.sin(theta / 2), 0.0, math.cos(theta / 2)],
                extras={"tls": h.tls, "link": h.link, "lane": h.lane}))
            group.children.append(len(gltf.nodes) - 1)
        stats["tls_heads"] = (len(bpos), len(btris))
    gltf.scenes.append(pygltflib.Scene(name="sumoco map", nodes=[0], extras={"sumoco": {
        "origin": list(origin), "net_offset": list(net.net_offset), "projection": net.projection,
        "bounds": list(net.bounds), "lefthand": net.lefthand, "heads": len(heads),
        "frame": "X = x - origin_x (east), Y = up, Z = -(y - origin_y) (south)"}}))
    gltf.scene = 0
    gltf.buffers.append(pygltflib.Buffer(byteLength=len(w.blob)))
    gltf.set_binary_blob(bytes(w.blob))
    return b"".join(gltf.save_to_bytes()), stats, origin


def build_map(net: NetGeometry | str | Path) -> MapMesh:
    """The GLB of a network (a parsed ``NetGeometry`` or a path to its file)."""
    t0 = time.perf_counter()
    if not isinstance(net, NetGeometry):
        net = read_net(net)
    layers, heads = build_layers(net)
    glb, stats, origin = to_glb(net, layers, heads)
    seconds = time.perf_counter() - t0
    return MapMesh(glb=glb, sha256=hashlib.sha256(glb).hexdigest(), origin=origin, layers=stats,
                   heads=len(heads), seconds=seconds)


def export_map(net_file: str | Path, out: str | Path) -> MapMesh:
    """Write the GLB of ``net_file`` to ``out``; returns what was written."""
    mesh = build_map(net_file)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(mesh.glb)
    log.info("map %s: %d vertices, %d triangles, %d signal heads, %.1f KiB in %.2f s",
             out, mesh.vertices, mesh.triangles, mesh.heads, len(mesh.glb) / 1024, mesh.seconds)
    return mesh


# ----------------------------------------------------------------------------- serving


class MapService:
    """Builds the GLB of the run's network once, in the background, and answers map queries.

    The build runs on its own thread so the SUMO side starts stepping at once; a query that
    arrives before it is done gets ``None`` (the daemon replies with an error: ask again).
    """

    def __init__(self, net_file: Path | None, run: str) -> None:
        self.run = run
        self.net_file = net_file
        self.mesh: MapMesh | None = None
        self.error: str | None = None
        self._full: bytes | None = None
        self._short: bytes | None = None
        self._thread = threading.Thread(target=self._build, name="map-build", daemon=True)
        if net_file is not None:
            self._thread.start()
        else:
            self.error = "the scenario names no network file"

    def _build(self) -> None:
        try:
            mesh = build_map(self.net_file)
        except Exception as e:  # a broken network already failed SUMO; log, never kill the daemon
            self.error = str(e)
            log.warning("no map for %s: %s", self.net_file, e)
            return
        head = {"v": list(SCHEMA_VERSION), "kind": "map", "run": self.run, "sha256": mesh.sha256,
                "size": len(mesh.glb)}
        self._short = msgpack.packb({**head, "glb": None}, use_bin_type=True)
        self._full = msgpack.packb({**head, "glb": mesh.glb}, use_bin_type=True)
        self.mesh = mesh
        log.info("map ready: %d KiB, %d triangles, %d signal heads (%.2f s)",
                 len(mesh.glb) // 1024, mesh.triangles, mesh.heads, mesh.seconds)

    def wait(self, timeout: float) -> bool:
        """Wait for the build [s]; True when the map is ready."""
        if self._thread.is_alive():
            self._thread.join(timeout)
        return self.mesh is not None

    def reply(self, parameters: str) -> bytes | None:
        """The reply to a map query with these selector parameters, None while not ready."""
        if self.mesh is None:
            return None
        have = _parameter(parameters, "sha256")
        return self._short if have == self.mesh.sha256 else self._full


def _parameter(parameters: str, name: str) -> str | None:
    """Value of ``name`` in Zenoh selector parameters (``a=1;b=2``, ``&`` accepted too)."""
    for part in str(parameters or "").replace("&", ";").split(";"):
        key, _, value = part.partition("=")
        if key.strip() == name:
            return value.strip()
    return None


# ----------------------------------------------------------------------------- from static data


def geometry_from_static(static) -> NetGeometry:
    """A ``NetGeometry`` from the static-data message (SPEC 3.2), for a viewer whose SUMO
    side serves no map: lanes, junctions and signal heads are there; lane-change
    permissions are not (every separator is dashed) and sidewalks are not raised areas."""
    from sumo_side.netfile import ALL_CLASSES, NetConnection

    L = static.lanes
    off = np.asarray(L.shape_offsets, np.int64)
    xy = np.asarray(L.shape_xy, np.float64).reshape(-1, 2)
    lanes = []
    for i, lid in enumerate(L.ids):
        shape = xy[off[i]:off[i + 1]]
        if len(shape) < 2:
            continue
        internal = lid.startswith(":")
        allow = frozenset(L.allow[i]) if L.allow[i] else ALL_CLASSES
        index = int(lid.rsplit("_", 1)[1]) if lid.rsplit("_", 1)[-1].isdigit() else 0
        lanes.append(NetLane(id=lid, edge=L.edge[i], index=index, function="internal" if internal else "normal",
                             width=float(L.width[i]), shape=shape, allow=allow))
    J = static.junctions
    joff = np.asarray(J.shape_offsets, np.int64)
    jxy = np.asarray(J.shape_xy, np.float64).reshape(-1, 2)
    junctions = {jid: jxy[joff[k]:joff[k + 1]] for k, jid in enumerate(J.ids) if joff[k + 1] - joff[k] >= 3}
    T = static.tls_links
    conns = []
    for r in range(len(T.tls)):
        fl = int(T.from_lane[r])
        if 0 <= fl < len(L.ids):
            to = int(T.to_lane[r])
            conns.append(NetConnection(L.ids[fl], L.ids[to] if 0 <= to < len(L.ids) else "", "",
                                       static.tls_ids[int(T.tls[r])], int(T.link[r]), "o"))
    return NetGeometry(path=Path(f"static:{static.run}"), net_offset=tuple(static.net_offset),
                       projection=static.projection, bounds=tuple(static.bounds), lanes=lanes,
                       junctions=junctions, connections=conns)
