"""Two-way coupling end to end, real SUMO and real MuJoCo as OS processes in lockstep.

On a straight one-lane road every car is physics-authoritative. ``lead`` stalls in physics
from 15 s to 35 s (``[physics] stall``: full brakes, no drive). SUMO never tells it to stop;
it follows the physical states, so SUMO's traffic queues behind it and drives on after.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from protocol.keys import Keys
from protocol.messages import AgentFlag
from tests.harness import ROOT, Daemon, Probe, assert_exit_codes, endpoint, wait_until

pytestmark = pytest.mark.integration

STRAIGHT = ROOT / "configs" / "scenarios" / "straight" / "straight.sumocfg"
STALL = (15.0, 35.0)  # [s] SUMO time the lead car is held in physics
CAR_LENGTH_M = 4.5


def _run(tmp_path: Path, authority: str, duration_s: float = 45.0, faults: str = "") -> tuple[list, list, dict]:
    cfg = tmp_path / f"{authority}.toml"
    cfg.write_text(f"""
[run]
id = "couple"
timing = "lockstep"
duration_s = {duration_s}
lockstep_timeout_s = 30.0
[coupling]
authority = "{authority}"
[sumo]
sumocfg = "{STRAIGHT}"
[physics]
preset = "default"
stall = ["lead@{STALL[0]:g}-{STALL[1]:g}"]
{faults}
""")
    keys = Keys("sumoco", "couple")
    sumo_ep, phys_ep = endpoint(), endpoint()
    out = tmp_path / f"sumo-{authority}"
    phys = Daemon("physics", ["physics", "--config", str(cfg), "--listen", phys_ep, "--quiet"], tmp_path / authority)
    probe = Probe(keys, [phys_ep])
    sumo = Daemon("sumo", ["sumo", "--config", str(cfg), "--listen", sumo_ep, "--connect", phys_ep,
                           "--output-dir", str(out), "--quiet"], tmp_path / authority)
    try:
        # physics leaves on the final step too, possibly a moment before SUMO: only a failure counts
        wait_until(lambda: sumo.poll() is not None or phys.poll() not in (None, 0), 240, "the run to end",
                   poll_s=0.2)
        phys.leave(30)
    finally:
        probe.close()
        sumo.terminate(5)
        phys.terminate(5)
    assert_exit_codes([sumo, phys])
    with probe.lock:
        steps = sorted(probe.steps, key=lambda m: m.step)
        states = [st for lst in probe.physics.values() for st in lst]
    return steps, states, json.loads((out / "sumoco_stats.json").read_text())


def _row(msg, agent):
    return msg.agents.ids.index(agent) if agent in msg.agents.ids else None


def test_a_stall_in_physics_makes_sumo_traffic_queue_and_drive_on(tmp_path):
    steps, states, stats = _run(tmp_path, "physics")
    assert steps[-1].final and stats["teleports"] == 0
    assert stats["feedback_late"] == 0 and stats["feedback_steps_applied"] >= len(steps) - 2
    assert stats["feedback_clamped"] == 0
    # SUMO's own account: every vehicle it inserted arrived or still runs (none lost to the write-back)
    assert stats["vanished"] == 0 and stats["vehicles_inserted"] >= 5, stats
    assert stats["trips_arrived"] + stats["vehicles_running_end"] == stats["vehicles_inserted"], stats
    gaps, lead_speed, moving_again = [], [], None
    for m in steps:
        i = _row(m, "lead")
        if i is None:
            continue
        assert m.agents.flags[i] & AgentFlag.PHYSICS_AUTHORITY
        behind = [j for j, a in enumerate(m.agents.ids) if a != "lead" and m.agents.x[j] < m.agents.x[i]]
        ahead = [j for j, a in enumerate(m.agents.ids) if a.startswith("f.") and m.agents.x[j] > m.agents.x[i]]
        if STALL[0] + 2.0 <= m.time < STALL[1]:
            lead_speed.append(float(m.agents.speed[i]))
            assert not ahead, f"t={m.time}: {[m.agents.ids[j] for j in ahead]} passed through the stalled car"
            if behind:
                gaps.append(float(m.agents.x[i] - max(m.agents.x[j] for j in behind)))
        if m.time >= STALL[1] and moving_again is None and behind:
            first = max(behind, key=lambda j: m.agents.x[j])
            if m.agents.speed[first] > 2.0:
                moving_again = m.time - STALL[1]
    # SUMO has the lead stopped where physics holds it ...
    assert max(lead_speed) < 0.5, max(lead_speed)
    # ... its followers stopped behind it (a queue formed), none through it ...
    assert gaps and min(gaps) > CAR_LENGTH_M and min(gaps) < CAR_LENGTH_M + 5.0, (min(gaps), max(gaps))
    # ... and drive on within 5 s of its release
    assert moving_again is not None and moving_again <= 5.0, moving_again
    # physics and SUMO agree where the lead is (the intent gap stays small)
    assert stats["intent_gap_p95_m"] < 0.5, stats


def test_a_crash_in_physics_leaves_both_cars_stopped_in_sumo_where_physics_has_them(tmp_path):
    """``lead`` stalls at 15 s; the car behind it, ``f.0``, loses its brakes at 14.5 s and
    coasts into it. The crash is a physics fact: SUMO shows both stopped where physics has
    them, neither removed nor teleported, and the cars behind queue."""
    steps, states, stats = _run(tmp_path, "physics", duration_s=30.0, faults='brake_failure = ["f.0@14.5-40"]')
    assert stats["teleports"] == 0 and stats["feedback_late"] == 0, stats
    assert stats["vanished"] == 0, stats  # collision.action "warn": both crashed cars stay in SUMO
    last_state = max(states, key=lambda st: st.time)
    assert last_state.counters.get("collisions", 0) >= 1, last_state.counters  # they did collide in physics
    m = steps[-1]
    phys = last_state.agents
    for car in ("lead", "f.0"):
        i, j = _row(m, car), phys.ids.index(car)
        assert i is not None, f"{car} vanished from SUMO"
        assert m.agents.speed[i] < 0.5 and phys.speed[j] < 0.5, (car, m.agents.speed[i], phys.speed[j])
        assert abs(m.agents.x[i] - phys.x[j]) < 0.5, (car, m.agents.x[i], phys.x[j])
    gap = m.agents.x[_row(m, "lead")] - CAR_LENGTH_M - m.agents.x[_row(m, "f.0")]
    assert gap < 0.5, gap  # f.0 ended against the lead's rear, as in physics
