"""Codec: round trips, validation errors that name the field, fuzzing, size budget."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import (
    SCHEMA_VERSION, AgentBatch, CameraPose, EgoPose, PhysicsState, ProtocolError, StaticData, StepAck, StepMessage,
    decode, decode_as, encode,
)
from protocol.codec import STEP_AGENT_COLUMNS
from protocol.golden_vectors import valid_messages
from protocol.messages import PhysicsFeedback, SumoStatus
from synthetic.traffic import synthetic_step


#: Fields sent as float32 offsets from the agent's float64 position: equal to 1 mm.
ANCHORED = ("la_x", "la_y", "path_xy")


def _assert_same(a, b, path="msg"):
    if hasattr(a, "__dataclass_fields__"):
        assert type(a) is type(b), path
        for k in a.__dataclass_fields__:
            _assert_same(getattr(a, k), getattr(b, k), f"{path}.{k}")
    elif isinstance(a, np.ndarray) and path.rsplit(".", 1)[-1] in ANCHORED:
        assert np.asarray(b).dtype == np.float64, path
        np.testing.assert_allclose(np.asarray(a, np.float64), b, rtol=0, atol=1e-3, err_msg=path)
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=path)
    elif isinstance(a, float):
        assert a == pytest.approx(b, rel=0, abs=0), path
    else:
        assert a == b, path


@pytest.mark.parametrize("name", list(valid_messages()))
def test_round_trip_every_message_kind(name):
    msg = valid_messages()[name]
    out = decode(encode(msg))
    _assert_same(msg, out)


def test_round_trip_large_step_with_paths():
    msg = synthetic_step(500, seed=3, path_points=9)
    out = decode_as(encode(msg), StepMessage)
    _assert_same(msg, out)
    assert out.agents.path(17).shape == (9, 2)
    np.testing.assert_allclose(out.agents.path(17), msg.agents.path_xy[17 * 9 : 18 * 9], rtol=0, atol=1e-3)


def test_decoded_columns_are_numpy_ready():
    out = decode(encode(synthetic_step(10)))
    assert out.agents.x.dtype == np.float64 and out.agents.speed.dtype == np.float32
    assert (out.agents.x * 2).shape == (10,)


def test_decode_as_rejects_other_kind():
    with pytest.raises(ProtocolError, match="expected a StepMessage"):
        decode_as(encode(StepAck("r", 1, 2)), StepMessage)


def test_byte_budget_1000_agents_without_paths():
    data = encode(synthetic_step(1000))
    assert len(data) / 1000 <= 64


def _wire(msg):
    return msgpack.unpackb(encode(msg), raw=False)


def _pack(d):
    return msgpack.packb(d, use_bin_type=True)


def test_other_major_version_names_both_versions():
    d = _wire(EgoPose("ego", 1, 2, 3, 4))
    d["v"] = [7, 3]
    with pytest.raises(ProtocolError) as e:
        decode(_pack(d))
    ours = f"{SCHEMA_VERSION[0]}.{SCHEMA_VERSION[1]}"
    assert e.value.field == "v" and "7.3" in str(e.value) and ours in str(e.value)


def test_newer_minor_version_is_accepted():
    d = _wire(EgoPose("ego", 1, 2, 3, 4))
    d["v"] = [1, 9]
    assert decode(_pack(d)).x == 1


@pytest.mark.parametrize("col,dt", STEP_AGENT_COLUMNS)
def test_wrong_length_column_names_field(col, dt):
    d = _wire(synthetic_step(4))
    d["agents"][col] = d["agents"][col][: -np.dtype(dt).itemsize]
    with pytest.raises(ProtocolError) as e:
        decode(_pack(d))
    assert e.value.field == f"agents.{col}"


@pytest.mark.parametrize("col", ["x", "y", "angle", "speed", "la_dx", "length"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_column_rejected(col, bad):
    d = _wire(synthetic_step(4))
    dt = dict(STEP_AGENT_COLUMNS)[col]
    arr = np.frombuffer(d["agents"][col], dt).copy()
    arr[2] = bad
    d["agents"][col] = arr.tobytes()
    with pytest.raises(ProtocolError, match="finite") as e:
        decode(_pack(d))
    assert e.value.field == f"agents.{col}"


def test_non_finite_scalar_rejected():
    d = _wire(EgoPose("ego", 1, 2, 3, 4))
    d["x"] = math.nan
    with pytest.raises(ProtocolError) as e:
        decode(_pack(d))
    assert e.value.field == "x"


def test_absurd_agent_count_rejected_before_allocation():
    d = _wire(synthetic_step(2))
    d["agents"]["n"] = 10**9
    with pytest.raises(ProtocolError) as e:
        decode(_pack(d))
    assert e.value.field == "agents.n"


def test_wrong_types_name_field():
    d = _wire(StepAck("r", 1, 2))
    d["step"] = "one"
    with pytest.raises(ProtocolError, match="integer") as e:
        decode(_pack(d))
    assert e.value.field == "step"


def test_class_out_of_range_rejected():
    d = _wire(synthetic_step(3))
    d["agents"]["cls"] = bytes([0, 1, 200])
    with pytest.raises(ProtocolError) as e:
        decode(_pack(d))
    assert e.value.field == "agents.cls"


def test_vtype_index_out_of_table_rejected():
    d = _wire(synthetic_step(3))
    d["agents"]["vtype"] = np.array([0, 0, 5], "<u2").tobytes()
    with pytest.raises(ProtocolError) as e:
        decode(_pack(d))
    assert e.value.field == "agents.vtype"


def test_path_offsets_must_rise_to_point_count():
    d = _wire(synthetic_step(3, path_points=2))
    d["agents"]["path"]["off"] = np.array([0, 4, 2, 6], "<u4").tobytes()
    with pytest.raises(ProtocolError) as e:
        decode(_pack(d))
    assert e.value.field == "agents.path.off"


def test_top_level_not_a_map():
    with pytest.raises(ProtocolError, match="map"):
        decode(_pack([1, 2, 3]))


def test_static_from_a_1_0_sender_without_tls_links_decodes():
    d = _wire(valid_messages()["static"])
    d["v"] = [1, 0]
    del d["tls_links"]
    out = decode(_pack(d))
    assert len(out.tls_links.tls) == 0 and out.tls_ids == ["J1"]


def test_tls_link_lane_index_out_of_range_rejected():
    d = _wire(valid_messages()["static"])
    d["tls_links"]["to_lane"] = np.array([5, -1], "<i4").tobytes()
    with pytest.raises(ProtocolError) as e:
        decode(_pack(d))
    assert e.value.field == "tls_links.to_lane"


def test_empty_step_round_trip():
    msg = StepMessage("r", 0, 0.0, 0.1, AgentBatch.empty(), valid_messages()["step"].tls, [])
    assert decode(encode(msg)).agents.n == 0


@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(st.binary(max_size=2048))
def test_no_byte_string_crashes_decoder(data):
    try:
        decode(data)
    except ProtocolError:
        pass


_msgpack_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats()
    | st.text(max_size=8) | st.binary(max_size=24),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.text(max_size=6), children, max_size=4),
    max_leaves=20,
)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(st.sampled_from(list(valid_messages())), st.data())
def test_mutated_valid_messages_only_raise_protocol_error(name, data):
    """Replace one field anywhere in a valid message by an arbitrary msgpack value."""
    d = _wire(valid_messages()[name])
    node = d
    while True:
        key = data.draw(st.sampled_from(sorted(node)))
        if isinstance(node[key], dict) and data.draw(st.booleans()):
            node = node[key]
            continue
        node[key] = data.draw(_msgpack_values)
        break
    try:
        out = decode(_pack(d))
    except ProtocolError:
        return
    assert isinstance(out, (StepMessage, EgoPose, CameraPose, PhysicsState, PhysicsFeedback, StepAck, StaticData,
                            SumoStatus))


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(list(valid_messages())), st.data())
def test_truncated_messages_rejected(name, data):
    raw = encode(valid_messages()[name])
    cut = data.draw(st.integers(0, len(raw) - 1))
    with pytest.raises(ProtocolError):
        decode(raw[:cut])


def test_round_trip_step_whose_agents_have_no_path_points():
    """Offsets for every agent but no points at all (agents parked or at their route's end)."""
    from dataclasses import replace

    msg = synthetic_step(5, seed=1, path_points=2)
    agents = replace(msg.agents, path_offsets=np.zeros(6, np.uint32), path_xy=np.zeros((0, 2), np.float32))
    out = decode_as(encode(replace(msg, agents=agents)), StepMessage)
    assert out.agents.n == 5 and len(out.agents.path_xy) == 0
