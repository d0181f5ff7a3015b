"""Tracking experiments on synthetic SUMO-like references (no Zenoh, same code path).

``track_reference`` drives one agent through ``Fleet`` (spawn, references, controllers,
MuJoCo) exactly as the daemon does in lockstep, feeding it ``StepMessage``s built from
a ``Trajectory`` at the SUMO rate, and returns time series for plots in the style of the
paper's Figures 7-12 (trajectory, position error over distance, steering, torque,
velocity) and for the LAD_min sweep (``lad_sweep``).

Trajectories (front-bumper centre, like SUMO): ``straight``, ``turn90``,
``lane_change``, ``paper_route`` (start from rest, two lane changes, a right turn).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from physics_side import control as C
from physics_side.config import PhysicsSettings, check_rates, ticks_to
from physics_side.fleet import Fleet
from physics_side.models import default_spec, family_for, spec_for_size
from physics_side.reference import PathSet
from physics_side.world import PhysicsWorld
from protocol.frames import yaw_to_sumo_angle
from protocol.messages import AgentBatch, AgentClass, StepMessage, TrafficLights, VType

PATH_AHEAD_M = 60.0  # [m] length of the path ahead sent with each step (like the SUMO side)
PATH_STEP_M = 1.0  # [m] its vertex spacing


@dataclass(frozen=True)
class Trajectory:
    """A reference: dense path of the front bumper plus an arc-length-over-time profile."""

    path_xy: np.ndarray
    """Dense polyline of the bumper's route [m], (k, 2)."""
    t: np.ndarray
    """Dense time base [s] (uniform, fine)."""
    s: np.ndarray
    """Arc length along the path at each t [m]."""
    v: np.ndarray
    """Speed at each t [m/s]."""
    a: np.ndarray
    """Acceleration at each t [m/s^2]."""
    name: str = ""

    @classmethod
    def from_samples(cls, t, x, y, speed, name: str = "samples", hz: float = 1000.0) -> "Trajectory":
        """A trajectory through SUMO-like samples (e.g. a recorded 10 Hz front-bumper track).

        The path is the polyline through the sample positions (standing samples merged),
        continued 80 m straight at the end; arc length over time is interpolated linearly
        between samples, speed from the samples, acceleration its derivative.
        """
        t = np.asarray(t, np.float64) - float(t[0])
        xy = np.c_[np.asarray(x, np.float64), np.asarray(y, np.float64)]
        seg = np.hypot(*np.diff(xy, axis=0).T)
        s_samples = np.concatenate(([0.0], np.cumsum(seg)))
        keep = np.concatenate(([True], seg > 1e-3))
        path = xy[keep]
        if len(path) < 2:
            raise ValueError("the samples never move")
        d = path[-1] - path[-2]
        d = d / max(np.hypot(*d), 1e-9)
        path = np.vstack([path, path[-1] + d * (PATH_AHEAD_M + 20.0)])
        tt = np.arange(0.0, t[-1] + 1e-9, 1.0 / hz)
        ss = np.interp(tt, t, s_samples)
        vv = np.interp(tt, t, np.asarray(speed, np.float64))
        aa = np.gradient(vv, tt) if len(tt) > 1 else np.zeros_like(tt)
        return cls(path, tt, ss, vv, aa, name)

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    def _path(self) -> PathSet:
        return PathSet(np.array([0, len(self.path_xy)]), self.path_xy)

    def at(self, t) -> dict[str, np.ndarray]:
        """Exact reference at times t: x, y, yaw [rad], speed, accel, s."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        s = np.interp(t, self.t, self.s)
        v = np.interp(t, self.t, self.v)
        a = np.interp(t, self.t, self.a)
        ps = self._path()
        xs, ys, hs, ks = [], [], [], []
        for si in s:  # one polyline: evaluate each time with n = 1
            p = ps.at(np.array([si]))
            xs.append(p.x[0]), ys.append(p.y[0]), hs.append(p.heading[0]), ks.append(p.curvature[0])
        return {"x": np.array(xs), "y": np.array(ys), "yaw": np.array(hs), "curvature": np.array(ks),
                "speed": v, "accel": a, "s": s}


def _polyline_arc_length(xy: np.ndarray) -> np.ndarray:
    return np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))))


def _resample(xy: np.ndarray, s0: float, length: float, step: float) -> np.ndarray:
    """Points of polyline ``xy`` from arc length s0 over ``length`` every ``step`` (extrapolated at the end)."""
    s = s0 + np.arange(0.0, length + 1e-9, step)
    ps = PathSet(np.array([0, len(xy)]), xy)
    out = np.empty((len(s), 2))
    for i, si in enumerate(s):
        p = ps.at(np.array([si]))
        out[i] = p.x[0], p.y[0]
    return out


def _profile(duration: float, v0: float, accel=None, hz: float = 1000.0):
    t = np.arange(0.0, duration + 1e-9, 1.0 / hz)
    if accel is None:
        a = np.zeros_like(t)
    else:
        a = np.array([accel(ti) for ti in t])
    v = np.maximum(v0 + np.concatenate(([0.0], np.cumsum(0.5 * (a[1:] + a[:-1]) / hz))), 0.0)
    s = np.concatenate(([0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / hz)))
    return t, s, v, a


def straight(v: float = 13.9, duration: float = 12.0, x0: float = 100.0, y0: float = 100.0) -> Trajectory:
    t, s, vv, a = _profile(duration, v)
    L = s[-1] + PATH_AHEAD_M + 20
    xy = np.c_[x0 + np.arange(0, L, 1.0), np.full(int(np.ceil(L)), y0)]
    return Trajectory(xy, t, s, vv, a, "straight")


def turn90(radius: float = 10.0, v: float = 6.0, lead_in: float = 30.0, lead_out: float = 80.0,
           right: bool = True, x0: float = 100.0, y0: float = 100.0) -> Trajectory:
    """Straight east, a 90 deg turn (right by default) of ``radius``, straight on."""
    ds = 0.25
    a1 = np.c_[np.arange(0, lead_in, ds), np.zeros(int(round(lead_in / ds)))]
    th = np.arange(0, np.pi / 2, ds / radius)
    sgn = -1.0 if right else 1.0
    arc = np.c_[lead_in + radius * np.sin(th), sgn * radius * (1 - np.cos(th))]
    ex, ey = lead_in + radius, sgn * radius
    out = np.c_[np.full(int(round(lead_out / ds)), ex), ey + sgn * np.arange(0, lead_out, ds)]
    xy = np.vstack([a1, arc, out]) + [x0, y0]
    dur = (lead_in + np.pi / 2 * radius + lead_out - PATH_AHEAD_M - 5) / v
    t, s, vv, a = _profile(dur, v)
    return Trajectory(xy, t, s, vv, a, "turn90")


def lane_change(v: float = 13.9, width: float = 3.2, lc_time: float = 3.0, lead_in: float = 40.0,
                duration: float = 10.0, x0: float = 100.0, y0: float = 100.0) -> Trajectory:
    """Straight with one smooth (cosine-shaped) lane change to the left over ``lc_time`` [s]."""
    ds = 0.25
    t, s, vv, a = _profile(duration, v)
    L = s[-1] + PATH_AHEAD_M + 20
    x = np.arange(0, L, ds)
    lc_len = v * lc_time
    u = np.clip((x - lead_in) / lc_len, 0, 1)
    y = width * 0.5 * (1 - np.cos(np.pi * u))
    xy = np.c_[x + x0, y + y0]
    # arc length along the S-curve slightly exceeds x: the profile's s is path arc length
    return Trajectory(xy, t, s, vv, a, "lane_change")


def paper_route(v_max: float = 8.0, x0: float = 100.0, y0: float = 100.0) -> Trajectory:
    """Paper Figure 7-like route: start from rest, lane changes at ~45 m and ~78 m, right turn at ~128 m."""
    ds = 0.25
    x = np.arange(0, 120, ds)
    y = np.zeros_like(x)
    for start, sgn in ((38.0, 1.0), (72.0, -1.0)):
        u = np.clip((x - start) / 14.0, 0, 1)
        y += sgn * 3.2 * 0.5 * (1 - np.cos(np.pi * u))
    R = 10.0
    th = np.arange(ds / R, np.pi / 2, ds / R)
    arc = np.c_[120 + R * np.sin(th), -R * (1 - np.cos(th))]
    out = np.c_[np.full(400, 120 + R), -R - np.arange(0, 100, ds)]
    xy = np.vstack([np.c_[x, y], arc, out]) + [x0, y0]

    def accel(ti: float) -> float:
        return 2.0 if ti < v_max / 2.0 else 0.0

    t, s, vv, a = _profile(38.0, 0.0, accel)
    # slow down to 6 m/s for the turn
    return Trajectory(xy, t, s, vv, a, "paper_route")


def u_turn(radius: float = 3.0, v: float = 3.5, lead_in: float = 30.0, lead_out: float = 90.0,
           x0: float = 100.0, y0: float = 100.0) -> Trajectory:
    """Straight east, a U-turn to the left of ``radius`` (SUMO's turnaround lanes: ~3 m,
    tighter than any car can steer), straight back west."""
    ds = 0.25
    a1 = np.c_[np.arange(0, lead_in, ds), np.zeros(int(round(lead_in / ds)))]
    th = np.arange(ds / radius, np.pi, ds / radius)
    arc = np.c_[lead_in + radius * np.sin(th), radius * (1 - np.cos(th))]
    back = np.c_[lead_in - np.arange(0, lead_out, ds), np.full(int(round(lead_out / ds)), 2 * radius)]
    xy = np.vstack([a1, arc, back]) + [x0, y0]
    dur = (lead_in + np.pi * radius + lead_out - PATH_AHEAD_M - 5) / v
    t, s, vv, a = _profile(dur, v)
    return Trajectory(xy, t, s, vv, a, "u_turn")


def _vtype_for(cls: AgentClass) -> str:
    return {AgentClass.PASSENGER: "passenger", AgentClass.TAXI: "taxi", AgentClass.BUS: "bus",
            AgentClass.BICYCLE: "bicycle", AgentClass.PEDESTRIAN: "pedestrian"}.get(cls, "truck")


def step_messages(traj: Trajectory, cls: AgentClass, length: float, width: float, step_s: float = 0.1,
                  lad_params=(7.0, 10.0, 1.0), agent_id: str = "a0", vclass: str | None = None):
    """SUMO-like StepMessages of one agent following ``traj`` (look-ahead by the paper's LAD);
    ``vclass``: its vType's vClass (default: the wire class's)."""
    # the last step's ticks run to its time + step_s: stay inside the trajectory
    n = int(np.floor(traj.duration / step_s + 1e-9))
    times = np.arange(n) * step_s
    ref = traj.at(times)
    la = C.lad(ref["speed"], *lad_params)
    ps = PathSet(np.array([0, len(traj.path_xy)]), traj.path_xy)
    # SUMO's angle is the chord from the vehicle's back to its front on the lane, not the
    # lane's tangent at the front (they differ in turns by ~asin(length / 2R))
    back = ps.at(ref["s"] - length)
    ref["yaw"] = np.where(ref["s"] >= length, np.arctan2(ref["y"] - back.y, ref["x"] - back.x), ref["yaw"])
    vt = [VType("t0", vclass or _vtype_for(cls))]
    for k in range(n):
        s0 = ref["s"][k]
        pts = _resample(traj.path_xy, s0, PATH_AHEAD_M, PATH_STEP_M).astype(np.float32)
        lp = ps.at(np.array([s0 + la[k]]))
        f32 = lambda v: np.array([v], np.float32)  # noqa: E731
        batch = AgentBatch(
            ids=[agent_id], cls=np.array([int(cls)], np.uint8), vtype=np.zeros(1, np.uint16),
            x=np.array([ref["x"][k]]), y=np.array([ref["y"][k]]),
            angle=f32(yaw_to_sumo_angle(ref["yaw"][k])), speed=f32(ref["speed"][k]), accel=f32(ref["accel"][k]),
            signals=np.zeros(1, np.uint16), la_x=f32(lp.x[0]), la_y=f32(lp.y[0]), length=f32(length),
            width=f32(width), lane=np.zeros(1, np.int32), flags=np.array([8 if k == 0 else 0], np.uint8),
            path_offsets=np.array([0, len(pts)], np.uint32), path_xy=pts,
        )
        yield StepMessage("exp", k, float(times[k]), step_s, batch, TrafficLights.empty(), vt)


def track_reference(
    preset: str, agent_class: AgentClass | int, traj: Trajectory, *, settings: PhysicsSettings | None = None,
    lad_min: float | None = None, length: float | None = None, lateral: str | None = None,
    max_steer_deg: float | None = None, vclass: str | None = None, width: float | None = None,
) -> dict[str, np.ndarray]:
    """Run one agent of ``agent_class`` under ``preset`` along ``traj``; time series at the control rate.

    Keys: t, x, y (actual front bumper), ref_x, ref_y (exact reference), held_x, held_y
    (the last SUMO sample), err (distance to the exact reference), err_lon, err_lat
    (as published: vs the extrapolated reference), err_held (distance to the held
    sample), dist (distance travelled), speed, v_ref, steer_deg, steer_pct (of max
    steer), drive, brake [N*m], u (u_in for paper, commanded accel for default), roll,
    pitch [deg], z [m], mode (``AgentMode``). ``max_steer_deg`` [deg, at most the model's]: the car's
    steering limit (what the paper preset's P_steer is a share of). ``vclass`` (with ``agent_class``
    OTHER, as SUMO's motorcycles and mopeds travel): the model family of that SUMO vClass, at
    ``length`` and ``width`` [m] (SUMO's vType size; default: the family's at the wire class's size).
    """
    cls = AgentClass(int(agent_class))
    settings, rates = _experiment_settings(settings or PhysicsSettings(), preset, lad_min, lateral)
    phys, ctl = settings.physics, settings.control
    spec, initial = _experiment_spec(cls, vclass, length, width)
    length = spec.length if length is None else length
    width = spec.width if width is None else width
    world = PhysicsWorld(phys.timestep_s, rates.substeps, shards=1, initial=initial)
    if max_steer_deg is not None:  # the model's steering joints allow up to their own limit
        world.tables.max_steer[:] = np.minimum(world.tables.max_steer, np.radians(max_steer_deg))
    fleet = Fleet(world, settings, rates)
    lad_params = (ctl.paper.lad_min, ctl.paper.lad_max, ctl.paper.k_lad)
    rec: dict[str, list] = {k: [] for k in _SERIES}
    max_steer = np.rad2deg(world.tables.max_steer[0]) if len(world.tables.max_steer) else spec.max_steer_deg
    t = None
    for msg in step_messages(traj, cls, length, width, phys.sumo_step_s, lad_params, vclass=vclass):
        # physics time and ticks as the daemon keeps them in lockstep (``ticks_to``: a step
        # length that is no whole number of control periods, e.g. SUMO's 0.05 s at 50 Hz, too);
        # interpolating, physics covers (previous step, this step]
        start = msg.time - (msg.step_length if fleet.interpolates(msg.step_length) else 0.0)
        ahead = 0.0 if t is None else t - start
        restart = t is None or not -rates.control_dt <= ahead <= phys.max_extrapolation_steps * msg.step_length
        fleet.apply_step(msg, tau=0.0 if restart else ahead)
        t = start if restart else t
        for _ in range(ticks_to(t, msg.time + msg.step_length - fleet.lag, rates.control_dt)):
            fleet.tick()
            t += rates.control_dt
            if t < -1e-9:  # interpolating, the first step covers the time before the reference starts
                continue
            _sample(rec, t, fleet, msg, max_steer)
    return _series(rec, traj, world, fleet)


#: The time series ``track_reference`` samples every control tick.
_SERIES = ("t", "x", "y", "held_x", "held_y", "err_lon", "err_lat", "speed", "v_ref", "steer_deg", "steer_pct",
           "drive", "brake", "u", "roll", "pitch", "z", "mode")


def _experiment_settings(settings: PhysicsSettings, preset: str, lad_min: float | None, lateral: str | None):
    """One simulation of ``preset``, with the paper's LAD_min or the default lateral law changed
    when given; its rates."""
    phys = replace(settings.physics, preset=preset, presets={}, shards=1, initial_slots={})
    ctl = settings.control
    if lad_min is not None:
        ctl = replace(ctl, paper=replace(ctl.paper, lad_min=lad_min, lad_max=max(lad_min, ctl.paper.lad_max)))
    if lateral is not None:
        ctl = replace(ctl, default=replace(ctl.default, lateral=lateral))
    return PhysicsSettings(phys, ctl), check_rates(phys.sumo_step_s, phys.control_hz, phys.timestep_s)


def _experiment_spec(cls: AgentClass, vclass: str | None, length: float | None, width: float | None):
    """The model of the agent and the pool made up front (none for a vClass family: its pool
    is made at the first spawn)."""
    wire = cls if cls != AgentClass.OTHER else AgentClass.PASSENGER
    if vclass is None:
        return default_spec(wire), {wire: 1}
    base = default_spec(wire)
    L, W = length or base.length, width or base.width
    return spec_for_size(family_for(cls, vclass, L), L, W), {}


def _sample(rec: dict[str, list], t: float, fleet, msg, max_steer: float) -> None:
    """The agent's state at physics time ``t`` and the SUMO sample it follows."""
    snap = fleet.snapshot()
    rec["t"].append(t)
    rec["x"].append(snap.x[0])
    rec["y"].append(snap.y[0])
    rec["held_x"].append(msg.agents.x[0])
    rec["held_y"].append(msg.agents.y[0])
    rec["err_lon"].append(snap.err_lon[0])
    rec["err_lat"].append(snap.err_lat[0])
    rec["speed"].append(snap.speed[0])
    rec["steer_deg"].append(snap.steer[0])
    rec["steer_pct"].append(100.0 * snap.steer[0] / max_steer)
    rec["drive"].append(snap.drive[0])
    rec["brake"].append(snap.brake[0])
    rec["u"].append(fleet.aux[0] if len(fleet.aux) else 0.0)
    rec["roll"].append(snap.roll[0])
    rec["pitch"].append(snap.pitch[0])
    rec["z"].append(snap.z[0])
    rec["mode"].append(snap.mode[0])


def _series(rec: dict[str, list], traj: Trajectory, world, fleet) -> dict[str, np.ndarray]:
    """The sampled series as arrays, with the errors against the exact reference, the distance
    travelled and the run's counters."""
    out = {k: np.asarray(v, np.float64) for k, v in rec.items()}
    exact = traj.at(out["t"])
    out["ref_x"], out["ref_y"], out["v_ref"] = exact["x"], exact["y"], exact["speed"]
    out["err"] = np.hypot(out["x"] - exact["x"], out["y"] - exact["y"])
    out["err_held"] = np.hypot(out["x"] - out["held_x"], out["y"] - out["held_y"])
    # signed lateral error vs the exact path (+ left)
    c, s = np.cos(exact["yaw"]), np.sin(exact["yaw"])
    dx, dy = out["x"] - exact["x"], out["y"] - exact["y"]
    out["err_true_lon"] = dx * c + dy * s
    out["err_true_lat"] = -dx * s + dy * c
    out["dist"] = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(out["x"]), np.diff(out["y"])))))
    out["placements"] = np.array([world.counters["placements"]])
    # by cause, as the daemon's summary counts them (a replay's placements are no spawn of the run's)
    for cause in ("spawn", "jump", "divergence", "flip"):
        out[f"placements_{cause}"] = np.array([fleet.counters[f"placements_{cause}"]])
    out["collisions"] = np.array([world.counters["collisions"]])
    out["carries_infeasible"] = np.array([fleet.counters["carries_infeasible"]])
    return out


def lad_sweep(lad_mins=(5.0, 6.0, 7.0, 8.0), agent_class=AgentClass.PASSENGER, traj: Trajectory | None = None,
              settings: PhysicsSettings | None = None) -> dict[float, dict[str, np.ndarray]]:
    """Paper Figure 9: the paper preset through a right turn for several LAD_min."""
    traj = traj or turn90()
    return {lm: track_reference("paper", agent_class, traj, settings=settings, lad_min=lm) for lm in lad_mins}


def steer_sweep(max_steers=(15.0, 20.0, 25.0, 30.0, 35.0), lad_min: float = 7.0, traj: Trajectory | None = None,
                settings: PhysicsSettings | None = None) -> dict[float, dict[str, np.ndarray]]:
    """The paper preset through a right turn for several maximum steering angles [deg]: its
    P_steer = delta_ref[deg] * k_steer is a share of the car's maximum angle, so the law is a
    plain pure pursuit only where max_steer = 1 / k_steer (20 deg for k_steer = 0.05)."""
    traj = traj or turn90(v=4.0)
    return {m: track_reference("paper", AgentClass.PASSENGER, traj, settings=settings, lad_min=lad_min,
                               max_steer_deg=m) for m in max_steers}


__all__ = ["Trajectory", "lad_sweep", "lane_change", "paper_route", "step_messages", "steer_sweep",
           "straight", "track_reference", "turn90", "u_turn"]
