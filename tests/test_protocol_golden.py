"""Golden vectors on disk match the encoder, the decoder and the JSON expectations."""

from __future__ import annotations

import json

import msgpack
import numpy as np
import pytest

from protocol import ProtocolError, decode, encode
from protocol.golden_vectors import (
    GOLDEN_DIR, bin_dtype, expected_json, invalid_vectors, valid_messages,
)


@pytest.mark.parametrize("name", list(valid_messages()))
def test_encoder_reproduces_golden_bytes(name):
    assert encode(valid_messages()[name]) == (GOLDEN_DIR / f"{name}.msgpack").read_bytes()


def _language_neutral_decode(raw: bytes):
    """What a client in another language does: msgpack, then bins by SPEC dtype."""
    wire = msgpack.unpackb(raw, raw=False)
    kind = wire["kind"]

    def walk(v, path):
        if isinstance(v, bytes):
            return np.frombuffer(v, bin_dtype(kind, path)).tolist()
        if isinstance(v, dict):
            return {k: walk(x, f"{path}.{k}" if path else k) for k, x in v.items()}
        if isinstance(v, list):
            return [walk(x, path) for x in v]
        return v

    return walk(wire, "")


@pytest.mark.parametrize("name", list(valid_messages()))
def test_golden_json_matches_bytes(name):
    raw = (GOLDEN_DIR / f"{name}.msgpack").read_bytes()
    expected = json.loads((GOLDEN_DIR / f"{name}.json").read_text())
    assert _language_neutral_decode(raw) == expected
    assert expected == json.loads(json.dumps(expected_json(valid_messages()[name])))


@pytest.mark.parametrize("name", list(valid_messages()))
def test_golden_bytes_decode(name):
    decode((GOLDEN_DIR / f"{name}.msgpack").read_bytes())


@pytest.mark.parametrize("name", list(invalid_vectors()))
def test_invalid_golden_vectors_rejected_with_field(name):
    raw = (GOLDEN_DIR / f"{name}.msgpack").read_bytes()
    assert raw == invalid_vectors()[name][0]
    want = json.loads((GOLDEN_DIR / f"{name}.json").read_text())["error_field"]
    with pytest.raises(ProtocolError) as e:
        decode(raw)
    assert e.value.field == want


def test_spec_names_every_wire_key():
    """SPEC.md documents every key the encoder emits."""
    spec = (GOLDEN_DIR.parent / "SPEC.md").read_text()
    missing = set()

    def keys(v):
        if isinstance(v, dict):
            for k, x in v.items():
                if f"`{k}`" not in spec:
                    missing.add(k)
                keys(x)

    for msg in valid_messages().values():
        keys(msgpack.unpackb(encode(msg), raw=False))
    assert not missing, f"SPEC.md does not document: {sorted(missing)}"
