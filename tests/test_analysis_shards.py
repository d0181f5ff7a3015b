"""The report of an instance run as shard processes (``--processes``): one entry for the
instance, with the samples of every shard and their counters summed."""

from __future__ import annotations

import dataclasses

import numpy as np

from sumoco.analysis.summary import Analysis
from tests.test_analysis_lanechange import _messages, _static


def _split(state, shard: int):
    """The part of ``state`` shard ``shard`` of 2 simulates: ``car`` in shard 0, the rest in 1."""
    a = state.agents
    rows = [i for i, name in enumerate(a.ids) if (name == "car") == (shard == 0)]
    cols = {f.name: np.asarray(getattr(a, f.name))[rows] for f in dataclasses.fields(a)
            if f.name != "ids" and isinstance(getattr(a, f.name), np.ndarray) and len(getattr(a, f.name)) == a.n}
    part = dataclasses.replace(a, ids=[a.ids[i] for i in rows], **cols)
    return dataclasses.replace(state, agents=part, counters={"collisions": 1 + shard, "shards_alive": 2})


def _summary(sharded: bool) -> dict:
    steps, states = _messages(change=True)
    an = Analysis()
    an.feed("", 0, _static())
    items = [(m.time, 0, "", m) for m in steps]
    for m in states:
        if sharded:
            items += [(m.time, 1, f"default.{i}of2", _split(m, i)) for i in (0, 1)]
        else:
            items.append((m.time, 1, "default", dataclasses.replace(m, counters={"collisions": 3, "shards_alive": 2})))
    for _, _, inst, m in sorted(items, key=lambda x: x[:2]):
        an.feed(inst, 0, m)
    return an.summary()["presets"]


def test_shards_of_an_instance_are_reported_as_the_instance():
    whole, sharded = _summary(False), _summary(True)
    assert set(sharded) == {"default"}
    assert sharded["default"]["error_m"] == whole["default"]["error_m"]
    c = sharded["default"]["counters"]
    assert c["collisions"] == 3  # 1 + 2: counts add up over the shards
    assert c["shards_alive"] == 2  # the shards' view of their set: not summed
