"""The C vehicle read (sumo_side._fastread) against the Python one.

A real libsumo run, once with each path (two processes: libsumo allows one simulation per
process), must give the same Snapshot in every step, bit for bit, with vehicles added,
re-typed to new vTypes, unsubscribed and stopped on the way. Hand-made results, hostile
ones included, must give the same columns and the same vType table, or the same error.
Each case also asserts whether the C path took the input or stepped aside, so a C path
that always steps aside fails here too.
"""

from __future__ import annotations

import copy
import math
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sumo_side import simulation
from sumo_side.config import SumoConfig
from sumo_side.simulation import (
    FAST_READ, V_ANGLE, V_LANE, V_LANEPOS, V_POS, V_ROUTE, V_SIGNALS, V_SPEED, V_TYPE, SumoSim,
)
from sumo_side.tables import VTypeTable
from tests.sumo_testnet import make_testnet

needs_c = pytest.mark.skipif(not FAST_READ, reason="sumo_side._fastread not built (or SUMOCO_PURE_READ set)")


def _same(a, b, path: str = "") -> None:
    """Equal down to the bits: types, dtypes, shapes, array bytes, float bit patterns."""
    assert type(a) is type(b), (path, type(a), type(b))
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, (path, a.dtype, b.dtype, a.shape, b.shape)
        if a.dtype == object:
            assert len(a) == len(b) and all(x == y for x, y in zip(a.tolist(), b.tolist())), path
        else:
            assert np.ascontiguousarray(a).tobytes() == np.ascontiguousarray(b).tobytes(), path
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _same(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{path}[{i}]")
    elif isinstance(a, float):
        assert struct_bits(a) == struct_bits(b), (path, a, b)
    else:
        assert a == b, (path, a, b)


def struct_bits(x: float) -> bytes:
    return np.float64(x).tobytes()


# --------------------------------------------------------------------------- hand-made results


class _FakeVehicle:
    """libsumo.vehicle over a fixed table of results: a fresh copy per call, as libsumo's."""

    def __init__(self, rows: dict) -> None:
        self.rows = rows
        self.calls = 0

    def getIDList(self):
        return tuple(self.rows)

    def getSubscriptionResults(self, vid):
        self.calls += 1
        r = self.rows[vid]
        if isinstance(r, BaseException):
            raise r
        return copy.deepcopy(r)

    # the getters of SumoSim._vehicle_row (a vehicle whose subscription lacks variables)
    def getPosition(self, vid):
        return (11.0, 12.0)

    def getAngle(self, vid):
        return 13.0

    def getSpeed(self, vid):
        return 14.0

    def getSignals(self, vid):
        return 2

    def getLanePosition(self, vid):
        return 15.0

    def getLaneID(self, vid):
        return "e_1"

    def getTypeID(self, vid):
        return "car"

    def getRouteID(self, vid):
        return "r_getter"


class _FakeVehicleType:
    def getIDList(self):
        return ("car",)

    def getVehicleClass(self, t):
        if not isinstance(t, str):  # as libsumo's SWIG wrapper
            raise TypeError("in method 'vehicletype_getVehicleClass', argument 1 of type 'std::string const &'")
        return "bicycle" if t.startswith("bike") else "passenger"

    def getLength(self, t):
        return 1.5 if t.startswith("bike") else 4.5

    def getWidth(self, t):
        return 0.6 if t.startswith("bike") else 1.8


class _FakeApi:
    def __init__(self, rows: dict) -> None:
        self.vehicle = _FakeVehicle(rows)
        self.vehicletype = _FakeVehicleType()


def _sim(rows: dict, capacity: int) -> SumoSim:
    """A SumoSim over fake results, its tables set up as ``_after_start`` does."""
    sim = SumoSim(SumoConfig(sumocfg=Path("unused.sumocfg")))
    api = _FakeApi(copy.deepcopy(rows))
    sim.api = api
    sim._vehicle_results = api.vehicle.getSubscriptionResults
    sim._lane_index = {"e_0": 0, "e_1": 1, "w_0": 7, "": -1}
    sim.vtypes = VTypeTable(api, capacity)
    for t in ("car", "bus"):
        sim.vtypes.add(t)
    return sim


def _table(vt: VTypeTable) -> dict:
    return {"index": dict(vt.index), "types": list(vt.types), "version": vt.version, "overflow": vt.overflow,
            "length": vt.length.copy(), "width": vt.width.copy(), "cls": vt.cls.copy()}


def _outcome(rows: dict, fast, capacity: int, monkeypatch) -> tuple:
    monkeypatch.setattr(simulation, "_fast", fast)
    sim = _sim(rows, capacity)
    try:
        c = sim._read_vehicles()
        result = ("ok", {k: getattr(c, k) for k in
                         ("ids", "xy", "angle", "speed", "lane_pos", "lane", "vtype", "signals", "route", "riding")})
    except Exception as e:
        result = ("error", type(e), str(e))
    return result, _table(sim.vtypes)


def _compare(rows: dict, monkeypatch, takes, capacity: int = 100) -> tuple:
    """The C path's outcome equals the Python path's; ``takes``: whether the C path takes the
    rows (else it steps aside), or the exception it raises. Returns the outcome."""
    fast = simulation._fast
    c_out = _outcome(rows, fast, capacity, monkeypatch)
    py_out = _outcome(rows, None, capacity, monkeypatch)
    _same(c_out, py_out)
    sim = _sim(rows, capacity)
    monkeypatch.setattr(simulation, "_fast", fast)
    if isinstance(takes, bool):
        assert (sim._read_vehicles_fast(list(rows)) is not None) is takes
    else:
        with pytest.raises(takes):
            sim._read_vehicles_fast(list(rows))
    return py_out


def row(x=1.0, y=2.0, angle=90.0, speed=3.5, signals=8, lane="e_0", lane_pos=4.25, vtype="car",
        route="r0", pos=...) -> dict:
    """One vehicle's results as libsumo gives them (``pos`` replaces the position tuple)."""
    return {V_POS: (x, y) if pos is ... else pos, V_ANGLE: angle, V_SPEED: speed, V_SIGNALS: signals,
            V_LANE: lane, V_LANEPOS: lane_pos, V_TYPE: vtype, V_ROUTE: route}


def _fleet(n: int = 5, **changed) -> dict:
    """``n`` ordinary vehicles; ``changed`` replaces some of them (``v<i>=row``)."""
    rows = {f"v{i}": row(x=float(i), y=-float(i), angle=i * 7.5, speed=i / 3, signals=i % 4,
                         lane=("e_0", "e_1", "w_0")[i % 3], lane_pos=i * 1.25, route=f"r{i % 2}")
            for i in range(n)}
    rows.update(changed)
    return rows


@needs_c
def test_ordinary_results_take_the_c_path(monkeypatch):
    result, _ = _compare(_fleet(7), monkeypatch, takes=True)
    assert result[0] == "ok"
    cols = result[1]
    assert cols["ids"] == [f"v{i}" for i in range(7)]
    assert cols["lane"].tolist() == [0, 1, 7, 0, 1, 7, 0]
    assert cols["route"] == ["r0", "r1"] * 3 + ["r0"]


@needs_c
def test_one_vehicle(monkeypatch):
    _compare(_fleet(1), monkeypatch, takes=True)


@needs_c
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, -0.0, 5e-324, 1.7976931348623157e308])
def test_special_floats_bit_for_bit(monkeypatch, value):
    _compare(_fleet(3, v1=row(x=value, y=value, angle=value, speed=value, lane_pos=value)), monkeypatch, takes=True)


@needs_c
@pytest.mark.parametrize("signals", [0, 1, -1, 2**31, -(2**31), 2**53, -(2**53)])
def test_signal_values(monkeypatch, signals):
    _compare(_fleet(3, v2=row(signals=signals)), monkeypatch, takes=True)


@needs_c
@pytest.mark.parametrize("lane", ["", "nowhere", "e_0\x00", "é_0"])
def test_lanes_unknown_to_the_table_are_minus_one(monkeypatch, lane):
    result, _ = _compare(_fleet(3, v0=row(lane=lane)), monkeypatch, takes=True)
    assert result[1]["lane"][0] == -1


@needs_c
def test_new_types_are_added_in_the_vehicles_order(monkeypatch):
    rows = _fleet(6, v0=row(vtype="bike_b"), v1=row(vtype="truck"), v2=row(vtype="bike_b"), v3=row(vtype="bus"),
                  v5=row(vtype="truck2"))
    result, table = _compare(rows, monkeypatch, takes=True)
    assert [t.id for t in table["types"]] == ["car", "bus", "bike_b", "truck", "truck2"]
    assert result[1]["vtype"].tolist() == [2, 3, 2, 1, 0, 4]


@needs_c
def test_a_full_type_table_borrows_as_in_python(monkeypatch):
    rows = _fleet(5, v0=row(vtype="t1"), v1=row(vtype="t2"), v2=row(vtype="t2"), v3=row(vtype="bike9"))
    _, table = _compare(rows, monkeypatch, takes=True, capacity=3)
    assert table["overflow"] == 3  # t2 twice and bike9: every vehicle of a type without a slot


@needs_c
def test_a_failing_type_lookup_raises_as_in_python(monkeypatch):
    class Boom(Exception):
        pass

    known = _FakeVehicleType.getVehicleClass

    def boom(self, t):
        if t == "new":
            raise Boom(f"no vClass for {t}")
        return known(self, t)

    monkeypatch.setattr(_FakeVehicleType, "getVehicleClass", boom)
    result, _ = _compare(_fleet(4, v2=row(vtype="new")), monkeypatch, takes=Boom)
    assert result[:2] == ("error", Boom)


@needs_c
def test_a_failing_getter_raises_as_in_python(monkeypatch):
    class TraCIException(Exception):
        pass

    result, _ = _compare(_fleet(4, v3=TraCIException("Vehicle 'v3' is not known.")), monkeypatch,
                         takes=TraCIException)
    assert result[:3] == ("error", TraCIException, "Vehicle 'v3' is not known.")


class _F(float):
    pass


class _D(dict):
    pass


#: Results the C path steps aside for; the Python path then reads, repairs or rejects them.
HOSTILE = {
    "no subscription ({})": {},
    "None": None,
    "a list": [1.0, 2.0],
    "a tuple": (),
    "a string": "results",
    "a dict subclass": _D(row()),
    "missing position": {k: v for k, v in row().items() if k != V_POS},
    "missing signals": {k: v for k, v in row().items() if k != V_SIGNALS},
    "missing route": {k: v for k, v in row().items() if k != V_ROUTE},
    "missing type": {k: v for k, v in row().items() if k != V_TYPE},
    "only the position": {V_POS: (1.0, 2.0)},
    "position of 3": row(pos=(1.0, 2.0, 3.0)),
    "position of 1": row(pos=(1.0,)),
    "position of 0": row(pos=()),
    "position None": row(pos=None),
    "position a list": row(pos=[1.0, 2.0]),
    "position of ints": row(x=1, y=2),
    "position of strings": row(x="1", y="2"),
    "position of float subclass": row(x=_F(1.0)),
    "position of numpy floats": row(x=np.float64(1.5), y=np.float32(2.5)),
    "angle int": row(angle=90),
    "angle None": row(angle=None),
    "angle string": row(angle="90.5"),
    "angle bool": row(angle=True),
    "speed numpy": row(speed=np.float64(3.0)),
    "speed complex": row(speed=1j),
    "lane position None": row(lane_pos=None),
    "signals float": row(signals=8.0),
    "signals fraction": row(signals=8.75),
    "signals bool": row(signals=True),
    "signals beyond 2^53": row(signals=2**53 + 1),
    "signals huge": row(signals=2**80),
    "signals None": row(signals=None),
    "signals string": row(signals="8"),
    "lane None": row(lane=None),
    "lane int": row(lane=0),
    "lane a list": row(lane=["e_0"]),
    "lane bytes": row(lane=b"e_0"),
    "type None": row(vtype=None),
    "type int": row(vtype=1),
    "type bytes": row(vtype=b"car"),
    "type a list": row(vtype=["car"]),
    "route None": row(route=None),
    "route a tuple": row(route=("a", "b")),
    "route bytes": row(route=b"r0"),
}


@needs_c
@pytest.mark.filterwarnings("ignore:invalid value encountered in cast")  # the Python path's, on bad signals
@pytest.mark.parametrize("where", [0, 2, 4])
@pytest.mark.parametrize("case", list(HOSTILE))
def test_hostile_results_step_aside_with_the_same_outcome(monkeypatch, case, where):
    _compare(_fleet(5, **{f"v{where}": HOSTILE[case]}), monkeypatch, takes=False)


@needs_c
def test_hostile_results_after_a_new_type_leave_no_trace(monkeypatch):
    """Stepping aside after a row with a new type: the type is added once (by the Python path)."""
    rows = _fleet(4, v0=row(vtype="new1"), v2=row(vtype="new2"), v3={})
    _, table = _compare(rows, monkeypatch, takes=False)
    assert table["version"] == 4  # car, bus, new1, new2: each added once


@needs_c
def test_bad_arguments_are_errors():
    f = simulation._fast
    get = {"a": row()}.__getitem__
    with pytest.raises(ValueError):
        f.read_vehicles(get, ["a"], {}, {}, print, np.empty(4), np.empty(3, np.int64))
    with pytest.raises(ValueError):
        f.read_vehicles(get, ["a"], {}, {}, print, np.empty(5), np.empty(2, np.int64))
    with pytest.raises(TypeError):
        f.read_vehicles(get, ("a",), {}, {}, print, np.empty(5), np.empty(3, np.int64))
    with pytest.raises(TypeError):
        f.read_vehicles(get, ["a"], {}, {})
    with pytest.raises(TypeError, match="floats: needs a writable"):  # read-only
        f.read_vehicles(get, ["a"], {}, {}, print, b"\0" * 40, np.empty(3, np.int64))
    with pytest.raises(TypeError, match="ints: needs int64"):
        f.read_vehicles(get, ["a"], {}, {}, print, np.empty(5), np.empty(3))
    empty = f.read_vehicles(get, [], {}, {}, print, np.empty(0), np.empty(0, np.int64))
    assert empty == []


# --------------------------------------------------------------------------- a real libsumo run

STEPS = 220
#: Fields of Snapshot compared step by step (tls, an object with arrays, separately).
SNAPSHOT_FIELDS = ("time", "ids", "x", "y", "angle", "speed", "accel", "signals", "lane", "lane_pos", "vtype",
                   "flags", "mode", "n_vehicles", "departed", "arrived", "teleports", "prev_index", "serial",
                   "route_changed")


def _drive(sumocfg: Path, out: Path) -> None:
    """Run the test network with changes along the way; pickle every Snapshot's columns,
    the vType table and, per step, whether the C path took the vehicles."""
    sim = SumoSim(SumoConfig(sumocfg=sumocfg), seed=3, run_id="t")
    sim.start()
    api = sim.api
    taken: list[bool | None] = []
    fast_read = sim._read_vehicles_fast

    def watched(vids):
        cols = fast_read(vids)
        taken.append(cols is not None)
        return cols

    sim._read_vehicles_fast = watched
    steps = []
    hidden = None
    try:
        for k in range(STEPS):
            sim.step()
            vids = sorted(api.vehicle.getIDList())
            if k == 5:  # a crowd on two routes
                for i in range(30):
                    api.vehicle.add(f"x{i}", ("r0", "rb")[i % 2], typeID="car", depart="now")
            if k == 40 and vids:  # a type that appears during the run
                api.vehicletype.copy("car", "car_red")
                api.vehicle.setType(vids[0], "car_red")
            if k == 60 and len(vids) > 3:
                api.vehicletype.copy("bike", "bike_fast")
                api.vehicle.setType(vids[1], "bike_fast")
                api.vehicle.setType(vids[2], "bike_fast")
                api.vehicle.setType(vids[3], "bus")
                api.vehicle.setSignals(vids[3], 0b1010)
            if k == 90 and vids:  # without results for a while: the Python path leaves it out
                hidden = vids[-1]
                api.vehicle.unsubscribe(hidden)
            if k == 110 and hidden in vids:
                sim._subscribe_vehicle(hidden)
            if k == 130 and len(vids) > 4:  # a vehicle stopped by the run
                api.vehicle.setSpeed(vids[4], 0.0)
            taken.append(None)  # a step mark: what follows is this step's read
            snap = sim.read()
            row = {f: getattr(snap, f) for f in SNAPSHOT_FIELDS}
            row["tls"] = (snap.tls.ids, snap.tls.state, snap.tls.phase, snap.tls.next_switch, snap.tls.program)
            row["static_version"] = sim.static_version
            steps.append(row)
        table = _table(sim.vtypes)
    finally:
        sim.close()
    out.write_bytes(pickle.dumps({"fast": simulation.FAST_READ, "steps": steps, "table": table, "taken": taken}))


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same run with the C path and with the Python path (one process each)."""
    folder = tmp_path_factory.mktemp("fastread")
    cfg = make_testnet(folder / "net")
    procs = {}
    for name, pure in (("c", "0"), ("python", "1")):
        env = dict(os.environ, SUMOCO_PURE_READ=pure)
        procs[name] = subprocess.Popen([sys.executable, "-m", "tests.test_sumo_fastread", str(cfg), str(folder / name)],
                                       env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                       cwd=Path(__file__).resolve().parents[1])
    for name, p in procs.items():
        text = p.communicate(timeout=120)[0].decode(errors="replace")
        assert p.returncode == 0, f"{name} run failed:\n{text[-3000:]}"
    return {name: pickle.loads((folder / name).read_bytes()) for name in procs}


def _per_step(taken: list) -> list[list[bool]]:
    steps: list[list[bool]] = []
    for t in taken:
        if t is None:
            steps.append([])
        else:
            steps[-1].append(t)
    return steps


@needs_c
def test_real_run_same_snapshots_every_step(runs):
    c, py = runs["c"], runs["python"]
    assert c["fast"] is True and py["fast"] is False
    assert len(c["steps"]) == len(py["steps"]) == STEPS
    for k, (a, b) in enumerate(zip(c["steps"], py["steps"])):
        _same(a, b, f"step {k}")
    _same(c["table"], py["table"])
    # the run did meet what it was built for
    assert max(s["n_vehicles"] for s in py["steps"]) >= 20
    assert {"car_red", "bike_fast"} <= set(py["table"]["index"])
    assert py["steps"][-1]["static_version"] > py["steps"][0]["static_version"]


@needs_c
def test_real_run_c_path_took_every_step_but_the_unsubscribed_ones(runs):
    steps = _per_step(runs["c"]["taken"])
    assert len(steps) == STEPS
    assert not any(_per_step(runs["python"]["taken"]))  # the Python run never called it
    declined = [k for k, s in enumerate(steps) if s == [False]]
    taken = [k for k, s in enumerate(steps) if s == [True]]
    # a vehicle without a subscription: from the step after the unsubscribe (libsumo still has
    # that step's results) until the step of the new subscription (it reads at once)
    assert declined == list(range(91, 110)), declined
    assert len(taken) + len(declined) == sum(1 for s in steps if s)
    assert len(taken) > 150


if __name__ == "__main__":  # one run for the ``runs`` fixture: python -m tests.test_sumo_fastread CFG OUT
    _drive(Path(sys.argv[1]), Path(sys.argv[2]))
