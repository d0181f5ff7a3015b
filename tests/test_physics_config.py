"""Physics config: typed tables, preset validation, whole-number rate checks."""

from __future__ import annotations

from pathlib import Path

import pytest

from physics_side.config import check_rates, load_physics_config, ticks_to
from protocol.errors import ConfigError
from runtime.config import load_toml


def _load(tmp_path: Path, text: str):
    p = tmp_path / "c.toml"
    p.write_text(text)
    data, base = load_toml(p)
    return load_physics_config(data, base, str(p))


def test_defaults_are_the_documented_ones(tmp_path):
    s = _load(tmp_path, "")
    assert (s.physics.control_hz, s.physics.timestep_s, s.physics.sumo_step_s) == (50.0, 0.005, 0.1)
    p = s.control.paper
    assert (p.k1, p.k2, p.lad_min, p.lad_max, p.k_lad, p.k_steer) == (15.0, 1.0, 7.0, 10.0, 1.0, 0.05)
    assert s.physics.preset_for("bus") == "default"


def test_tables_are_typed_and_checked(tmp_path):
    s = _load(tmp_path, """
[physics]
preset = "paper"
presets = {pedestrian = "kinematic"}
state_every = 5
[control.paper]
lad_min = 5
[control.default]
lateral = "pursuit"
""")
    assert s.physics.preset_for("pedestrian") == "kinematic" and s.physics.preset_for("taxi") == "paper"
    assert s.control.paper.lad_min == 5.0 and s.control.default.lateral == "pursuit"
    with pytest.raises(ConfigError, match=r"control\.paper\.k_1: unknown key"):
        _load(tmp_path, "[control.paper]\nk_1 = 3\n")
    with pytest.raises(ConfigError, match=r"physics\.presets\.truck: unknown agent type"):
        _load(tmp_path, '[physics]\npresets = {truck = "paper"}\n')
    with pytest.raises(ConfigError, match=r"physics\.presets\.bus: expected one of"):
        _load(tmp_path, '[physics]\npresets = {bus = "fast"}\n')
    with pytest.raises(ConfigError, match=r"k_lad: the paper requires >= 1"):
        _load(tmp_path, "[control.paper]\nk_lad = 0.5\n")
    with pytest.raises(ConfigError, match=r"physics\.preset: expected one of"):
        _load(tmp_path, '[physics]\npreset = "fast"\n')


def test_rates_any_sumo_step_length():
    r = check_rates(0.1, 50.0, 0.005)
    assert (r.ticks_per_step, r.substeps, r.control_dt) == (5, 4, 0.02)
    assert check_rates(0.05, 100.0, 0.0025).ticks_per_step == 5
    # SUMO steps need not be whole control periods: ticks are counted by time
    for step in (0.01, 0.05, 0.2, 0.5, 1.0):
        check_rates(step, 50.0, 0.005)


@pytest.mark.parametrize("step", [0.01, 0.05, 0.07, 0.1, 0.5, 1.0])
def test_ticks_to_keeps_physics_time_within_half_a_tick(step):
    dt, t, total = 0.02, 0.0, 0
    for k in range(1, 200):
        n = ticks_to(t, k * step, dt)
        t += n * dt
        total += n
        assert abs(t - k * step) <= dt / 2 + 1e-9, (k, t)
    assert total == pytest.approx(199 * step / dt, abs=1)


def test_rate_errors_name_the_number_to_change(tmp_path):
    with pytest.raises(ConfigError, match=r"physics\.timestep_s = 0\.003 s does not divide .* 0\.02 s; change physics\.timestep_s to one of 0\.02, 0\.01"):
        check_rates(0.1, 50.0, 0.003)
    with pytest.raises(ConfigError, match=r"SUMO step length 20 s is outside"):
        check_rates(20.0, 50.0, 0.005)
    with pytest.raises(ConfigError, match=r"physics\.control_hz = 10 Hz is too slow"):
        check_rates(0.1, 10.0, 0.005)
    with pytest.raises(ConfigError, match=r"too coarse.*change physics\.timestep_s to 0\.005"):
        check_rates(0.1, 50.0, 0.02)
    with pytest.raises(ConfigError, match="control_hz"):
        _load(tmp_path, "[physics]\ncontrol_hz = 10\n")


@pytest.mark.parametrize("value", [-1.0, 10_001.0])
def test_a_busy_poll_window_out_of_range_is_named(tmp_path, value):
    assert _load(tmp_path, "").physics.busy_poll_ms == 0.0  # off unless asked for
    assert _load(tmp_path, "[physics]\nbusy_poll_ms = 20.0\n").physics.busy_poll_ms == 20.0
    with pytest.raises(ConfigError, match=r"physics\.busy_poll_ms: expected 0 \(off\) to 10000 ms"):
        _load(tmp_path, f"[physics]\nbusy_poll_ms = {value}\n")
