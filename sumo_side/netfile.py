"""Read the geometry of a SUMO network file (``.net.xml`` or ``.net.xml.gz``) without SUMO.

Only the standard library and numpy: the map export (``sumo_side.mapmesh``) must work in
a bare ``pip install sumoco`` that has neither libsumo nor sumolib. What is read:

- every lane (normal, junction-internal, crossing, walking area) with its centre line,
  width, allowed classes and lane-change permissions;
- every junction outline;
- every connection (``from``/``to`` lane, ``via`` lane, traffic light and link index,
  link state);
- ``<location>`` (netOffset, convBoundary, projection).

Coordinates are SUMO's network frame (x east, y north, metres), float64.
"""

from __future__ import annotations

import gzip
import logging
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from protocol.errors import ConfigError

log = logging.getLogger(__name__)

#: SUMO's default lane width [m] when a lane has no ``width`` attribute.
DEFAULT_LANE_WIDTH = 3.2
#: Every vClass SUMO knows; ``allow``/``disallow`` are resolved against it.
ALL_CLASSES = frozenset((
    "private emergency authority army vip pedestrian passenger hov taxi bus coach delivery truck "
    "trailer motorcycle moped bicycle evehicle tram rail_urban rail rail_electric rail_fast ship "
    "container cable_car subway aircraft wheelchair scooter drone custom1 custom2").split())


@dataclass
class NetLane:
    """One lane of the network."""

    id: str
    edge: str
    index: int
    """Index within its edge (0 = the outermost lane on the driving side)."""
    function: str
    """Edge function: ``normal``, ``internal``, ``crossing`` or ``walkingarea``."""
    width: float
    """Lane width [m]."""
    shape: np.ndarray
    """Centre line (walking areas: outline polygon), shape (m, 2) [m]."""
    allow: frozenset[str]
    """vClasses allowed on the lane."""
    change_left: frozenset[str] | None = None
    """vClasses that may change to the left neighbour; None = every class (SUMO's default)."""
    change_right: frozenset[str] | None = None
    """vClasses that may change to the right neighbour; None = every class."""

    @property
    def pedestrian_only(self) -> bool:
        return bool(self.allow) and self.allow <= {"pedestrian", "wheelchair"}

    @property
    def bicycle_only(self) -> bool:
        return self.allow == {"bicycle"}

    @property
    def rail_only(self) -> bool:
        return bool(self.allow) and all(c in ("tram", "rail_urban", "rail", "rail_electric", "rail_fast",
                                              "subway", "cable_car") for c in self.allow)


@dataclass(frozen=True)
class NetConnection:
    """One ``<connection>``: lane ``from_lane`` leads to ``to_lane`` (through ``via``)."""

    from_lane: str
    to_lane: str
    via: str
    tls: str
    """Controlling traffic light id, '' when none."""
    link: int
    """Position of this link in the traffic light's state string, -1 when none."""
    state: str
    """SUMO link state letter (``M`` major, ``m`` minor, ``=``, ``s`` stop, ``w``, ``o``, ...)."""


@dataclass
class NetGeometry:
    """What the map export needs from a network file."""

    path: Path
    net_offset: tuple[float, float] = (0.0, 0.0)
    """SUMO's netOffset [m]: projected coordinates = network coordinates - offset."""
    projection: str = "!"
    """proj4 string of the projection, '!' when not geo-referenced."""
    bounds: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    """convBoundary: xmin, ymin, xmax, ymax [m] (network frame)."""
    lefthand: bool = False
    lanes: list[NetLane] = field(default_factory=list)
    junctions: dict[str, np.ndarray] = field(default_factory=dict)
    """Junction id -> outline polygon (k, 2) [m]; internal junctions are left out."""
    junction_types: dict[str, str] = field(default_factory=dict)
    connections: list[NetConnection] = field(default_factory=list)

    def lane(self, lane_id: str) -> NetLane | None:
        if not hasattr(self, "_index"):
            self._index = {ln.id: ln for ln in self.lanes}
        return self._index.get(lane_id)


def _shape(text: str | None, where: str) -> np.ndarray:
    if not text:
        return np.zeros((0, 2))
    try:
        pts = [tuple(map(float, p.split(",")[:2])) for p in text.split()]
    except ValueError as e:
        raise ValueError(f"{where}: shape {text[:60]!r}: {e}") from None
    return np.array(pts, np.float64).reshape(-1, 2)


def _classes(text: str | None) -> frozenset[str]:
    if text is None:
        return frozenset()
    words = set(text.split())
    if "all" in words:
        return ALL_CLASSES
    return frozenset(words)


def _allowed(lane: ET.Element, edge: ET.Element) -> frozenset[str]:
    allow = lane.get("allow", edge.get("allow"))
    disallow = lane.get("disallow", edge.get("disallow"))
    if allow is not None:
        return _classes(allow)
    if disallow is not None:
        return ALL_CLASSES - _classes(disallow)
    return ALL_CLASSES


def _change(value: str | None) -> frozenset[str] | None:
    if value is None:
        return None
    words = set(value.split())
    if "all" in words:
        return ALL_CLASSES
    return frozenset(words - {"ignoring"})


def read_net(path: str | Path) -> NetGeometry:
    """Parse a SUMO network file; a missing or broken file is a ``ConfigError`` naming it."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"network file {path}: not found (expected a SUMO .net.xml or .net.xml.gz)")
    net = NetGeometry(path=path)
    opener = gzip.open if path.name.endswith(".gz") else open
    try:
        with opener(path, "rb") as f:
            _parse(f, net)
    except (OSError, ET.ParseError, EOFError) as e:
        raise ConfigError(f"network file {path}: not a readable SUMO network ({e})") from None
    except ValueError as e:
        raise ConfigError(f"network file {path}: {e}") from None
    if not net.lanes:
        raise ConfigError(f"network file {path}: no <edge>/<lane> elements (is it a SUMO .net.xml?)")
    return net


def _parse(f, net: NetGeometry) -> None:
    root_seen = False
    for event, el in ET.iterparse(f, events=("start", "end")):
        if event == "start":
            if not root_seen:
                root_seen = True
                if el.tag != "net":
                    raise ValueError(f"root element is <{el.tag}>, expected <net>")
                net.lefthand = el.get("lefthand", "false").lower() == "true"
            continue
        tag = el.tag
        if tag == "location":
            off = el.get("netOffset", "0,0").split(",")
            net.net_offset = (float(off[0]), float(off[1]))
            net.projection = el.get("projParameter", "!")
            b = [float(v) for v in el.get("convBoundary", "0,0,0,0").split(",")]
            net.bounds = (b[0], b[1], b[2], b[3])
        elif tag == "edge":
            eid = el.get("id", "")
            func = el.get("function", "normal")
            for ln in el.iter("lane"):
                lid = ln.get("id", "")
                shape = _shape(ln.get("shape"), f"lane {lid}")
                if len(shape) < 2:
                    continue
                net.lanes.append(NetLane(
                    id=lid, edge=eid, index=int(ln.get("index", "0")), function=func,
                    width=float(ln.get("width", DEFAULT_LANE_WIDTH)), shape=shape,
                    allow=_allowed(ln, el),
                    change_left=_change(ln.get("changeLeft")), change_right=_change(ln.get("changeRight")),
                ))
            el.clear()
        elif tag == "junction":
            jid = el.get("id", "")
            jtype = el.get("type", "")
            if jtype != "internal" and not jid.startswith(":"):
                shape = _shape(el.get("shape"), f"junction {jid}")
                if len(shape) >= 3:
                    net.junctions[jid] = shape
                net.junction_types[jid] = jtype
            el.clear()
        elif tag == "connection":
            frm, to = el.get("from", ""), el.get("to", "")
            if not frm.startswith(":"):
                net.connections.append(NetConnection(
                    from_lane=f"{frm}_{el.get('fromLane', '0')}", to_lane=f"{to}_{el.get('toLane', '0')}",
                    via=el.get("via", ""), tls=el.get("tl", ""), link=int(el.get("linkIndex", "-1")),
                    state=el.get("state", "")))
            el.clear()
    if net.bounds == (0.0, 0.0, 0.0, 0.0) and net.lanes:
        xy = np.concatenate([ln.shape for ln in net.lanes])
        net.bounds = (float(xy[:, 0].min()), float(xy[:, 1].min()), float(xy[:, 0].max()), float(xy[:, 1].max()))
