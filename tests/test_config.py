"""Typed TOML config: unknown keys and wrong types are errors naming the key."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from protocol.errors import ConfigError
from runtime.config import RunConfig, ZenohConfig, from_dict, load_common, section, load_toml


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "c.toml"
    p.write_text(text)
    return p


def test_defaults_when_tables_absent(tmp_path):
    common, _, _ = load_common(_write(tmp_path, ""))
    assert common.run == RunConfig() and common.zenoh == ZenohConfig()


def test_values_are_typed(tmp_path):
    common, _, _ = load_common(_write(tmp_path, """
[run]
id = "x1"
timing = "lockstep"
duration_s = 30
[zenoh]
listen = ["tcp/127.0.0.1:7000"]
"""))
    assert common.run.duration_s == 30.0 and isinstance(common.run.duration_s, float)
    assert common.zenoh.listen == ("tcp/127.0.0.1:7000",)


def test_unknown_key_names_key_and_choices(tmp_path):
    with pytest.raises(ConfigError, match=r"run\.durration_s: unknown key.*duration_s"):
        load_common(_write(tmp_path, "[run]\ndurration_s = 3\n"))


def test_wrong_type_names_key(tmp_path):
    with pytest.raises(ConfigError, match=r"run\.seed: expected an integer, got str"):
        load_common(_write(tmp_path, '[run]\nseed = "x"\n'))


def test_bad_literal_lists_choices(tmp_path):
    with pytest.raises(ConfigError, match=r"run\.timing: expected one of \['realtime', 'lockstep'\]"):
        load_common(_write(tmp_path, '[run]\ntiming = "fast"\n'))


def test_unknown_table_is_error(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown table \[sumoo\]"):
        load_toml(_write(tmp_path, "[sumoo]\n"))


def test_missing_file_names_file(tmp_path):
    with pytest.raises(ConfigError, match="nope.toml: config file not found"):
        load_toml(tmp_path / "nope.toml")


def test_broken_toml_names_file(tmp_path):
    with pytest.raises(ConfigError, match="c.toml: not valid TOML"):
        load_toml(_write(tmp_path, "[run\n"))


@dataclass(frozen=True)
class _WithPath:
    file: Path = Path("x")
    gains: dict[str, float] | None = None


def test_paths_resolve_against_config_dir(tmp_path):
    data, base = load_toml(_write(tmp_path, '[demo]\nfile = "sub/a.xml"\n'))
    obj = section(data, "demo", _WithPath, base)
    assert obj.file == (tmp_path / "sub/a.xml").resolve()


def test_nested_dict_values_checked():
    with pytest.raises(ConfigError, match=r"gains\.k1: expected a number"):
        from_dict(_WithPath, {"gains": {"k1": "fast"}})
    assert from_dict(_WithPath, {"gains": {"k1": 15}}).gains == {"k1": 15.0}


def test_bool_is_not_a_number():
    with pytest.raises(ConfigError, match="duration_s: expected a number"):
        from_dict(RunConfig, {"duration_s": True})


def test_bundled_configs_load():
    root = Path(__file__).resolve().parents[1] / "configs"
    for p in sorted(root.glob("*.toml")):
        load_common(p)
