"""Lane geometry and connectivity, read from SUMO once at start-up.

``LaneGraph`` holds every lane of the network (normal, junction-internal, crossings,
walking areas): centre-line polylines, widths, lengths, allowed classes and, per lane,
the lanes it leads to. It backs both the static data (``build_static``) and the path
ahead (``sumo_side.lookahead``), so each lane shape is fetched from SUMO exactly once.

Connectivity comes from ``lane.getLinks``: a link from lane A reaches lane B, usually
through a junction-internal ``via`` lane. An internal lane's own links continue the
chain (possibly through a second internal lane at an internal junction), which is how
the path crosses a junction without relying on ``vehicle.getNextLinks`` (that does not
say where a vehicle already inside a junction goes).
"""

from __future__ import annotations

import gzip
import logging
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.messages import JunctionTable, LaneTable, StaticData, TlsLinks, VType

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Link:
    """One connection out of a lane."""

    to: int
    """Index of the lane reached after the junction."""
    via: int
    """Index of the first junction-internal lane on the way, -1 when there is none."""

    @property
    def next(self) -> int:
        """The lane a vehicle enters right after leaving the current one."""
        return self.via if self.via >= 0 else self.to


class LaneGraph:
    """All lanes with shapes and successors; indices match ``StaticData.lanes``."""

    def __init__(
        self,
        ids: list[str],
        edges: list[str],
        shapes: list[np.ndarray],
        widths: np.ndarray,
        lengths: np.ndarray,
        allowed: list[list[str]],
        links: list[list[Link]],
    ) -> None:
        self.ids = ids
        self.index: dict[str, int] = {lid: i for i, lid in enumerate(ids)}
        self.edges = edges
        self.widths = np.asarray(widths, np.float64)
        self.lengths = np.asarray(lengths, np.float64)
        """SUMO lane length [m] (the unit of lane positions)."""
        self.allowed = allowed
        self.links = links
        self.internal = np.array([e.startswith(":") for e in edges], bool)
        self.shapes = [np.asarray(s, np.float64).reshape(-1, 2) for s in shapes]
        # Geometric length of each centre line [m]. SUMO's lane length can differ from it
        # (junction-internal lanes, user-set lengths); a lane position p lies p * factor
        # metres along the polyline.
        self.geom_lengths = np.array(
            [float(np.hypot(*np.diff(s, axis=0).T).sum()) if len(s) > 1 else 0.0 for s in self.shapes]
        )
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where(self.lengths > 0, self.geom_lengths / self.lengths, 1.0)
        self.pos_factor = np.where(np.isfinite(f), f, 1.0)
        self.edge_lanes: dict[str, list[int]] = {}
        for i, e in enumerate(edges):
            self.edge_lanes.setdefault(e, []).append(i)

    @property
    def n(self) -> int:
        return len(self.ids)

    def lane_index_of(self, lane_id: str) -> int:
        return self.index.get(lane_id, -1)

    def lane_table(self) -> LaneTable:
        counts = np.array([len(s) for s in self.shapes], np.int64)
        off = np.zeros(self.n + 1, np.uint32)
        np.cumsum(counts, out=off[1:])
        xy = np.concatenate(self.shapes).astype(np.float64) if self.n else np.zeros((0, 2))
        return LaneTable(
            ids=list(self.ids),
            edge=list(self.edges),
            width=self.widths.astype(np.float32),
            length=self.lengths.astype(np.float32),
            allow=[list(a) for a in self.allowed],
            shape_offsets=off,
            shape_xy=xy,
        )

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_sumo(cls, api) -> "LaneGraph":
        """Read every lane once through a running libsumo/TraCI connection."""
        ids = list(api.lane.getIDList())
        index = {lid: i for i, lid in enumerate(ids)}
        edges, shapes, widths, lengths, allowed, links = [], [], [], [], [], []
        extended = _links_need_extended_flag(api)
        for lid in ids:
            edges.append(api.lane.getEdgeID(lid))
            shapes.append(np.array(api.lane.getShape(lid), np.float64).reshape(-1, 2))
            widths.append(api.lane.getWidth(lid))
            lengths.append(api.lane.getLength(lid))
            allowed.append(list(api.lane.getAllowed(lid)))
            raw = api.lane.getLinks(lid, True) if extended else api.lane.getLinks(lid)
            out = []
            for lk in raw:
                to = index.get(lk[0], -1)
                via = index.get(lk[4], -1) if len(lk) > 4 and lk[4] else -1
                if to >= 0:
                    out.append(Link(to, via))
            links.append(out)
        g = cls(ids, edges, shapes, np.array(widths), np.array(lengths), allowed, links)
        log.debug("lane graph: %d lanes (%d internal)", g.n, int(g.internal.sum()))
        return g


def _links_need_extended_flag(api) -> bool:
    """TraCI's ``lane.getLinks(id, extended)`` has a flag libsumo's lacks."""
    return getattr(api, "__name__", "").split(".")[0] == "traci"


# ---------------------------------------------------------------------- static data


@dataclass(frozen=True)
class NetLocation:
    offset: tuple[float, float]
    projection: str


def read_net_location(net_file: Path) -> NetLocation:
    """netOffset and projParameter from the ``<location>`` element near the top of a net file.

    Only the head of the file is parsed (the element precedes every edge), so this is
    cheap even for city-sized networks. Missing element: offset (0, 0), projection '!'.
    """
    opener = gzip.open if str(net_file).endswith(".gz") else open
    try:
        with opener(net_file, "rb") as f:
            for _, elem in ET.iterparse(f, events=("start",)):
                if elem.tag == "location":
                    off = elem.get("netOffset", "0,0").split(",")
                    return NetLocation((float(off[0]), float(off[1])), elem.get("projParameter", "!"))
                if elem.tag in ("edge", "junction"):
                    break
    except (OSError, ET.ParseError, ValueError, IndexError) as e:
        log.warning("could not read <location> of %s (%s); using offset 0,0", net_file, e)
    return NetLocation((0.0, 0.0), "!")


def _junction_shape(api, junction_id: str) -> np.ndarray:
    if junction_id.startswith(":"):
        # Internal junctions have no outline (and TraCI cannot even parse their empty shape).
        return np.zeros((0, 2))
    try:
        return np.array(api.junction.getShape(junction_id), np.float64).reshape(-1, 2)
    except Exception as e:  # a shape SUMO cannot serialise: leave it out, keep the id
        log.debug("junction %s: no shape (%s)", junction_id, e)
        return np.zeros((0, 2))


def junction_table(api) -> JunctionTable:
    ids = list(api.junction.getIDList())
    shapes = [_junction_shape(api, j) for j in ids]
    counts = np.array([len(s) for s in shapes], np.int64)
    off = np.zeros(len(ids) + 1, np.uint32)
    np.cumsum(counts, out=off[1:])
    xy = np.concatenate(shapes) if shapes else np.zeros((0, 2))
    return JunctionTable(ids, off, xy.astype(np.float64))


def tls_link_table(api, graph: LaneGraph, tls_ids: list[str]) -> TlsLinks:
    """Per traffic-light link: the lanes it controls (read once at start)."""
    rows = []
    for t, tl in enumerate(tls_ids):
        for k, links in enumerate(api.trafficlight.getControlledLinks(tl)):
            for lk in links or [("", "", "")]:  # a link index may control several connections
                frm, to, via = (tuple(lk) + ("", "", ""))[:3]
                rows.append((t, k, graph.lane_index_of(frm), graph.lane_index_of(to), graph.lane_index_of(via)))
    if not rows:
        return TlsLinks.empty()
    a = np.array(rows, np.int64)
    return TlsLinks(a[:, 0].astype(np.uint16), a[:, 1].astype(np.uint16),
                    *(a[:, i].astype(np.int32) for i in (2, 3, 4)))


def build_static(
    api,
    graph: LaneGraph,
    run: str,
    step_length: float,
    net_file: Path | None,
    vtypes: list[VType],
    vtype_length: np.ndarray,
    vtype_width: np.ndarray,
    tls_ids: list[str],
) -> StaticData:
    loc = read_net_location(net_file) if net_file is not None else NetLocation((0.0, 0.0), "!")
    (xmin, ymin), (xmax, ymax) = api.simulation.getNetBoundary()
    return StaticData(
        run=run,
        step_length=float(step_length),
        net_offset=loc.offset,
        projection=loc.projection,
        bounds=(float(xmin), float(ymin), float(xmax), float(ymax)),
        lanes=graph.lane_table(),
        junctions=junction_table(api),
        vtypes=list(vtypes),
        vtype_length=np.asarray(vtype_length, np.float32),
        vtype_width=np.asarray(vtype_width, np.float32),
        tls_ids=list(tls_ids),
        tls_links=tls_link_table(api, graph, list(tls_ids)),
    )
