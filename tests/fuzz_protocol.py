"""Coverage-guided fuzzing of the wire decoder over every message kind (atheris / libFuzzer).

    python tests/fuzz_protocol.py --seconds 600      # what `make fuzz` runs
    python tests/fuzz_protocol.py --seconds 12       # the short run inside `make test`

Each input is read by ``atheris.FuzzedDataProvider`` as one of three cases:
0. raw bytes straight into ``decode``;
1. a golden message of any kind, unpacked, with a few fields anywhere in it replaced by
   fuzzed msgpack values (ints, floats incl. NaN/inf, strings, bins of any length, arrays,
   maps, None, bools), packed again and decoded;
2. raw bytes decoded under tiny ``DecodeLimits`` (the limits must hold inside msgpack).

The properties: ``decode`` returns a message or raises ``ProtocolError`` and nothing else;
a message it accepts encodes again and decodes to the same kind, ids and agent count.
When the C fast path is built (``protocol.codec.FAST_CODEC``), ``decode`` and ``encode`` go
through it for steps and physics states: they must agree with ``decode_python`` and
``encode_python`` exactly (the same message, the same error, the same bytes).
libFuzzer's ``-rss_limit_mb`` turns unbounded memory growth into a failure. Exit code 0
means no input broke a property within the budget.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

import atheris

with atheris.instrument_imports(include=["protocol"]):
    import msgpack

    import numpy as np

    from protocol.codec import DEFAULT_LIMITS, DecodeLimits, decode, decode_python, encode, encode_python
    from protocol.errors import ProtocolError
    from protocol.golden_vectors import GOLDEN_DIR, valid_messages

_GOLDEN = [msgpack.unpackb(encode(m), raw=False) for m in valid_messages().values()]
_TINY = DecodeLimits(max_agents=2, max_static_rows=4, max_points=8, max_str=16, max_bytes=4096)


def _value(fdp: atheris.FuzzedDataProvider, depth: int = 0):
    kind = fdp.ConsumeIntInRange(0, 10 if depth < 2 else 7)
    if kind == 0:
        return None
    if kind == 1:
        return fdp.ConsumeBool()
    if kind == 2:
        return fdp.ConsumeIntInRange(-(2**63), 2**64 - 1)
    if kind == 3:
        return fdp.ConsumeRegularFloat()
    if kind == 4:
        return fdp.PickValueInList([float("nan"), float("inf"), -float("inf"), -0.0, 1e308])
    if kind == 5:
        return fdp.ConsumeUnicodeNoSurrogates(fdp.ConsumeIntInRange(0, 40))
    if kind in (6, 7):
        return fdp.ConsumeBytes(fdp.ConsumeIntInRange(0, 64))
    if kind == 8:
        return [_value(fdp, depth + 1) for _ in range(fdp.ConsumeIntInRange(0, 4))]
    n = fdp.ConsumeIntInRange(0, 4)
    return {fdp.ConsumeUnicodeNoSurrogates(6): _value(fdp, depth + 1) for _ in range(n)}


def _mutate(doc, fdp: atheris.FuzzedDataProvider) -> None:
    """Replace (or delete) one field somewhere in ``doc`` (maps and arrays, in place)."""
    node = doc
    while True:
        if isinstance(node, dict) and node:
            key = fdp.PickValueInList(sorted(node))
        elif isinstance(node, list) and node:
            key = fdp.ConsumeIntInRange(0, len(node) - 1)
        else:
            return
        child = node[key]
        if isinstance(child, (dict, list)) and child and fdp.ConsumeBool():
            node = child
            continue
        action = fdp.ConsumeIntInRange(0, 3)
        if action == 0 and isinstance(node, dict):
            del node[key]
        elif action == 1 and isinstance(child, bytes):  # the same bin, cut or grown
            cut = fdp.ConsumeIntInRange(0, len(child) + 16)
            node[key] = (child + fdp.ConsumeBytes(16))[:cut]
        else:
            node[key] = _value(fdp)
        return


def _same(a, b) -> bool:
    """Equal down to the bits (dtypes, shapes, array bytes, value types)."""
    if type(a) is not type(b):
        return False
    if hasattr(a, "__dataclass_fields__"):
        return all(_same(getattr(a, k), getattr(b, k)) for k in a.__dataclass_fields__)
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    return a == b or (a != a and b != b)


def _check(data: bytes, limits: DecodeLimits | None = None) -> None:
    lim = DEFAULT_LIMITS if limits is None else limits
    try:
        msg = decode(data, lim)
    except ProtocolError as e:
        try:  # the fast path steps aside on what it refuses: the Python decoder's own error
            decode_python(data, lim)
        except ProtocolError as ref:
            assert (str(e), e.field) == (str(ref), ref.field), (str(e), str(ref))
            return
        raise AssertionError(f"decode refused what decode_python accepts: {e}") from None
    assert _same(msg, decode_python(data, lim)), "decode and decode_python disagree"
    assert encode(msg) == encode_python(msg), "encode and encode_python disagree"
    again = decode(encode(msg))  # an accepted message must survive its own round trip
    assert type(again) is type(msg), (type(again), type(msg))
    agents = getattr(msg, "agents", None)
    if agents is not None:
        assert again.agents.ids == agents.ids


def test_one_input(data: bytes) -> None:
    fdp = atheris.FuzzedDataProvider(data)
    case = fdp.ConsumeIntInRange(0, 2)
    if case == 0:
        _check(fdp.ConsumeBytes(fdp.remaining_bytes()))
    elif case == 1:
        doc = msgpack.unpackb(msgpack.packb(fdp.PickValueInList(_GOLDEN), use_bin_type=True), raw=False)
        for _ in range(fdp.ConsumeIntInRange(1, 4)):
            _mutate(doc, fdp)
        try:
            raw = msgpack.packb(doc, use_bin_type=True)
        except (OverflowError, ValueError, TypeError):  # e.g. an int msgpack cannot hold
            return
        _check(raw)
    else:
        _check(fdp.ConsumeBytes(fdp.remaining_bytes()), _TINY)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=int, default=600, help="fuzzing budget [s]")
    ap.add_argument("--corpus", type=Path, default=Path(__file__).resolve().parents[1] / "build" / "fuzz-corpus",
                    help="corpus folder, kept between runs (default: build/fuzz-corpus)")
    ap.add_argument("--rss-mb", type=int, default=2048, help="fail when the process grows beyond [MiB]")
    args = ap.parse_args(argv)
    corpus = args.corpus
    corpus.mkdir(parents=True, exist_ok=True)
    for seed in GOLDEN_DIR.glob("*.msgpack"):  # the golden vectors seed the raw-bytes case
        shutil.copy(seed, corpus / seed.name)
    lib_args = [sys.argv[0], str(corpus), f"-max_total_time={args.seconds}", f"-rss_limit_mb={args.rss_mb}",
                "-timeout=10", "-print_final_stats=1", f"-artifact_prefix={corpus.parent}/fuzz-"]
    atheris.Setup(lib_args, test_one_input)
    atheris.Fuzz()  # exits the process: 0 when the budget ran out, non-zero on a finding
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    sys.exit(main())
