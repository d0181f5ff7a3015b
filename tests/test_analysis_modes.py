"""The shadow / two-way comparison (``modes.md``) from run folders' summary.json."""

from __future__ import annotations

import json

import pytest

from protocol.errors import ConfigError
from sumoco.analysis.modes import COLUMNS, cli_main, mode_row, write_modes


def _summary(authority: str, share: float, p95: float, arrived: int, travel: float) -> dict:
    return {
        "authority": authority, "sim_time_s": 60.0,
        "presets": {"paper": {"physical_share": 0.5},
                    "default": {"physical_share": share, "collisions": 0,
                                "error_m": {"overall": {"p50": 0.01, "p95": p95, "max": 1.0}}}},
        "sumo_side": {"trips_arrived": arrived, "travel_time_mean_s": travel, "time_loss_mean_s": 9.5,
                      "vehicles_inserted": 30, "vanished": 0, "teleports": 0,
                      **({"intent_gap_p95_m": 0.15, "feedback_ms": 0.24} if authority == "physics" else {})},
        "daemons": {"exit_codes": {"sumo": 0, "physics-default": 0}},
    }


def test_rows_take_the_followed_preset_and_sumos_trip_account(tmp_path):
    for mode, share, arrived in (("sumo", 0.9987, 14), ("physics", 1.0, 15)):
        (tmp_path / mode).mkdir()
        (tmp_path / mode / "summary.json").write_text(json.dumps(_summary(mode, share, 0.08, arrived, 30.5)))
    rows = write_modes([tmp_path / "sumo", tmp_path / "physics"], tmp_path / "cmp")
    assert [r["authority"] for r in rows] == ["sumo", "physics"]
    assert rows[0]["physical_share"] == 0.9987 and rows[0]["preset"] == "default"
    assert rows[1]["throughput_veh_h"] == 900.0  # 15 trips in 60 s
    assert rows[0]["intent_gap_p95_m"] is None and rows[1]["intent_gap_p95_m"] == 0.15
    md = (tmp_path / "cmp" / "modes.md").read_text()
    assert md.count("\n| ") == 3 and "| physics | 1.000 |" in md and "n/a" in md
    assert len(md.splitlines()[-1].split("|")) == len(COLUMNS) + 2
    assert json.loads((tmp_path / "cmp" / "modes.json").read_text()) == rows
    assert mode_row(tmp_path / "physics")["vanished"] == 0


def test_compare_names_a_folder_without_a_summary(tmp_path):
    class Args:
        runs = [str(tmp_path)]
        out = None
    with pytest.raises(ConfigError, match="expected a run folder with summary.json"):
        cli_main(Args())
