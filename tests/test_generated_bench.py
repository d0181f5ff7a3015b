"""``sumoco bench generated`` builds scenarios nobody has seen as a new user would: a network
from netgenerate and randomTrips demand of every SUMO default vClass plus persons, at 0.05 s
steps with the sublane model (real SUMO tools; the runs themselves are the benchmark's)."""

from __future__ import annotations

import re

from sumoco.app.generated_bench import NETWORKS, STEP_S, VCLASS_PERIOD_S, generate


def test_a_generated_scenario_has_every_default_vclass_and_persons(tmp_path):
    cfg = generate("lefthand_grid", tmp_path / "g")
    text = cfg.read_text()
    assert f'<step-length value="{STEP_S}"/>' in text and '<lateral-resolution value="0.8"/>' in text
    files = re.search(r'route-files value="([^"]+)"', text).group(1).split(",")
    demand = {f.split(".")[0]: (cfg.parent / f).read_text() for f in files}
    # every default class found edges it may use on this network (sidewalks and bike lanes too)
    assert set(VCLASS_PERIOD_S) <= set(demand), sorted(demand)
    for vclass in VCLASS_PERIOD_S:
        assert f'vClass="{vclass}"' in demand[vclass] and demand[vclass].count("<trip ") >= 3, vclass
    assert demand["persons"].count("<person ") >= 20
    assert 'lefthand="true"' in (cfg.parent / "net.net.xml").read_text()[:5000]
    assert set(NETWORKS) == {"spider", "random", "grid", "lefthand_grid"}
