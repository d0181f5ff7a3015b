"""Physics shards: spatial partition with a halo, subsets of a step, take-over of a lost shard."""

from __future__ import annotations

import numpy as np
import pytest

from physics_side.shard import HALO_M, TILE_M, ShardFilter, parse_shard, shard_instance, shard_of_instance, subset
from protocol.errors import ConfigError
from synthetic.traffic import circle_traffic


def test_names_and_arguments():
    assert parse_shard("1/3") == (1, 3)
    assert shard_instance("main", 1, 3) == "main.1of3" and shard_of_instance("main.1of3") == ("main", 1, 3)
    assert shard_of_instance("main") is None
    for bad in ("3/3", "x/2", "1"):
        with pytest.raises(ConfigError, match="--shard"):
            parse_shard(bad)


def test_subset_keeps_rows_and_their_paths():
    a = circle_traffic(6, 0).agents
    s = subset(a, np.array([4, 1]))
    assert s.ids == ["veh4", "veh1"] and s.n == 2
    assert np.array_equal(s.x, a.x[[4, 1]])
    assert np.array_equal(s.path(0), a.path(4)) and np.array_equal(s.path(1), a.path(1))
    assert subset(a, np.zeros(0, np.int64)).n == 0


def test_every_agent_has_exactly_one_shard_and_neighbours_share_it():
    a = circle_traffic(300, 0).agents  # ~2 km of circles: several tiles
    f = [ShardFilter(i, 3) for i in range(3)]
    rows = [x.rows(a) for x in f]
    assert sum(len(r) for r in rows) == a.n and len(set(np.concatenate(rows).tolist())) == a.n
    assert all(len(r) > 0 for r in rows)
    own = f[0].owners(a)
    # cars 22 m apart on one lane: most consecutive pairs share a shard (tiles of 250 m)
    same = np.mean(own[1:] == own[:-1])
    assert same > 0.8, same
    assert TILE_M > 5 * HALO_M


def test_an_agent_keeps_its_shard_inside_the_halo_and_a_lost_shard_is_taken_over():
    f = ShardFilter(0, 2)
    a = circle_traffic(200, 0).agents
    before = f.owners(a).copy()
    later = circle_traffic(200, 5).agents  # 5 m further: nobody leaves the halo of its tiles
    assert np.array_equal(f.owners(later), before)
    # shard 1 dies: shard 0 owns everything from the next step, counted as take-overs
    assert f.set_alive(1, False) and not f.set_alive(1, False)
    assert len(f.rows(later)) == later.n
    assert f.takeovers == int((before == 1).sum()) > 0
    assert f.set_alive(1, True)


def test_a_restarted_sibling_and_the_survivor_split_the_agents_again_without_overlap():
    """Shard 1 dies and comes back with an empty assignment: the survivor drops its sticky
    one, so the two partition the agents again (no agent simulated by both)."""
    a = circle_traffic(200, 0).agents
    survivor = ShardFilter(0, 2)
    survivor.owners(a)
    survivor.set_alive(1, False)
    later = circle_traffic(200, 5).agents
    assert len(survivor.rows(later)) == later.n  # it covers the lost shard meanwhile
    survivor.set_alive(1, True)
    restarted = ShardFilter(1, 2)
    again = circle_traffic(200, 6).agents
    mine, theirs = set(survivor.rows(again).tolist()), set(restarted.rows(again).tolist())
    assert not mine & theirs and len(mine | theirs) == again.n and theirs


def test_every_size_of_a_step_is_reserved_once_without_a_compile_on_the_stepping_thread():
    from dataclasses import replace

    from physics_side.config import PhysicsSettings
    from physics_side.daemon import build_fleet

    fleet = build_fleet(PhysicsSettings())
    try:
        m = circle_traffic(6, 0)
        a = m.agents
        # two agents of another shard are 12 m long: a size this shard has no pool for
        length = a.length.copy()
        length[[1, 4]] = 12.0
        a = replace(a, length=length)
        gen = fleet.world.generation
        assert fleet.reserve(a, m.vtypes) == 1
        assert fleet.world.growing and fleet.world.generation == gen
        assert fleet.reserve(a, m.vtypes) == 0  # known sizes cost one np.unique per step
    finally:
        fleet.world.close()
