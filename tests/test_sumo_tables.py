"""Static tables that change mid-run: vehicle.setType, per-vehicle types, program switches.

Real libsumo on the small test network; every change must arrive in the decoded step (what
every client and the physics side receive) and in the static data of the new version.
"""

from __future__ import annotations

import numpy as np
import pytest

from protocol.codec import decode, encode
from protocol.messages import AgentClass, StaticData, StepMessage, VType
from protocol.tables import StaticTracker
from sumo_side.bridge import Bridge
from sumo_side.config import SumoConfig
from sumo_side.simulation import SumoSim
from sumo_side.tables import UNUSED, VTypeTable
from tests.sumo_testnet import make_testnet


@pytest.fixture()
def run(tmp_path_factory):
    cfg = make_testnet(tmp_path_factory.mktemp("net"))
    sim = SumoSim(SumoConfig(sumocfg=cfg), sumocfg=cfg, run_id="tables")
    sim.start()
    bridge = Bridge(sim, sim.cfg, "tables")
    tracker = StaticTracker()
    k = [0]

    def step() -> StepMessage:
        sim.step()
        raw = decode(encode(bridge.build(k[0], sim.read())))  # what a receiver gets
        k[0] += 1
        return tracker.resolve(raw), raw

    try:
        yield sim, step
    finally:
        sim.close()


def _row(msg: StepMessage, aid: str) -> int:
    return msg.agents.ids.index(aid)


def test_set_type_mid_run_reaches_the_step_and_the_static_data(run):
    sim, step = run
    for _ in range(30):
        msg, raw = step()
    assert raw.vtypes is None  # unchanged table: not re-sent every step
    i = _row(msg, "v0")
    assert msg.vtypes[msg.agents.vtype[i]].id == "car" and msg.agents.cls[i] == AgentClass.PASSENGER
    sv = msg.static_version
    sim.api.vehicle.setType("v0", "bus")
    msg, raw = step()
    i = _row(msg, "v0")
    # "bus" is in the table already: same static version, the table is not re-sent
    assert raw.vtypes is None and raw.static_version == sv
    assert msg.vtypes[msg.agents.vtype[i]] == VType("bus", "bus")
    assert msg.agents.cls[i] == AgentClass.BUS and msg.agents.length[i] == pytest.approx(12.0)


def test_per_vehicle_type_gets_a_new_static_version_and_drops_out_after(run):
    sim, step = run
    for _ in range(30):
        msg, _ = step()
    sv0 = msg.static_version
    sim.api.vehicle.setLength("v0", 7.5)  # SUMO gives v0 a private copy of its vType
    msg, raw = step()
    i = _row(msg, "v0")
    own = msg.vtypes[msg.agents.vtype[i]]
    assert own.id != "car" and own.vclass == "passenger", own
    assert raw.static_version > sv0 and raw.vtypes is not None
    assert msg.agents.length[i] == pytest.approx(7.5)
    static = decode(encode(sim.static_data()))
    assert isinstance(static, StaticData) and static.version == raw.static_version
    k = [v.id for v in static.vtypes].index(own.id)
    assert static.vtype_length[k] == pytest.approx(7.5)
    # v0 leaves the network: its private type is dropped once the table collects
    for _ in range(2000):
        msg, raw = step()
        if "v0" not in msg.agents.ids:
            break
    assert "v0" not in msg.agents.ids, "v0 should reach the end of its route"
    assert sim.vtypes.collect(msg.agents.vtype, force=True) == 1
    msg, raw = step()
    assert raw.vtypes is not None and own.id not in {v.id for v in raw.vtypes}
    assert sim.static_data().version == raw.static_version


def test_program_switch_mid_run_reaches_the_step(run):
    sim, step = run
    msg, _ = step()
    tl = msg.tls.ids[0]
    assert msg.tls.program[0] == "0"
    sim.api.trafficlight.setProgram(tl, "off")
    msg, raw = step()
    assert raw.tls.program[0] == "off" and set(raw.tls.state[0]) <= {"O", "o"}  # off: blinking or no signal
    assert sim.tls.switches == 1
    # the lights' links belong to the light: the static tables did not change
    static = decode(encode(sim.static_data()))
    n_links = len(raw.tls.state[0])
    assert sorted(set(static.tls_links.link[static.tls_links.tls == 0].tolist())) == list(range(n_links))


# ------------------------------------------------------------------ the table itself (no SUMO)


class _FakeTypes:
    """The three vehicletype getters VTypeTable uses."""

    def __init__(self, known):
        self.known = list(known)

    def getVehicleClass(self, t):
        return "bus" if t.startswith("bus") else "passenger"

    def getLength(self, t):
        return 12.0 if t.startswith("bus") else 5.0

    def getWidth(self, t):
        return 2.5 if t.startswith("bus") else 1.8

    def getIDList(self):
        return tuple(self.known)


class _FakeApi:
    def __init__(self, known):
        self.vehicletype = _FakeTypes(known)


def test_full_table_never_raises_and_reuses_dropped_indexes():
    api = _FakeApi(["car", "bus"])
    t = VTypeTable(api, capacity=4)
    assert list(t.indices(["car", "bus", "car@a", "car@b"])) == [0, 1, 2, 3]
    v = t.version
    # full: a fifth type borrows the index of a type of its vClass, counted, no exception
    assert t.add("car@c") in (0, 2, 3) and t.overflow == 1
    # car@a and car@b are unused and unknown to SUMO: dropped, their indexes reused
    assert t.collect(np.array([0, 1]), force=True) == 2
    assert t.version > v and t.types[2:] == [] and t.live == 2
    assert t.add("car@c") == 2 and t.types[2] == VType("car@c", "passenger")
    # a hole inside the table travels as an unused row
    t.add("car@d")
    t.collect(np.array([0, 1, 3]), force=True)
    assert t.types[2] is UNUSED and t.add("bus@e") == 2 and t.cls[2] == AgentClass.BUS


def test_vehicles_without_our_subscription_are_read_with_getters_or_left_out(run):
    """Someone else re-subscribing a vehicle with fewer variables (libsumo replaces the list)
    does not lose it; a vehicle with no subscription at all is left out, as before."""
    sim, step = run
    for _ in range(30):
        msg, _ = step()
    ids = list(msg.agents.ids)
    assert len(ids) >= 2, ids
    a, b = ids[0], ids[1]
    sim.api.vehicle.subscribe(a, (sim.api.VAR_SPEED,))  # only the speed
    sim.api.vehicle.unsubscribe(b)
    msg, _ = step()
    got = list(msg.agents.ids)
    assert a in got and b not in got
    i = got.index(a)
    x, y = sim.api.vehicle.getPosition(a)
    assert (msg.agents.x[i], msg.agents.y[i]) == pytest.approx((x, y))
    assert msg.agents.lane[i] >= 0 and msg.vtypes[msg.agents.vtype[i]].id == sim.api.vehicle.getTypeID(a)
