"""Decode limits: lengths bounded while msgpack parses, from the configured maximum agents."""

from __future__ import annotations

import struct
import time

import msgpack
import numpy as np
import pytest

from protocol import ProtocolError, decode, encode
from protocol.codec import DEFAULT_LIMITS, DecodeLimits
from protocol.golden_vectors import valid_messages
from sumoco.common.config import ConfigError, RunConfig, from_dict
from sumoco.testing.synthetic import synthetic_step


def test_limits_follow_the_configured_maximum_agents():
    lim = RunConfig(max_agents=50).decode_limits
    assert lim.max_agents == 50 and lim == DecodeLimits.for_agents(50)
    kw = lim.unpack_kwargs()
    assert kw["max_ext_len"] == 0 and kw["max_str_len"] == 4 * lim.max_str
    assert DecodeLimits.for_agents(50).max_points < DEFAULT_LIMITS.max_points
    assert kw["max_array_len"] == 65_535  # 50 agents, or as many traffic lights as u16 indexes
    assert lim.max_bytes < DEFAULT_LIMITS.max_bytes
    # the golden world decodes under live limits; static data keeps the default ones
    for name in ("step", "physics", "ack", "ego"):
        decode(encode(valid_messages()[name]), lim)
    with pytest.raises(ConfigError, match="run.max_agents"):
        from_dict(RunConfig, {"max_agents": 0}, "run")


def test_more_agents_than_configured_rejected_naming_the_count():
    data = encode(synthetic_step(60))
    assert decode(data).agents.n == 60
    with pytest.raises(ProtocolError) as e:
        decode(data, DecodeLimits.for_agents(50))
    assert e.value.field == "agents.n"


def _hostile(header: bytes) -> bytes:
    """A map {"v": [1, 2], "kind": "step", "agents": <header + 8 bytes>}: the header claims far
    more than the payload holds."""
    head = msgpack.packb({"v": [1, 2], "kind": "step"}, use_bin_type=True)
    return bytes([head[0] + 1]) + head[1:] + msgpack.packb("agents") + header + b"\x00" * 8


@pytest.mark.parametrize("header", [
    b"\xdd" + struct.pack(">I", 2**31),  # array32 of 2^31 elements
    b"\xdf" + struct.pack(">I", 2**31),  # map32 of 2^31 entries
    b"\xc6" + struct.pack(">I", 2**31),  # bin32 of 2 GiB
    b"\xdb" + struct.pack(">I", 2**31),  # str32 of 2 GiB
])
def test_hostile_length_prefixes_fail_inside_msgpack(header):
    t0 = time.perf_counter()
    with pytest.raises(ProtocolError, match="msgpack"):
        decode(_hostile(header), DecodeLimits.for_agents(1000))
    assert time.perf_counter() - t0 < 0.5


def test_ext_types_and_oversized_messages_rejected():
    with pytest.raises(ProtocolError, match="msgpack"):
        decode(msgpack.packb({"v": [1, 2], "kind": msgpack.ExtType(5, b"x")}))
    small = DecodeLimits(max_bytes=100)
    with pytest.raises(ProtocolError, match="exceeds 100"):
        decode(encode(valid_messages()["static"]), small)


@pytest.mark.parametrize("name,key,bad", [
    ("physics", "heading", 1e4), ("physics", "speed", -5e3), ("physics", "z", np.inf),
    ("step", "length", -1.0), ("step", "la_dx", 2e5), ("step", "accel", np.nan),
])
def test_out_of_range_and_non_finite_values_name_the_field(name, key, bad):
    d = msgpack.unpackb(encode(valid_messages()[name]), raw=False)
    col = np.frombuffer(d["agents"][key], "<f4").copy()
    col[0] = bad
    d["agents"][key] = col.tobytes()
    with pytest.raises(ProtocolError) as e:
        decode(msgpack.packb(d, use_bin_type=True))
    assert e.value.field == f"agents.{key}"


def test_duplicate_ids_rejected_in_physics_and_static():
    d = msgpack.unpackb(encode(valid_messages()["physics"]), raw=False)
    d["agents"]["id"] = ["ref", "ref"]
    with pytest.raises(ProtocolError, match="twice") as e:
        decode(msgpack.packb(d, use_bin_type=True))
    assert e.value.field == "agents.id"
    d = msgpack.unpackb(encode(valid_messages()["static"]), raw=False)
    d["lanes"]["id"][1] = d["lanes"]["id"][0]
    with pytest.raises(ProtocolError) as e:
        decode(msgpack.packb(d, use_bin_type=True))
    assert e.value.field == "lanes.id"
