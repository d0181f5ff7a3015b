"""Golden vectors: fixed messages, their msgpack bytes and their values as JSON.

``python -m protocol.golden_vectors`` (re)writes ``protocol/golden/<name>.msgpack`` and
``<name>.json``. A client in any language decodes each ``.msgpack`` and compares with the
``.json``; ``invalid_*`` vectors must be rejected (the JSON names the offending field).
The tests check that this module, the files on disk and the decoder agree.
"""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import numpy as np

from protocol.codec import FEEDBACK_COLUMNS, PHYSICS_AGENT_COLUMNS, STEP_AGENT_COLUMNS, TLS_LINK_COLUMNS, encode
from protocol.messages import (
    AgentBatch,
    AgentClass,
    AgentFlag,
    AgentMode,
    CameraPose,
    EgoPose,
    JunctionTable,
    LaneTable,
    PhysicsAgents,
    PhysicsFeedback,
    PhysicsState,
    StaticData,
    StepAck,
    StepMessage,
    SumoStatus,
    TlsLinks,
    TrafficLights,
    VType,
)

GOLDEN_DIR = Path(__file__).with_name("golden")

f32, f64 = np.float32, np.float64

#: The golden world: road E0 runs east into the signalised junction J1 and on as E1; S0
#: comes from the south and turns right into E1. Traffic light J1 has two links: 0 (E0 ->
#: E1, green) and 1 (S0 -> E1, red). At step 41 (t = 4.2 s, dt = 0.1 s, begin 0) car
#: ``ref`` drives on E0, bus ``bus_0`` crosses J1 and person ``ped_7`` rides the bus.
LANES = (  # id, edge, width [m], allow, centre line [m]
    ("E0_0", "E0", 3.2, ["passenger", "taxi", "bus"], [(0.0, -1.6), (98.0, -1.6)]),
    (":J1_0_0", ":J1_0", 3.2, ["passenger", "taxi", "bus"], [(98.0, -1.6), (112.0, -1.6)]),
    ("E1_0", "E1", 3.2, ["passenger", "taxi", "bus", "bicycle"], [(112.0, -1.6), (200.0, -1.6)]),
    ("S0_0", "S0", 3.2, ["passenger", "taxi", "bus"], [(108.4, -100.0), (108.4, -12.0)]),
    (":J1_1_0", ":J1_1", 3.2, ["passenger", "taxi", "bus"], [(108.4, -12.0), (109.5, -5.0), (112.0, -1.6)]),
)
VTYPES = (  # id, vClass, length [m], width [m]
    ("car", "passenger", 5.0, 1.8),
    ("city_bus", "bus", 12.0, 2.5),
    ("DEFAULT_PEDTYPE", "pedestrian", 0.215, 0.478),
)
STATIC_VERSION = 1
#: The golden run's incarnation: its SUMO side started at 2026-09-21 12:13:20.123456789 UTC [ns].
EPOCH = 1_790_000_000_123_456_789
#: UTM-sized translation of the golden world (step_utm): x ~ 691,000 m, y ~ 5,335,000 m.
UTM_SHIFT = (691_000.25, 5_335_000.75)


def _lane_length(shape) -> float:
    return float(np.hypot(*np.diff(np.asarray(shape, f64), axis=0).T).sum())


def _step(with_paths: bool, shift: tuple[float, float] = (0.0, 0.0), with_vtypes: bool = True) -> StepMessage:
    sx, sy = shift
    vt = lambda name: [v[0] for v in VTYPES].index(name)  # noqa: E731
    size = lambda name: VTYPES[vt(name)][2:]  # noqa: E731
    x = np.array([50.0, 105.0, 105.0]) + sx
    y = np.array([-1.6, -1.6, -1.6]) + sy
    agents = AgentBatch(
        ids=["ref", "bus_0", "ped_7"],
        cls=np.array([AgentClass.PASSENGER, AgentClass.BUS, AgentClass.PEDESTRIAN], np.uint8),
        vtype=np.array([vt("car"), vt("city_bus"), vt("DEFAULT_PEDTYPE")], np.uint16),
        x=x,
        y=y,
        angle=np.array([90.0, 90.0, 90.0], f32),
        speed=np.array([10.0, 5.0, 5.0], f32),
        accel=np.array([0.5, -1.0, -1.0], f32),
        signals=np.array([0, 8, 0], np.uint16),
        # LAD: ref at 10 m/s -> 10 m; bus at 5 m/s -> LAD_min = 7 m; the rider: its own position
        la_x=np.array([60.0, 112.0, 105.0]) + sx,
        la_y=np.array([-1.6, -1.6, -1.6]) + sy,
        length=np.array([size("car")[0], size("city_bus")[0], size("DEFAULT_PEDTYPE")[0]], f32),
        width=np.array([size("car")[1], size("city_bus")[1], size("DEFAULT_PEDTYPE")[1]], f32),
        lane=np.array([0, 1, -1], np.int32),
        flags=np.array([AgentFlag.PHYSICS_AUTHORITY, AgentFlag.NEW, AgentFlag.INSIDE_VEHICLE], np.uint8),
    )
    if with_paths:
        path = np.array([[50.0, -1.6], [98.0, -1.6], [112.0, -1.6],
                         [105.0, -1.6], [112.0, -1.6], [200.0, -1.6]]) + (sx, sy)
        agents = AgentBatch(**{**agents.__dict__, "path_offsets": np.array([0, 3, 6, 6], np.uint32),
                               "path_xy": path})
    return StepMessage(
        run="golden",
        step=41,
        time=4.2,
        step_length=0.1,
        agents=agents,
        tls=TrafficLights(["J1"], ["Gr"], np.array([0], np.int32), np.array([3.5], f32), ["0"]),
        vtypes=[VType(i, c) for i, c, _, _ in VTYPES] if with_vtypes else None,
        static_version=STATIC_VERSION,
        epoch=EPOCH,
    )


def _physics() -> PhysicsState:
    return PhysicsState(
        run="golden",
        tick=210,
        time=4.2,
        sumo_step=41,
        agents=PhysicsAgents(
            ids=["ref", "bus_0"],
            cls=np.array([AgentClass.PASSENGER, AgentClass.BUS], np.uint8),
            mode=np.array([AgentMode.PHYSICAL, AgentMode.PHYSICAL], np.uint8),
            x=np.array([49.75, 105.0], f64),
            y=np.array([-1.5, -1.625], f64),
            z=np.array([0.5, 0.75], f32),
            heading=np.array([90.5, 90.0], f32),
            roll=np.array([0.25, 0.0], f32),
            pitch=np.array([-0.5, 0.25], f32),
            speed=np.array([9.75, 5.0], f32),
            steer=np.array([1.5, 0.0], f32),
            drive=np.array([350.0, 0.0], f32),
            brake=np.array([0.0, 1200.0], f32),
            err_lon=np.array([-0.25, 0.0], f32),
            err_lat=np.array([0.125, -0.025], f32),
        ),
        counters={"collisions": 0, "placements": 3, "rejected": 1},
    )


def _static() -> StaticData:
    shapes = [np.asarray(s, f64) for *_, s in LANES]
    counts = [len(s) for s in shapes]
    return StaticData(
        run="golden",
        step_length=0.1,
        net_offset=(-100.0, -200.0),
        projection="!",
        bounds=(0.0, -100.0, 200.0, 10.0),
        lanes=LaneTable(
            ids=[ln[0] for ln in LANES],
            edge=[ln[1] for ln in LANES],
            width=np.array([ln[2] for ln in LANES], f32),
            length=np.array([_lane_length(s) for s in shapes], f32),
            allow=[list(ln[3]) for ln in LANES],
            shape_offsets=np.concatenate(([0], np.cumsum(counts))).astype(np.uint32),
            shape_xy=np.concatenate(shapes),
        ),
        junctions=JunctionTable(
            ids=["J1"],
            shape_offsets=np.array([0, 4], np.uint32),
            shape_xy=np.array([[98.0, -12.0], [112.0, -12.0], [112.0, 4.0], [98.0, 4.0]], f64),
        ),
        vtypes=[VType(i, c) for i, c, _, _ in VTYPES],
        vtype_length=np.array([v[2] for v in VTYPES], f32),
        vtype_width=np.array([v[3] for v in VTYPES], f32),
        tls_ids=["J1"],
        tls_links=TlsLinks(np.array([0, 0], np.uint16), np.array([0, 1], np.uint16),
                           np.array([0, 3], np.int32), np.array([2, 2], np.int32), np.array([1, 4], np.int32)),
        version=STATIC_VERSION,
        epoch=EPOCH,
    )


def valid_messages() -> dict[str, object]:
    return {
        "step": _step(with_paths=True),
        "step_no_paths": _step(with_paths=False, with_vtypes=False),
        "step_utm": _step(with_paths=True, shift=UTM_SHIFT),
        "ego": EgoPose("ego", 150.0, -1.6, 90.0, 8.25, time=12.5, vtype="car"),
        "camera": CameraPose("page1", 152.5, -40.25, time=3.5),
        "physics": _physics(),
        "ack": StepAck("golden", 41, 210),
        # ``ref`` (physics-authoritative in ``step``) is 0.25 m behind SUMO's sample of step 41
        "feedback": PhysicsFeedback("golden", 41, 4.2, ["ref"], np.array([49.75], f64), np.array([-1.5], f64),
                                    np.array([90.0], f32), np.array([8.0], f32), np.array([-0.25], f32),
                                    np.array([0.125], f32), np.array([0], np.uint8)),
        "static": _static(),
        "status": SumoStatus({"steps": 42, "rejected": 0, "acks": 42, "teleports": 0, "ego_drift_max_m": 0.0125}),
    }


def bin_dtype(kind: str, path: str) -> str:
    """Little-endian dtype of the ``bin`` at dotted ``path`` in a message of ``kind``."""
    cols = dict({"step": STEP_AGENT_COLUMNS, "feedback": FEEDBACK_COLUMNS}.get(kind, PHYSICS_AGENT_COLUMNS))
    leaf = path.rsplit(".", 1)[-1]
    if path.startswith("agents.") and leaf in cols and path.count(".") == 1:
        return cols[leaf]
    if path.startswith("tls_links."):
        return dict(TLS_LINK_COLUMNS)[leaf]
    if leaf == "off":
        return "<u4"
    if leaf == "xy64":
        return "<f8"
    return "<f4"  # xy, dxy, widths, lengths


def _wire_json(v, kind: str, path: str = ""):
    if isinstance(v, bytes):
        dt = bin_dtype(kind, path)
        return np.frombuffer(v, dtype=dt).tolist()
    if isinstance(v, dict):
        return {k: _wire_json(x, kind, f"{path}.{k}" if path else k) for k, x in v.items()}
    if isinstance(v, list):
        return [_wire_json(x, kind, path) for x in v]
    return v


def expected_json(msg) -> dict:
    """The wire map of ``msg`` with every ``bin`` replaced by its decoded values.

    Keys are exactly the wire keys of SPEC.md; a client decodes the ``.msgpack``, turns
    each bin into numbers with the dtype SPEC.md gives, and must get this document.
    """
    wire = msgpack.unpackb(encode(msg), raw=False)
    return _wire_json(wire, wire["kind"])


def invalid_vectors() -> dict[str, tuple[bytes, str]]:
    """Byte strings a decoder must reject, with the field its error must name."""
    good = msgpack.unpackb(encode(_step(False)), raw=False)
    out: dict[str, tuple[bytes, str]] = {}

    d = dict(good, v=[2, 0])
    out["invalid_major_version"] = (msgpack.packb(d, use_bin_type=True), "v")

    d = dict(good)
    d["agents"] = dict(good["agents"], x=np.array([1.0, np.nan, 2.0], "<f8").tobytes())
    out["invalid_nan_x"] = (msgpack.packb(d, use_bin_type=True), "agents.x")

    d = dict(good)
    d["agents"] = dict(good["agents"], speed=good["agents"]["speed"][:-4])
    out["invalid_short_column"] = (msgpack.packb(d, use_bin_type=True), "agents.speed")

    d = dict(good)
    del d["step"]
    out["invalid_missing_step"] = (msgpack.packb(d, use_bin_type=True), "step")

    d = dict(good, kind="teleport")
    out["invalid_unknown_kind"] = (msgpack.packb(d, use_bin_type=True), "kind")

    d = dict(good)
    d["agents"] = dict(good["agents"], id=["ref", "bus_0", "ref"])
    out["invalid_duplicate_id"] = (msgpack.packb(d, use_bin_type=True), "agents.id")

    d = dict(good)
    d["agents"] = dict(good["agents"], speed=np.array([10.0, 5.0, 5e4], "<f4").tobytes())
    out["invalid_speed_out_of_range"] = (msgpack.packb(d, use_bin_type=True), "agents.speed")

    d = dict(good, epoch=-1)
    out["invalid_negative_epoch"] = (msgpack.packb(d, use_bin_type=True), "epoch")
    return out


def write_all(directory: Path = GOLDEN_DIR) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, msg in valid_messages().items():
        (directory / f"{name}.msgpack").write_bytes(encode(msg))
        (directory / f"{name}.json").write_text(json.dumps(expected_json(msg), indent=1) + "\n")
        written += [directory / f"{name}.msgpack", directory / f"{name}.json"]
    for name, (data, fld) in invalid_vectors().items():
        (directory / f"{name}.msgpack").write_bytes(data)
        (directory / f"{name}.json").write_text(json.dumps({"error_field": fld}, indent=1) + "\n")
        written += [directory / f"{name}.msgpack", directory / f"{name}.json"]
    return written


if __name__ == "__main__":
    for p in write_all():
        print(p)
