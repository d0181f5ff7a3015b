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
from protocol.keys import Keys
from runtime.config import ConfigError, RunConfig, from_dict
from synthetic.traffic import synthetic_step


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


# ------------------------------------------------------------------ decoders outside the daemons


class _NoFile:
    """A recorder without a file: the live recorder's writer needs only these; it keeps the
    schema of each record written."""

    context = None

    def __init__(self) -> None:
        self.written: list[tuple[bytes, str | None]] = []

    def write(self, topic, payload, stamp_ns=None, schema=None) -> None:
        self.written.append((payload, schema))

    def flush(self) -> None:
        pass


def _sample(key: str, payload: bytes):
    from types import SimpleNamespace

    return SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: payload))


def test_recorder_peeks_and_compacts_within_the_run_limits():
    from protocol.codec import peek
    from sumoco.recording.record import LiveRecorder, RecordConfig

    def _peek(payload, key, limits=DEFAULT_LIMITS):  # one number, or None
        return peek(payload, (key,), limits).get(key)

    lim = RunConfig(max_agents=50).decode_limits
    step = encode(synthetic_step(5, step=7))
    assert _peek(step, "t", lim) == decode(step).time and _peek(step, "sv", lim) == 0
    wide = msgpack.packb({"agents": [None] * 100_000, "t": 2.5})  # the other values are skipped, not built
    assert _peek(wide, "t", lim) == 2.5
    big = msgpack.packb({"pad": b"x" * 2_000_000, "t": 1.0})  # over 1 MiB + 4 KiB per agent
    assert _peek(big, "t") == 1.0 and _peek(big, "t", lim) is None
    for header in (b"\xdd" + struct.pack(">I", 2**31), b"\xc6" + struct.pack(">I", 2**31)):
        t0 = time.perf_counter()
        assert _peek(b"\x82\xa1t" + header + b"\x00" * 8, "t", lim) is None
        assert time.perf_counter() - t0 < 0.5
    out = _NoFile()
    live = LiveRecorder(None, Keys("sumoco", "lim"), out, limits=lim, config=RecordConfig(scene=False, physics_hz=0.0))
    over = encode(synthetic_step(60, step=8))  # more agents than the run is configured for
    try:
        live.on_sample(_sample(live.keys.step, step))
        live.on_sample(_sample(live.keys.step, over))
        assert live.drain(5)
    finally:
        live.stop(5)
    assert out.written[0][1] == "sumoco.rec.step"  # compacted
    assert out.written[1] == (over, None)  # kept as it came
    assert live.stats()["compact_errors"] == 1


def test_scene_decodes_steps_with_the_run_limits_and_static_data_with_the_default_ones():
    from sumoco.viewing import scene

    if not scene.available():
        pytest.skip("foxglove-sdk is not installed")
    import foxglove

    keys = Keys("sumoco", "lim")
    pub = scene.ScenePublisher(foxglove.Context(), limits=RunConfig(max_agents=50).decode_limits)
    assert pub.feed(keys.static, encode(valid_messages()["static"]))
    assert pub.feed(keys.step, encode(synthetic_step(5)))
    assert not pub.feed(keys.step, encode(synthetic_step(60, step=2))) and pub.errors == 1


def test_gateway_upstream_is_decoded_with_the_tightest_limits():
    from sumoco.viewing.gateway import MAX_UPSTREAM_BYTES, UPSTREAM_LIMITS

    ego = msgpack.unpackb(encode(valid_messages()["ego"]), raw=False)
    assert decode(msgpack.packb(ego), UPSTREAM_LIMITS) == valid_messages()["ego"]
    padded = msgpack.packb({**ego, "junk": list(range(100))})  # unknown keys are fine, long arrays not
    assert decode(padded) == valid_messages()["ego"]
    with pytest.raises(ProtocolError, match="msgpack"):
        decode(padded, UPSTREAM_LIMITS)
    assert UPSTREAM_LIMITS.max_bytes == MAX_UPSTREAM_BYTES


def test_viewer_map_reply_decoded_within_limits():
    import hashlib
    from types import SimpleNamespace

    from sumoco.viewing.viewer.server import LatestStore, ViewerConfig, ZenohFeed

    glb = b"glTF" + b"\x00" * 60
    good = msgpack.packb({"v": [1, 2], "kind": "map", "sha256": hashlib.sha256(glb).hexdigest(), "glb": glb})
    hostile = msgpack.packb({"v": [1, 2], "kind": "map", "pad": [None] * 3_000_000})  # > 2,000,000 rows
    keys = Keys("sumoco", "lim")
    static = encode(valid_messages()["static"])

    class Session:
        """Serves the static data and ``maps`` as the SUMO side's map replies."""

        def __init__(self, maps: list[bytes]) -> None:
            self.maps = maps

        def get(self, key, timeout):
            data = [static] if key == keys.static else self.maps if key.startswith(keys.sumo_map) else []
            return [SimpleNamespace(ok=SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda d=d: d)))
                    for d in data]

        def declare_subscriber(self, *args, **kwargs):
            return SimpleNamespace(undeclare=lambda: None)

        def liveliness(self):
            return self

    def map_of(maps: list[bytes]) -> tuple[bytes | None, str]:
        """The map a feed holds once the SUMO side answered with ``maps``."""
        store = LatestStore()
        feed = ZenohFeed(Session(maps), keys, store, ViewerConfig()).start()
        try:
            deadline = time.monotonic() + 20
            while store.map_glb is None and time.monotonic() < deadline:
                time.sleep(0.02)
        finally:
            feed.stop()
        return store.map_glb, store.map_source

    glb_here, source = map_of([hostile])  # refused while msgpack parses, no exception: built here
    assert glb_here is not None and source == "static"
    assert map_of([hostile, good]) == (glb, "sumo")


def test_peek_reads_top_level_numbers_from_the_head_or_the_whole_message():
    from protocol.codec import peek

    step = encode(synthetic_step(3000, step=42))  # well over the 4 KiB head
    assert len(step) > 4096
    got = peek(step, ("step", "sv", "t"))
    assert got["step"] == 42 and got["sv"] == 0 and got["t"] == decode(step).time
    late = msgpack.packb({"pad": b"x" * 10_000, "sv": 3, "flag": True, "name": "x"})  # past the head
    assert peek(late, ("sv", "flag", "name", "absent")) == {"sv": 3}  # no bools, strings or absent keys
    assert peek(b"\x93\x01\x02", ("sv",)) == {} and peek(b"\xc1", ("sv",)) == {}  # not a map; corrupt
