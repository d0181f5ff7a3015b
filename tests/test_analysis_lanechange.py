"""The summary's lane-change metric: the tracking error inside a window around each lane
change SUMO reports (the lane index changes within one edge), nothing outside it."""

from __future__ import annotations

import numpy as np

from protocol.messages import (
    AgentBatch, AgentMode, JunctionTable, LaneTable, PhysicsAgents, PhysicsState, StaticData, StepMessage,
    TrafficLights,
)
from sumoco.analysis.summary import (
    LANE_CHANGE_AFTER_S, LANE_CHANGE_BEFORE_S, Analysis, build_run_data, lane_change_cover, lane_change_events,
    summarise,
)

DT, PHYS_DT, T_END = 0.1, 0.05, 24.0
T_CHANGE = 10.0  # the car's lane index switches here (mid-manoeuvre, as SUMO reports it)
T_JUNCTION = 12.6  # the car enters a junction, inside its lane change's window
# lanes: 0 E_0, 1 E_1 (the same edge), 2 F_0 (the next edge), 3 a junction-internal lane
LANES = ["E_0", "E_1", "F_0", ":J_0"]


def _static() -> StaticData:
    n = len(LANES)
    z = np.zeros(n, np.float32)
    lanes = LaneTable(LANES, [i.rsplit("_", 1)[0] for i in LANES], z + 3.2, z + 300.0, [["passenger"]] * n,
                      np.arange(n + 1, dtype=np.uint32) * 2, np.zeros((2 * n, 2)))
    return StaticData(run="lc", step_length=DT, net_offset=(0.0, 0.0), projection="!", bounds=(0, 0, 1, 1),
                      lanes=lanes, junctions=JunctionTable([], np.zeros(1, np.uint32), np.zeros((0, 2))),
                      vtypes=[], vtype_length=np.zeros(0, np.float32), vtype_width=np.zeros(0, np.float32),
                      tls_ids=[])


def _smooth(t, t0, dur):
    u = np.clip((t - t0) / dur, 0.0, 1.0)
    return u * u * (3 - 2 * u)


T_EXIT = 9.0  # ``turner`` leaves the junction onto E_0 here, then changes lane at T_CHANGE


def _sumo(t: float, change: bool):
    """Cars eastbound at 10 m/s. ``car`` moves 3.2 m left over 3 s around T_CHANGE (its
    lane index 0 -> 1 at the midpoint) when ``change``; ``other`` goes from edge E to F;
    ``turner`` comes out of a junction onto E_0 at T_EXIT and changes to E_1 at T_CHANGE."""
    y = 3.2 * _smooth(t, T_CHANGE - 1.5, 3.0) if change else 0.0
    lane_car = 1 if change and t >= T_CHANGE - 1e-9 else 0
    lane_car = 3 if t >= T_JUNCTION - 1e-9 else lane_car
    lane_other = 2 if t >= T_CHANGE - 1e-9 else 0
    lane_turner = 3 if t < T_EXIT - 1e-9 else (1 if t >= T_CHANGE - 1e-9 else 0)
    return {"car": (10.0 * t, y, lane_car), "other": (10.0 * t, -20.0, lane_other),
            "turner": (10.0 * t, 40.0, lane_turner)}


def _deviation(t: float) -> dict[str, float]:
    """Sideways error of physics: 0.7 m peak inside the car's window (at 10.5 s), 1.2 m in
    the junction after it (a turn's error, at 13 s), 2 m on both cars well outside it (at
    3 s), 1.5 m for ``other`` at its change of edge; ``turner``: 1.0 m just out of its
    junction (9.5 s, the turn's), 0.9 m after it has settled (12 s, the lane change's)."""
    bump = lambda tc, a: a * np.exp(-(((t - tc) / 0.3) ** 2))  # noqa: E731
    return {"car": bump(10.5, 0.7) + bump(13.0, 1.2) + bump(3.0, 2.0), "other": bump(T_CHANGE, 1.5) + bump(3.0, 2.0),
            "turner": bump(9.5, 1.0) + bump(12.0, 0.9)}


def _messages(change: bool, turner: bool = False):
    steps, states = [], []
    ids = ["car", "other", "turner"] if turner else ["car", "other"]
    n = len(ids)
    z = np.zeros(n)
    for k, t in enumerate(np.round(np.arange(DT, T_END + 1e-9, DT), 6)):
        s = _sumo(t, change)
        a = AgentBatch(ids=ids, cls=np.zeros(n, np.uint8), vtype=np.zeros(n, np.uint16),
                       x=np.array([s[i][0] for i in ids]), y=np.array([s[i][1] for i in ids]),
                       angle=np.full(n, 90.0, np.float32), speed=np.full(n, 10.0, np.float32),
                       accel=z.astype(np.float32), signals=np.zeros(n, np.uint16), la_x=z, la_y=z,
                       length=np.full(n, 4.5, np.float32), width=np.full(n, 1.8, np.float32),
                       lane=np.array([s[i][2] for i in ids], np.int32), flags=np.zeros(n, np.uint8))
        steps.append(StepMessage(run="lc", step=k, time=float(t), step_length=DT, agents=a,
                                 tls=TrafficLights([], [], np.zeros(0, np.int32), np.zeros(0)), vtypes=[]))
    for k, t in enumerate(np.round(np.arange(DT, T_END + 1e-9, PHYS_DT), 6)):
        s, d = _sumo(t, change), _deviation(t)
        f = z.astype(np.float32)
        a = PhysicsAgents(ids=ids, cls=np.zeros(n, np.uint8), mode=np.full(n, AgentMode.PHYSICAL, np.uint8),
                          x=np.array([s[i][0] for i in ids]), y=np.array([s[i][1] + d[i] for i in ids]),
                          z=f, heading=f + 90.0, roll=f, pitch=f, speed=f + 10.0, steer=f, drive=f, brake=f,
                          err_lon=f, err_lat=f)
        states.append(PhysicsState(run="lc", tick=k, time=float(t), sumo_step=k // 2, agents=a, counters={}))
    return steps, states


def _in_memory(change: bool, turner: bool = False) -> dict:
    steps, states = _messages(change, turner)
    return summarise(build_run_data(_static(), steps, {"default": states}))["presets"]["default"]


def _streamed(change: bool, window_s: float, turner: bool = False) -> dict:
    steps, states = _messages(change, turner)
    an = Analysis(window_s=window_s)
    an.feed("", 0, _static())
    items = [(m.time, 0, "", m) for m in steps] + [(m.time, 1, "default", m) for m in states]
    for _, _, inst, m in sorted(items, key=lambda x: x[:2]):
        an.feed(inst, 0, m)
    return an.summary()["presets"]["default"]


def test_one_lane_change_and_the_known_error_inside_its_window():
    p = _in_memory(change=True)
    lc = p["lane_changes"]
    # the car's change of lane counts; the other car's change of edge does not
    assert lc["count"] == 1
    # the 0.7 m peak at 10.5 s is the only deviation inside 10 - before .. 10 + after
    # outside the junction (the 1.2 m there is the turn's)
    assert lc["max_error_m"] == 0.7
    assert 0.0 < lc["p95_error_m"] < 0.7
    assert lc["worst"] == {"agent": "car", "t": T_CHANGE, "at_s": 10.5, "error_m": 0.7}
    assert T_CHANGE + LANE_CHANGE_AFTER_S > 13.0
    window = (T_JUNCTION - (T_CHANGE - LANE_CHANGE_BEFORE_S)) / PHYS_DT
    assert abs(lc["samples"] - window) <= 2
    # the run's overall maximum is the 2 m outside every lane change
    assert p["error_m"]["overall"]["max"] == 2.0


def test_a_lane_change_right_after_a_junction_does_not_take_the_turns_error():
    """SUMO often starts a lane change on the first step after a junction: the turn's exit
    error (1.0 m at 9.5 s, within TURN_SETTLE_S of the junction) is not the lane change's;
    the 0.9 m once the car has settled is."""
    lc = _in_memory(change=True, turner=True)["lane_changes"]
    assert lc["count"] == 2
    assert lc["max_error_m"] == 0.9
    assert lc["worst"] == {"agent": "turner", "t": T_CHANGE, "at_s": 12.0, "error_m": 0.9}
    for w in (2.0, 5.0):  # the junction samples before a window still count for it
        assert _streamed(True, w, turner=True)["lane_changes"] == lc, w


def test_no_lane_change_counts_zero():
    lc = _in_memory(change=False)["lane_changes"]
    assert lc == {"count": 0, "max_error_m": None, "p95_error_m": None, "samples": 0, "worst": None}


def test_streamed_windows_give_the_same_lane_change_numbers():
    whole = _in_memory(change=True)["lane_changes"]
    for w in (2.0, 5.0):  # windows split the lane change's window in different places
        assert _streamed(True, w)["lane_changes"] == whole, w
    assert _streamed(False, 2.0)["lane_changes"]["count"] == 0


def test_events_and_cover():
    steps, _ = _messages(change=True)
    run = build_run_data(_static(), steps, {})
    ev_t, ev_aid = lane_change_events(run.ref, run.static)
    assert ev_t.tolist() == [T_CHANGE] and [run.ids[i] for i in ev_aid] == ["car"]
    assert len(lane_change_events(run.ref, None)[0]) == 0  # no lane -> edge table: none found
    assert len(lane_change_events(run.ref, run.static, after_t=T_CHANGE)[0]) == 0
    t = np.array([T_CHANGE - LANE_CHANGE_BEFORE_S - 0.01, T_CHANGE - LANE_CHANGE_BEFORE_S, T_CHANGE,
                  T_CHANGE + LANE_CHANGE_AFTER_S, T_CHANGE + LANE_CHANGE_AFTER_S + 0.01, T_CHANGE])
    aid = np.array([0, 0, 0, 0, 0, 1])
    assert lane_change_cover(t, aid, np.array([T_CHANGE]), np.array([0])).tolist() == [-1, 0, 0, 0, -1, -1]
    # two lane changes of one agent and one of another: each sample finds its own
    cov = lane_change_cover(np.array([1.0, 9.0, 20.0, 9.0]), np.array([0, 0, 0, 1]),
                            np.array([2.0, 8.0, 9.5]), np.array([0, 1, 0]))
    assert cov.tolist() == [0, 2, -1, 1]
