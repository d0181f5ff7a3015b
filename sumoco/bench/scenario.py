"""What the benchmarks run on: the bundled scenario, the cached grid scenarios, the run
configs (TOML) their daemons and demos start with, and the fill of a grid to its size.

One place for these, so every row that names "the grid scenario of N vehicles" or "a
lockstep demo of these presets" means the same files and the same settings.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

#: The source checkout the benchmarks run from (``configs/`` and ``runs/`` beside the package).
REPO_ROOT = Path(__file__).resolve().parents[2]
CONFIGS = REPO_ROOT / "configs"
#: The bundled intersection scenario of ``sumoco demo``.
PAPER_SUMOCFG = CONFIGS / "scenarios" / "paper" / "paper.sumocfg"
#: A grid counts as filled at this share of its target vehicles (SUMO's departures jitter).
FILL_SHARE = 0.97
FILL_MAX_STEPS = 6000  # SUMO steps to wait for the fill at most (600 s at 0.1 s steps)


def cache_dir() -> Path:
    """``runs/scenarios`` of the checkout (grid scenarios are built once and kept), or a
    temporary folder where the checkout is read-only."""
    d = REPO_ROOT / "runs" / "scenarios"
    try:
        d.mkdir(parents=True, exist_ok=True)
        return d
    except OSError:
        return Path(tempfile.gettempdir()) / "sumoco-scenarios"


def grid_scenario(vehicles: int, seed: int = 42) -> Path:
    """The ``.sumocfg`` of the grid scenario with about ``vehicles`` in the network at once
    (``sumo_side.scenarios.make_grid_scenario``, cached in ``cache_dir()``)."""
    from sumo_side.scenarios import make_grid_scenario

    return Path(make_grid_scenario(cache_dir(), vehicles, seed=seed))


def fill(sim, bridge, target: int, max_steps: int = FILL_MAX_STEPS):
    """Step ``sim`` (through ``bridge``, as the daemon does, so its caches fill too) until
    the network holds about ``target`` vehicles; returns the last step index and snapshot."""
    k, snap = 0, None
    for k in range(max_steps):
        sim.step()
        snap = sim.read()
        bridge.build(k, snap)
        if snap.n >= FILL_SHARE * target:
            break
    return k, snap


def toml_value(v) -> str:
    """One TOML value: strings quoted, booleans lower case, lists and inline tables nested."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (str, Path)):
        return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return repr(v)


def toml_text(tables: dict[str, dict]) -> str:
    """A TOML document of ``{table: {key: value}}``."""
    return "".join(f"[{name}]\n" + "".join(f"{k} = {toml_value(v)}\n" for k, v in keys.items())
                   for name, keys in tables.items())


def write_toml(path: Path, tables: dict[str, dict]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(toml_text(tables))
    return path


def demo_wall_s(duration_s: float) -> float:
    """Wall-clock bound of a bench's ``sumoco demo`` run of ``duration_s`` simulated seconds:
    20 times that, at least 10 minutes (a loaded host runs far below real time)."""
    return max(600.0, duration_s * 20)


def demo_config(folder: Path, run_id: str, presets: tuple[str, ...], duration_s: float,
                preset: str | None = None) -> Path:
    """``folder/bench.toml``: lockstep ``sumoco demo`` runs of ``presets`` side by side (no
    LAD sweep), bounded by ``demo_wall_s``; ``preset`` also sets ``[physics] preset``."""
    tables: dict[str, dict] = {"run": {"id": run_id, "timing": "lockstep", "lockstep_timeout_s": 60.0}}
    if preset is not None:
        tables["physics"] = {"preset": preset}
    tables["demo"] = {"presets": list(presets), "lad_sweep": False, "wall_limit_s": demo_wall_s(duration_s)}
    return write_toml(folder / "bench.toml", tables)


__all__ = ["CONFIGS", "PAPER_SUMOCFG", "REPO_ROOT", "cache_dir", "demo_config", "demo_wall_s", "fill",
           "grid_scenario", "toml_text", "toml_value", "write_toml"]
