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

from protocol.codec import PHYSICS_AGENT_COLUMNS, STEP_AGENT_COLUMNS, TLS_LINK_COLUMNS, encode
from protocol.messages import (
    AgentBatch,
    AgentClass,
    AgentFlag,
    AgentMode,
    EgoPose,
    JunctionTable,
    LaneTable,
    PhysicsAgents,
    PhysicsState,
    StaticData,
    StepAck,
    StepMessage,
    TlsLinks,
    TrafficLights,
    VType,
)

GOLDEN_DIR = Path(__file__).with_name("golden")

f32, f64 = np.float32, np.float64


def _step(with_paths: bool) -> StepMessage:
    agents = AgentBatch(
        ids=["ref", "bus_0", "ped_7"],
        cls=np.array([AgentClass.PASSENGER, AgentClass.BUS, AgentClass.PEDESTRIAN], np.uint8),
        vtype=np.array([0, 1, 2], np.uint16),
        x=np.array([12.5, -40.25, 3.0], f64),
        y=np.array([-1.6, 7.75, 20.5], f64),
        angle=np.array([90.0, 270.0, 0.0], f32),
        speed=np.array([13.9, 8.5, 1.25], f32),
        accel=np.array([0.5, -1.0, 0.0], f32),
        signals=np.array([8, 2, 0], np.uint16),
        la_x=np.array([22.5, -48.75, 3.0], f32),
        la_y=np.array([-1.6, 7.75, 27.5], f32),
        length=np.array([5.0, 12.0, 0.215], f32),
        width=np.array([1.8, 2.5, 0.478], f32),
        lane=np.array([0, 1, -1], np.int32),
        flags=np.array([0, AgentFlag.NEW, AgentFlag.INSIDE_VEHICLE], np.uint8),
    )
    if with_paths:
        agents = AgentBatch(
            **{**agents.__dict__,
               "path_offsets": np.array([0, 3, 5, 5], np.uint32),
               "path_xy": np.array([[12.5, -1.6], [20.0, -1.6], [30.0, -1.6],
                                    [-40.25, 7.75], [-60.0, 7.75]], f32)}
        )
    return StepMessage(
        run="golden",
        step=42,
        time=4.2,
        step_length=0.1,
        agents=agents,
        tls=TrafficLights(["J1"], ["GGrrGGrr"], np.array([2], np.int32), np.array([3.5], f32)),
        vtypes=[VType("car", "passenger"), VType("city_bus", "bus"), VType("DEFAULT_PEDTYPE", "pedestrian")],
    )


def _physics() -> PhysicsState:
    n = 2
    return PhysicsState(
        run="golden",
        tick=210,
        time=4.2,
        sumo_step=42,
        agents=PhysicsAgents(
            ids=["ref", "ego"],
            cls=np.array([0, 0], np.uint8),
            mode=np.array([AgentMode.PHYSICAL, AgentMode.EXTERNAL], np.uint8),
            x=np.array([12.25, 100.0], f64),
            y=np.array([-1.5, 50.0], f64),
            z=np.array([0.5, 0.5], f32),
            heading=np.array([90.5, 180.0], f32),
            roll=np.array([0.25, 0.0], f32),
            pitch=np.array([-0.5, 0.0], f32),
            speed=np.array([13.75, 5.0], f32),
            steer=np.array([1.5, 0.0], f32),
            drive=np.array([350.0, 0.0], f32),
            brake=np.array([0.0, 0.0], f32),
            err_lon=np.array([-0.25, 0.0], f32),
            err_lat=np.array([0.125, 0.0], f32)[:n],
        ),
        counters={"collisions": 0, "placements": 3, "rejected": 1},
    )


def _static() -> StaticData:
    return StaticData(
        run="golden",
        step_length=0.1,
        net_offset=(-100.0, -200.0),
        projection="!",
        bounds=(0.0, 0.0, 300.0, 300.0),
        lanes=LaneTable(
            ids=["E0_0", ":J1_0_0"],
            edge=["E0", ":J1_0"],
            width=np.array([3.2, 3.2], f32),
            length=np.array([100.0, 8.5], f32),
            allow=[["passenger", "taxi", "bus"], ["passenger"]],
            shape_offsets=np.array([0, 2, 5], np.uint32),
            shape_xy=np.array([[0.0, -1.6], [100.0, -1.6], [100.0, -1.6], [104.0, -3.0], [106.4, -8.0]], f32),
        ),
        junctions=JunctionTable(
            ids=["J1"],
            shape_offsets=np.array([0, 4], np.uint32),
            shape_xy=np.array([[100.0, -10.0], [110.0, -10.0], [110.0, 10.0], [100.0, 10.0]], f32),
        ),
        vtypes=[VType("car", "passenger"), VType("city_bus", "bus")],
        vtype_length=np.array([5.0, 12.0], f32),
        vtype_width=np.array([1.8, 2.5], f32),
        tls_ids=["J1"],
        tls_links=TlsLinks(np.array([0, 0], np.uint16), np.array([0, 1], np.uint16),
                           np.array([0, 0], np.int32), np.array([-1, -1], np.int32), np.array([1, -1], np.int32)),
    )


def valid_messages() -> dict[str, object]:
    return {
        "step": _step(with_paths=True),
        "step_no_paths": _step(with_paths=False),
        "ego": EgoPose("ego", 55.5, -1.6, 90.0, 8.25, time=12.5, vtype="car"),
        "physics": _physics(),
        "ack": StepAck("golden", 42, 210),
        "static": _static(),
    }


def bin_dtype(kind: str, path: str) -> str:
    """Little-endian dtype of the ``bin`` at dotted ``path`` in a message of ``kind``."""
    cols = dict(STEP_AGENT_COLUMNS if kind == "step" else PHYSICS_AGENT_COLUMNS)
    leaf = path.rsplit(".", 1)[-1]
    if path.startswith("agents.") and leaf in cols and path.count(".") == 1:
        return cols[leaf]
    if path.startswith("tls_links."):
        return dict(TLS_LINK_COLUMNS)[leaf]
    if leaf == "off":
        return "<u4"
    return "<f4"  # xy, widths, lengths


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
