"""Protocol messages -> ROS 2 messages: one ``Converter`` shared by the live node and the
rosbag2 export, so both give the same topics.

The arithmetic is numpy over all agents (``frames``); what remains per agent is filling
the rclpy message objects, which ROS's Python API requires. The converter holds no thread
and no node: it takes decoded messages and returns ``(topic, message, stamp [s])`` tuples.

Topics (``prefix`` ``/sumoco`` by default; README "ROS 2" has the table with QoS):

- ``/clock`` (rosgraph_msgs/Clock): simulation time, every step;
- ``<prefix>/agents`` (visualization_msgs/MarkerArray): a DELETEALL, then one CUBE per agent
  (namespace ``agents``, marker id = the agent's row in the step, sized length x width x the
  class's height, coloured by class; the ego in magenta), brake lights (``brake``, red cubes
  at the rear of agents whose SUMO signal 8 is on), blinkers (``blinkers``, amber cubes at the
  front corners for signals 1 right, 2 left, 4 both) and traffic-light heads (``tls``, one
  cube per signal link 5 m above the end of its incoming lane, in the link's colour);
- ``<prefix>/poses`` (geometry_msgs/PoseArray): one pose per agent, in the step's order;
- ``<prefix>/odom/<id>`` (nav_msgs/Odometry) for the ids asked for;
- ``<prefix>/map`` (visualization_msgs/MarkerArray, latched): lanes as surfaces of their
  width (``lanes``), centre lines (``lane_lines``) and junction outlines (``junctions``).

Pose source: ``sumo`` takes each step's own samples (stamped with the step's time);
``physics`` takes each state of one physics instance, joined by id to the step it applied
(``sumo_step``, or the newest step), stamped with the physics time; an agent without a
physics row (a person riding a vehicle, an agent not spawned yet) keeps SUMO's pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from builtin_interfaces.msg import Duration, Time
from geometry_msgs.msg import Point, Pose, PoseArray, Vector3
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from protocol.messages import AgentFlag, PhysicsState, StaticData, StepMessage
from sumoco.ros2.config import Ros2Config, ros_name
from sumoco.ros2.frames import stamp_of, sumo_to_ros, yaw_to_quaternion

#: Marker box height per agent class (passenger, taxi, bus, bicycle, pedestrian, other) [m]
CLASS_HEIGHT_M = np.array([1.5, 1.5, 3.2, 1.7, 1.8, 2.6], np.float64)
#: Marker colour (r, g, b, a) per agent class
CLASS_RGBA = np.array([
    (0.20, 0.45, 0.90, 1.0),  # passenger: blue
    (0.95, 0.80, 0.10, 1.0),  # taxi: yellow
    (0.10, 0.65, 0.30, 1.0),  # bus: green
    (0.95, 0.50, 0.10, 1.0),  # bicycle: orange
    (0.85, 0.85, 0.85, 1.0),  # pedestrian: light grey
    (0.55, 0.40, 0.70, 1.0),  # other (trucks, ...): purple
], np.float64)
EGO_RGBA = (0.90, 0.10, 0.80, 1.0)  # the ego: magenta
BRAKE_RGBA = (1.0, 0.0, 0.0, 1.0)
BLINKER_RGBA = (1.0, 0.6, 0.0, 1.0)
#: SUMO signal bits (TraCI VAR_SIGNALS)
SIG_RIGHT, SIG_LEFT, SIG_EMERGENCY, SIG_BRAKE = 1, 2, 4, 8
LIGHT_M = 0.35  # [m] edge of a brake-light / blinker cube
TLS_HEAD_Z_M = 5.0  # [m] height of a traffic-light head (as in the glTF map, SPEC 9)
TLS_HEAD_M = 1.0  # [m] edge of a traffic-light head cube
#: Traffic-light colour per SUMO state letter (others, e.g. 'o' off: grey)
TLS_RGBA = {"r": (1.0, 0.0, 0.0, 1.0), "R": (1.0, 0.0, 0.0, 1.0), "u": (1.0, 0.6, 0.0, 1.0),
            "y": (1.0, 0.85, 0.0, 1.0), "Y": (1.0, 0.85, 0.0, 1.0), "g": (0.0, 0.6, 0.0, 1.0),
            "G": (0.0, 1.0, 0.0, 1.0), "s": (0.6, 0.0, 0.8, 1.0)}
TLS_OFF_RGBA = (0.4, 0.4, 0.4, 1.0)
STEPS_KEPT = 16  # recent steps kept to join physics states to the step they applied


def ros_time(t_s: float) -> Time:
    sec, nsec = stamp_of(t_s)
    return Time(sec=sec, nanosec=nsec)


def _rgba(c) -> ColorRGBA:
    return ColorRGBA(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=float(c[3]))


def _points(xyz: np.ndarray) -> list[Point]:
    return [Point(x=x, y=y, z=z) for x, y, z in xyz.tolist()]


@dataclass
class Poses:
    """Body-centre poses of one frame (every array of the step's length)."""

    stamp_s: float
    step: StepMessage
    cx: np.ndarray
    cy: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    source: str  # "sumo" or "physics"


@dataclass
class ConverterStats:
    steps: int = 0
    physics: int = 0
    frames: int = 0
    thinned: int = 0
    unjoined: int = 0  # physics states whose step was not kept (joined to the newest instead)
    physics_rows_missing: int = 0  # step agents without a physics row (SUMO's pose used)


@dataclass
class Converter:
    cfg: Ros2Config = field(default_factory=Ros2Config)

    def __post_init__(self) -> None:
        self.stats = ConverterStats()
        self._steps: dict[int, StepMessage] = {}
        self._last_frame_t: float | None = None
        self._last_clock_t: float | None = None
        self._tls_xy: np.ndarray = np.zeros((0, 2))  # per tls link: end of its incoming lane
        self._tls_rows: list[tuple[int, int]] = []  # per tls link: (tls index, link index)
        self._tls_ids: list[str] = []
        self._odom_prev: dict[str, tuple[float, float]] = {}  # id -> (t, yaw) for the yaw rate
        self.instance = self.cfg.instance

    # --- static data --------------------------------------------------------------------
    def static(self, sd: StaticData, stamp_s: float = 0.0) -> list[tuple[str, object, float]]:
        """The network as latched map markers; remembers the traffic-light heads' places."""
        lanes = sd.lanes
        off = lanes.shape_offsets.astype(np.int64)
        ends = off[1:] - 1
        links = sd.tls_links
        ok = (links.from_lane >= 0) & (links.from_lane < len(lanes.ids))
        fl = links.from_lane[ok].astype(np.int64)
        self._tls_xy = lanes.shape_xy[ends[fl]] if len(fl) else np.zeros((0, 2))
        self._tls_rows = list(zip(links.tls[ok].tolist(), links.link[ok].tolist()))
        self._tls_ids = list(sd.tls_ids)
        return [(self.cfg.topic("map"), self.map_markers(sd, stamp_s), stamp_s)]

    def map_markers(self, sd: StaticData, stamp_s: float) -> MarkerArray:
        lanes, hdr = sd.lanes, self._header(stamp_s)
        xy, off = lanes.shape_xy, lanes.shape_offsets.astype(np.int64)
        # segments of every polyline: consecutive points of one lane
        seg_lane = np.repeat(np.arange(len(lanes.ids)), np.maximum(np.diff(off) - 1, 0))
        ends_segment = np.ones(len(xy), bool)
        ends_segment[off[:-1][np.diff(off) > 0]] = False  # a point that starts a polyline ends no segment
        b_idx = np.nonzero(ends_segment)[0]
        a, b = xy[b_idx - 1], xy[b_idx]
        d = b - a
        norm = np.hypot(d[:, 0], d[:, 1])
        keep = norm > 1e-9
        a, b, d, norm, seg_lane = a[keep], b[keep], d[keep], norm[keep], seg_lane[keep]
        half = 0.5 * lanes.width.astype(np.float64)[seg_lane]
        nx, ny = -d[:, 1] / norm * half, d[:, 0] / norm * half
        al, ar = a + np.c_[nx, ny], a - np.c_[nx, ny]
        bl, br = b + np.c_[nx, ny], b - np.c_[nx, ny]
        tri = np.stack([al, ar, br, al, br, bl], axis=1).reshape(-1, 2)  # two triangles per segment
        ped = np.array([set(allow) == {"pedestrian"} for allow in lanes.allow], bool)
        tri_ped = np.repeat(ped[seg_lane], 6)
        z = np.where(tri_ped, 0.02, 0.0)[:, None]

        surf = Marker(header=hdr, ns="lanes", id=0, type=Marker.TRIANGLE_LIST, action=Marker.ADD)
        surf.pose.orientation.w = 1.0
        surf.scale = Vector3(x=1.0, y=1.0, z=1.0)
        surf.color = _rgba((0.3, 0.3, 0.3, 1.0))
        surf.points = _points(np.c_[tri, z])
        grey, light = _rgba((0.3, 0.3, 0.3, 1.0)), _rgba((0.6, 0.6, 0.55, 1.0))
        surf.colors = [light if p else grey for p in tri_ped.tolist()]

        centre = Marker(header=hdr, ns="lane_lines", id=0, type=Marker.LINE_LIST, action=Marker.ADD)
        centre.pose.orientation.w = 1.0
        centre.scale.x = 0.1
        centre.color = _rgba((0.9, 0.9, 0.9, 0.6))
        centre.points = _points(np.c_[np.stack([a, b], axis=1).reshape(-1, 2), np.full(2 * len(a), 0.03)])

        j = sd.junctions
        joff = j.shape_offsets.astype(np.int64)
        starts, stops = joff[:-1], joff[1:]
        pairs = []
        for s, e in zip(starts.tolist(), stops.tolist()):
            if e - s >= 2:
                ring = j.shape_xy[s:e]
                pairs.append(np.stack([ring, np.roll(ring, -1, axis=0)], axis=1).reshape(-1, 2))
        jl = np.concatenate(pairs) if pairs else np.zeros((0, 2))
        junc = Marker(header=hdr, ns="junctions", id=0, type=Marker.LINE_LIST, action=Marker.ADD)
        junc.pose.orientation.w = 1.0
        junc.scale.x = 0.15
        junc.color = _rgba((0.8, 0.8, 0.8, 1.0))
        junc.points = _points(np.c_[jl, np.full(len(jl), 0.01)])
        return MarkerArray(markers=[surf, centre, junc])

    # --- steps and physics states ------------------------------------------------------
    def step(self, m: StepMessage) -> list[tuple[str, object, float]]:
        """A SUMO step: the clock, and with the ``sumo`` source one frame (when due)."""
        self.stats.steps += 1
        self._steps[m.step] = m
        if len(self._steps) > STEPS_KEPT:
            for k in sorted(self._steps)[:-STEPS_KEPT]:
                del self._steps[k]
        out = self._clock(m.time)
        if self.cfg.source == "sumo":
            a = m.agents
            cx, cy, yaw = sumo_to_ros(a.x, a.y, a.angle, a.length.astype(np.float64))
            out += self._frame(Poses(m.time, m, cx, cy, yaw, a.speed.astype(np.float64), "sumo"))
        return out

    def physics(self, st: PhysicsState, instance: str = "") -> list[tuple[str, object, float]]:
        """A physics state: with the ``physics`` source one frame (when due), in the order of
        the step it applied."""
        if self.cfg.source != "physics":
            return []
        if not self.instance:
            self.instance = instance  # the first instance that publishes
        if instance and instance != self.instance:
            return []
        self.stats.physics += 1
        m = self._steps.get(st.sumo_step)
        if m is None:
            if not self._steps:
                return []
            self.stats.unjoined += 1
            m = self._steps[max(self._steps)]
        a, p = m.agents, st.agents
        length = a.length.astype(np.float64)
        x, y, ang = a.x.copy(), a.y.copy(), a.angle.astype(np.float64)
        speed = a.speed.astype(np.float64)
        if p.n and a.n:
            pid = np.asarray(p.ids)
            order = np.argsort(pid)
            sid = np.asarray(a.ids)
            pos = np.minimum(np.searchsorted(pid[order], sid), len(pid) - 1)
            found = pid[order][pos] == sid
            rows = order[pos[found]]
            x[found], y[found] = p.x[rows], p.y[rows]
            ang[found] = p.heading[rows]
            speed[found] = p.speed[rows]
            self.stats.physics_rows_missing += int((~found).sum())
        else:
            self.stats.physics_rows_missing += a.n
        cx, cy, yaw = sumo_to_ros(x, y, ang, length)
        stamp = max(st.time, m.time)
        return self._clock(stamp) + self._frame(Poses(stamp, m, cx, cy, yaw, speed, "physics"))

    def _clock(self, t: float) -> list[tuple[str, object, float]]:
        last = self._last_clock_t
        if last is not None and last - 1.0 < t <= last:  # never backwards, except a restarted run
            return []
        self._last_clock_t = t
        return [("/clock", Clock(clock=ros_time(t)), t)]

    def _due(self, t: float) -> bool:
        last, rate = self._last_frame_t, self.cfg.rate_hz
        if rate > 0 and last is not None and last <= t < last + 1.0 / rate - 1e-9:
            self.stats.thinned += 1
            return False
        self._last_frame_t = t
        return True

    def _frame(self, f: Poses) -> list[tuple[str, object, float]]:
        if not self._due(f.stamp_s):
            return []
        self.stats.frames += 1
        out = [(self.cfg.topic("agents"), self.agent_markers(f), f.stamp_s),
               (self.cfg.topic("poses"), self.pose_array(f), f.stamp_s)]
        if self.cfg.odometry:
            out += self.odometry(f)
        return out

    def _header(self, t: float) -> Header:
        return Header(stamp=ros_time(t), frame_id=self.cfg.frame_id)

    def pose_array(self, f: Poses) -> PoseArray:
        qz, qw = yaw_to_quaternion(f.yaw)
        poses = []
        for x, y, z, w in zip(f.cx.tolist(), f.cy.tolist(), qz.tolist(), qw.tolist()):
            p = Pose()
            p.position.x, p.position.y = x, y
            p.orientation.z, p.orientation.w = z, w
            poses.append(p)
        return PoseArray(header=self._header(f.stamp_s), poses=poses)

    def odometry(self, f: Poses) -> list[tuple[str, object, float]]:
        ids = f.step.agents.ids
        index = {i: k for k, i in enumerate(ids) if i in self.cfg.odometry}
        out = []
        for agent, k in index.items():
            yaw = float(f.yaw[k])
            prev = self._odom_prev.get(agent)
            rate = 0.0
            if prev is not None and f.stamp_s > prev[0]:
                rate = math.remainder(yaw - prev[1], 2 * math.pi) / (f.stamp_s - prev[0])
            self._odom_prev[agent] = (f.stamp_s, yaw)
            o = Odometry(header=self._header(f.stamp_s), child_frame_id=f"{ros_name(agent)}/base_link")
            o.pose.pose.position.x, o.pose.pose.position.y = float(f.cx[k]), float(f.cy[k])
            o.pose.pose.orientation.z, o.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
            o.twist.twist.linear.x = float(f.speed[k])  # in the body frame (child_frame_id)
            o.twist.twist.angular.z = rate
            out.append((self.cfg.topic("odom", ros_name(agent)), o, f.stamp_s))
        return out

    def agent_markers(self, f: Poses) -> MarkerArray:
        a, hdr = f.step.agents, self._header(f.stamp_s)
        n = a.n
        cls = np.minimum(a.cls.astype(np.int64), len(CLASS_HEIGHT_M) - 1)
        height = CLASS_HEIGHT_M[cls]
        length, width = a.length.astype(np.float64), a.width.astype(np.float64)
        rgba = CLASS_RGBA[cls].copy()
        rgba[(a.flags & AgentFlag.EGO) != 0] = EGO_RGBA
        qz, qw = yaw_to_quaternion(f.yaw)
        markers = [Marker(header=hdr, action=Marker.DELETEALL)]
        colors = {}
        lifetime = Duration()
        for k, (x, y, h, z, w, ln, wd, c) in enumerate(zip(
                f.cx.tolist(), f.cy.tolist(), height.tolist(), qz.tolist(), qw.tolist(), length.tolist(),
                width.tolist(), map(tuple, rgba.tolist()))):
            mk = Marker(header=hdr, ns="agents", id=k, type=Marker.CUBE, action=Marker.ADD, lifetime=lifetime)
            mk.pose.position.x, mk.pose.position.y, mk.pose.position.z = x, y, 0.5 * h
            mk.pose.orientation.z, mk.pose.orientation.w = z, w
            mk.scale.x, mk.scale.y, mk.scale.z = max(ln, 0.05), max(wd, 0.05), h
            mk.color = colors.get(c) or colors.setdefault(c, _rgba(c))
            markers.append(mk)
        if n:
            cos, sin = np.cos(f.yaw), np.sin(f.yaw)
            sig = a.signals.astype(np.int64)
            lights = []
            # brake lights: the middle of the rear, at 60 % of the height
            br = (sig & SIG_BRAKE) != 0
            if br.any():
                back = 0.5 * length[br]
                lights.append(("brake", np.c_[f.cx[br] - back * cos[br], f.cy[br] - back * sin[br],
                                              0.6 * height[br]], BRAKE_RGBA))
            # blinkers: the front corner(s) on the blinking side
            pts = []
            for bit, side in ((SIG_LEFT, 1.0), (SIG_RIGHT, -1.0)):
                on = (sig & (bit | SIG_EMERGENCY)) != 0
                if on.any():
                    fwd, lat = 0.5 * length[on], side * 0.5 * width[on]
                    pts.append(np.c_[f.cx[on] + fwd * cos[on] - lat * sin[on],
                                     f.cy[on] + fwd * sin[on] + lat * cos[on], 0.6 * height[on]])
            if pts:
                lights.append(("blinkers", np.concatenate(pts), BLINKER_RGBA))
            for ns, xyz, c in lights:
                mk = Marker(header=hdr, ns=ns, id=0, type=Marker.CUBE_LIST, action=Marker.ADD)
                mk.pose.orientation.w = 1.0
                mk.scale = Vector3(x=LIGHT_M, y=LIGHT_M, z=LIGHT_M)
                mk.color = _rgba(c)
                mk.points = _points(xyz)
                markers.append(mk)
        heads = self.tls_marker(f.step, hdr)
        if heads is not None:
            markers.append(heads)
        return MarkerArray(markers=markers)

    def tls_marker(self, m: StepMessage, hdr: Header) -> Marker | None:
        if not self._tls_rows or not m.tls.ids:
            return None
        state = dict(zip(m.tls.ids, m.tls.state))
        cols = []
        for t, link in self._tls_rows:
            s = state.get(self._tls_ids[t], "") if t < len(self._tls_ids) else ""
            cols.append(_rgba(TLS_RGBA.get(s[link], TLS_OFF_RGBA) if link < len(s) else TLS_OFF_RGBA))
        mk = Marker(header=hdr, ns="tls", id=0, type=Marker.CUBE_LIST, action=Marker.ADD)
        mk.pose.orientation.w = 1.0
        mk.scale = Vector3(x=TLS_HEAD_M, y=TLS_HEAD_M, z=TLS_HEAD_M)
        mk.color = _rgba(TLS_OFF_RGBA)
        mk.points = _points(np.c_[self._tls_xy, np.full(len(self._tls_xy), TLS_HEAD_Z_M)])
        mk.colors = cols
        return mk

