"""Two-way coupling on the SUMO side: which vehicles physics owns, and the write-back into a
real libsumo run (a vehicle held where "physics" has it makes SUMO's traffic queue behind it).
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from protocol.errors import ConfigError
from protocol.messages import AgentFlag, PhysicsFeedback, VType
from runtime.config import CouplingConfig, from_dict, load_common
from sumo_side.config import SumoConfig
from sumo_side.coupling import Authority, FeedbackWriter, GapHistogram
from sumo_side.simulation import SumoSim

ROOT = Path(__file__).resolve().parents[1]
STRAIGHT = ROOT / "configs" / "scenarios" / "straight" / "straight.sumocfg"
PHYS = int(AgentFlag.PHYSICS_AUTHORITY)


def _snap(ids, vtype, n_vehicles, prev_index=None, x=None, y=None):
    n = len(ids)
    return SimpleNamespace(n=n, n_vehicles=n_vehicles, ids=ids, vtype=np.asarray(vtype, np.int64),
                           flags=np.zeros(n, np.uint8), prev_index=prev_index,
                           x=np.zeros(n) if x is None else np.asarray(x, float),
                           y=np.zeros(n) if y is None else np.asarray(y, float))


VTYPES = SimpleNamespace(version=1, types=[VType("car", "passenger"), VType("lorry", "truck"),
                                           VType("walker", "pedestrian")])


def test_authority_by_class_type_and_id_pattern_never_persons_or_egos():
    snap = _snap(["c0", "t0", "truck_x", "p0"], [0, 1, 0, 2], n_vehicles=3)
    assert not Authority(CouplingConfig()).flags(snap, VTYPES).any()  # shadow mode: nobody
    by_class = Authority(CouplingConfig(classes=("truck",))).flags(snap, VTYPES)
    assert by_class.tolist() == [0, PHYS, 0, 0]
    by_type = Authority(CouplingConfig(types=("car",))).flags(snap, VTYPES)
    assert by_type.tolist() == [PHYS, 0, PHYS, 0]
    by_id = Authority(CouplingConfig(ids=("truck*",))).flags(snap, VTYPES)
    assert by_id.tolist() == [0, 0, PHYS, 0]
    everyone = Authority(CouplingConfig(authority="physics"))
    ego = np.array([0, 0, AgentFlag.EGO, 0], np.uint8)
    assert everyone.flags(snap, VTYPES, ego).tolist() == [PHYS, PHYS, 0, 0]  # the person stays SUMO's


def test_authority_by_id_is_decided_at_departure_and_kept_by_row():
    a = Authority(CouplingConfig(ids=("lead",)))
    first = a.flags(_snap(["x", "lead"], [0, 0], 2), VTYPES)
    assert first.tolist() == [0, PHYS]
    # next step: "lead" moved to row 0 (x arrived), a new vehicle at row 1
    second = a.flags(_snap(["lead", "y"], [0, 0], 2, prev_index=np.array([1, -1])), VTYPES)
    assert second.tolist() == [PHYS, 0]


def test_authority_by_zone_follows_the_level_of_detail_with_hysteresis():
    """``authority = "zones"``: physics owns the vehicles within 50 m of an ego or inside a
    fixed region, decided every step; between 0.9 r and r a vehicle keeps its owner."""
    a = Authority(CouplingConfig(authority="zones", zone_radius_m=50.0, zone_regions=((1000.0, 0.0, 20.0),)))
    ego = np.array([AgentFlag.EGO, 0, 0, 0, 0, 0], np.uint8)
    ids = ["ego", "near", "band", "far", "region", "p0"]
    first = a.flags(_snap(ids, [0] * 6, 5, x=[0, 30, 47, 80, 1010, 1], y=[0] * 6), VTYPES, ego)
    # the ego stays SUMO's (its pose comes from outside); 47 m is in the band: a new vehicle
    # there starts outside; persons are never physics-authoritative
    assert first.tolist() == [0, PHYS, 0, 0, PHYS, 0]
    prev = np.arange(6)
    # "near" drives into the band (kept), "far" to 44 m (inside 0.9 r: taken), the region's car leaves
    second = a.flags(_snap(ids, [0] * 6, 5, prev_index=prev, x=[0, 48, 47, 44, 1030, 1], y=[0] * 6), VTYPES, ego)
    assert second.tolist() == [0, PHYS, 0, PHYS, 0, 0]
    third = a.flags(_snap(ids, [0] * 6, 5, prev_index=prev, x=[0, 51, 47, 44, 1030, 1], y=[0] * 6), VTYPES, ego)
    assert third.tolist() == [0, 0, 0, PHYS, 0, 0]  # beyond r: SUMO's again


def test_zones_default_to_the_physics_level_of_detail(tmp_path):
    cfg = tmp_path / "run.toml"
    cfg.write_text('[coupling]\nauthority = "zones"\n[physics]\nlod_radius_m = 80.0\nlod_regions = [[1.0, 2.0, 30.0]]\n')
    c = load_common(cfg)[0].coupling
    assert c.two_way and c.zone_radius_m == 80.0 and c.zone_regions == ((1.0, 2.0, 30.0),)
    cfg.write_text('[coupling]\nauthority = "zones"\n')
    with pytest.raises(ConfigError, match=r'authority = "zones": expected level-of-detail zones'):
        load_common(cfg)


def test_gap_histogram_quantiles_and_exact_max():
    h = GapHistogram()
    h.add(np.array([0.01, 0.02, 0.03, 0.5]))
    h.add(np.array([]))
    s = h.summary()
    assert s["samples"] == 4 and s["max"] == 0.5
    assert 0.019 <= s["p50"] <= 0.021 and s["p95"] == 0.5


def test_coupling_config_names_what_is_wrong():
    with pytest.raises(ConfigError, match=r"coupling.classes: unknown vClass 'lorry'"):
        from_dict(CouplingConfig, {"classes": ["lorry"]}, "coupling")
    with pytest.raises(ConfigError, match=r"coupling.authority: expected one of \['sumo', 'physics', 'zones'\]"):
        from_dict(CouplingConfig, {"authority": "mujoco"}, "coupling")
    assert from_dict(CouplingConfig, {"authority": "physics"}, "coupling").two_way
    assert not CouplingConfig().two_way


@pytest.mark.integration
def test_a_vehicle_held_by_physics_makes_sumo_traffic_queue_and_dissolve():
    """The SUMO half of the stall: "lead" is written back at a fixed pose with speed 0 for
    20 s (as physics reports a stalled car); the cars behind it stop behind it, none passes
    it, none is teleported, and they drive on within 5 s of its release."""
    sim = SumoSim(SumoConfig(sumocfg=STRAIGHT), run_id="t")
    sim.start()
    try:
        g = sim.graph
        writer = FeedbackWriter(sim.api, g.ids, g.lengths, g.pos_factor)
        held_at = None
        hold_from, hold_to = 15.0, 35.0
        gap_min = np.inf
        moving_again = None
        snap = None
        for _ in range(600):
            if snap is not None and "lead" in snap.ids and hold_from <= snap.time < hold_to:
                row = snap.ids.index("lead")
                if held_at is None:
                    held_at = float(snap.lane_pos[row])
                # the physical body sits at held_at: its offset from SUMO's sample along the path
                d_lon = np.array([held_at - float(snap.lane_pos[row])], np.float32)
                zero = np.zeros(1, np.float32)
                fb = PhysicsFeedback("t", 0, snap.time, ["lead"], snap.x[[row]], snap.y[[row]], snap.angle[[row]],
                                     zero, d_lon, zero, np.zeros(1, np.uint8))
                writer.apply(fb, np.array([row]), snap.lane, snap.lane_pos)
            sim.step()
            snap = sim.read()
            if held_at is None or "lead" not in snap.ids:
                continue
            row = snap.ids.index("lead")
            on_lead_lane = (snap.lane[: snap.n_vehicles] == snap.lane[row])
            behind = on_lead_lane & (np.arange(snap.n_vehicles) != row)
            if hold_from + 1 <= snap.time < hold_to:
                assert abs(float(snap.lane_pos[row]) - held_at) < 0.1, snap.time  # SUMO keeps it where physics has it
                if behind.any():
                    gap_min = min(gap_min, float(held_at - snap.lane_pos[: snap.n_vehicles][behind].max()))
            if snap.time >= hold_to and moving_again is None and behind.any():
                follower = np.flatnonzero(behind)[np.argmax(snap.lane_pos[: snap.n_vehicles][behind])]
                if snap.speed[follower] > 2.0:
                    moving_again = snap.time - hold_to
        assert held_at is not None
        assert gap_min > 4.5  # the follower stopped behind it (its length 4.5 m), never through it
        assert sim.counters["teleports"] == 0
        assert moving_again is not None and moving_again <= 5.0
        assert writer.stats.moved > 0 and writer.stats.stopped > 0 and writer.stats.clamped == 0
    finally:
        sim.close()


class _RecordingVehicleApi:
    """libsumo's ``vehicle`` calls the write-back makes, recorded."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def moveTo(self, vid, lane, pos):  # noqa: N802 (libsumo's name)
        self.calls.append(("moveTo", vid, lane, round(pos, 3)))

    def setPreviousSpeed(self, vid, speed):  # noqa: N802
        self.calls.append(("speed", vid, round(speed, 3)))


def _coupling(feedback_steps: int):
    from protocol.codec import DecodeLimits
    from protocol.keys import Keys
    from sumo_side.coupling import SumoCoupling

    api = SimpleNamespace(vehicle=_RecordingVehicleApi())
    graph = SimpleNamespace(ids=["e_0"], lengths=np.array([100.0]), pos_factor=np.array([1.0]),
                            internal=np.array([False]))
    sim = SimpleNamespace(api=api, graph=graph)
    keys = Keys("sumoco", "rt")
    c = SumoCoupling(CouplingConfig(authority="physics", feedback_steps=feedback_steps), sim, keys,
                     DecodeLimits(), lambda what, e: pytest.fail(f"{what}: {e}"))
    return c, api.vehicle, keys


def _feedback(step: int, d_lon: float) -> bytes:
    from protocol.codec import encode

    f32 = lambda v: np.array([v], np.float32)  # noqa: E731
    return encode(PhysicsFeedback(run="rt", step=step, time=step * 0.1, ids=["car"], x=np.array([10.0]),
                                  y=np.array([0.0]), heading=f32(90.0), speed=f32(5.0), d_lon=f32(d_lon),
                                  d_lat=f32(0.0), contact=np.zeros(1, np.uint8)))


def test_realtime_writes_back_feedback_at_most_feedback_steps_old_and_counts_the_rest():
    """SPEC 3.8 "Timing": in realtime SUMO writes back the newest state at most
    ``feedback_steps`` old; a step without one keeps SUMO's own motion and counts as late."""
    c, api, keys = _coupling(feedback_steps=1)
    snap = _snap(["car"], [0], 1, x=[10.0], y=[0.0])
    snap.lane, snap.lane_pos = np.array([0]), np.array([50.0])
    for step in range(4):
        c.flags(snap, VTYPES, None)
        c.remember(step, snap)
    subscribed = []
    c.declare(SimpleNamespace(declare_subscriber=lambda key_expr, cb: subscribed.append(cb)))
    key = f"{keys.base}/physics/default/feedback"

    def deliver(payload: bytes) -> None:  # as Zenoh's thread does
        subscribed[0](SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: payload)))

    deliver(_feedback(2, 1.5))
    c.write_back(4)  # the state of step 2 before step 4: one step old, written
    assert api.calls == [("moveTo", "car", "e_0", 51.5), ("speed", "car", 5.0)]
    c.write_back(5)  # nothing new: SUMO keeps its own motion, one late step
    deliver(_feedback(2, 3.0))
    c.write_back(6)  # the state of step 2 before step 6: too old, not written, late again
    assert len(api.calls) == 2
    st = c.stats()
    assert st["feedback_steps_applied"] == 1 and st["feedback_late"] == 2, st
