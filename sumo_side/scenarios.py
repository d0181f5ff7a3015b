"""SUMO scenarios bundled with sumoco and generated on demand.

- ``paper``: a small signalised 4-arm intersection modelled on section 4 of the
  Sumonity paper (reference car ``ref``: two lane changes, then a right turn at a
  traffic light), with cars, taxis, buses, bicycles and pedestrians around it. Its
  plain-XML sources and the netconvert output live in ``configs/scenarios/paper/``;
  :func:`build_paper_net` regenerates the net from the sources.
- ``grid``: :func:`make_grid_scenario` builds a ``netgenerate`` grid and
  ``randomTrips.py`` demand sized so that about ``vehicles`` vehicles are in the
  network at once (benchmarks: ~250 and ~2,500). Results are cached per parameter set.

SUMO binaries and tools come from the ``eclipse-sumo`` wheel (``sumo.SUMO_HOME``), so
netconvert/netgenerate/duarouter have the same version as libsumo; ``PATH`` is only a
fallback. Everything raises :class:`protocol.errors.ConfigError` naming the missing
file or the failing tool.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from protocol.errors import ConfigError

log = logging.getLogger(__name__)

#: Repository folder of the bundled scenarios (present in a source checkout / editable install).
SCENARIOS_DIR = Path(__file__).resolve().parent.parent / "configs" / "scenarios"
#: The paper scenario's folder.
PAPER_DIR = SCENARIOS_DIR / "paper"

#: netconvert options for the paper net besides the input/output files. Offsets are not
#: normalised so junction C stays at the origin, as written in paper.nod.xml; no
#: U-turns (nobody needs them and they would add links to the signal program).
PAPER_NETCONVERT_OPTIONS: tuple[str, ...] = (
    "--offset.disable-normalization", "true",
    "--no-turnarounds", "true",
)

# Wall-clock limits for external tools [s]; generous, they normally take < 5 s.
_TOOL_TIMEOUT_S = 120.0


# --------------------------------------------------------------------------- locating SUMO


def sumo_home() -> Path:
    """SUMO_HOME of the eclipse-sumo wheel (or the ``SUMO_HOME`` environment variable).

    The wheel wins over the environment so tools match the installed libsumo version.
    """
    candidates: list[tuple[str, Path]] = []
    try:
        import sumo  # eclipse-sumo wheel; importing it only sets env defaults

        candidates.append(("eclipse-sumo package (sumo.SUMO_HOME)", Path(sumo.SUMO_HOME)))
    except ImportError:
        pass
    env_home = os.environ.get("SUMO_HOME")
    if env_home:
        candidates.append(("environment variable SUMO_HOME", Path(env_home)))
    for _, home in candidates:
        if (home / "tools").is_dir():
            return home
    tried = ", ".join(f"{what}={home}" for what, home in candidates) or "nothing"
    raise ConfigError(
        f"SUMO_HOME not found (tried {tried}; need a folder with tools/): "
        "install the eclipse-sumo package (`pip install eclipse-sumo`) or set SUMO_HOME"
    )


def find_sumo_binary(name: str) -> str:
    """Path of a SUMO executable (``sumo``, ``sumo-gui``, ``netconvert``, ``netgenerate``...).

    Looks in ``<SUMO_HOME>/bin`` of the eclipse-sumo wheel first, then on ``PATH``.
    """
    searched: list[str] = []
    try:
        bindir = sumo_home() / "bin"
    except ConfigError:
        bindir = None
    if bindir is not None:
        for candidate in (bindir / name, bindir / f"{name}.exe"):
            searched.append(str(candidate))
            if candidate.is_file() and os.access(candidate, os.X_OK):
                return str(candidate)
    on_path = shutil.which(name)
    if on_path:
        return on_path
    raise ConfigError(
        f"SUMO executable {name!r} not found (looked at {', '.join(searched) or 'no SUMO_HOME'} "
        "and on PATH): install the eclipse-sumo package"
    )


def sumo_tool(relative: str) -> Path:
    """Path of a script under ``<SUMO_HOME>/tools`` (e.g. ``randomTrips.py``)."""
    path = sumo_home() / "tools" / relative
    if not path.is_file():
        raise ConfigError(f"SUMO tool {relative!r} not found at {path}")
    return path


def _tool_env() -> dict[str, str]:
    """Environment for SUMO tools: SUMO_HOME of the wheel so sumolib finds duarouter & co."""
    env = dict(os.environ)
    env["SUMO_HOME"] = str(sumo_home())
    return env


def _run_tool(tool: str, args: list[str], cwd: Path) -> None:
    """Run an external SUMO tool; any failure is a ConfigError naming the tool and its output."""
    log.debug("running %s %s (cwd %s)", tool, " ".join(args[1:]), cwd)
    try:
        proc = subprocess.run(
            args, cwd=cwd, env=_tool_env(), capture_output=True, text=True,
            timeout=_TOOL_TIMEOUT_S, check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ConfigError(f"{tool} could not run ({args[0]}): {exc}") from exc
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-15:]
        raise ConfigError(
            f"{tool} failed with exit code {proc.returncode} (cwd {cwd}):\n" + "\n".join(tail)
        )


# --------------------------------------------------------------------------- paper scenario


def paper_sumocfg(scenario_dir: Path = PAPER_DIR) -> Path:
    """The paper scenario's ``paper.sumocfg`` (checks that the files it needs exist)."""
    cfg = scenario_dir / "paper.sumocfg"
    for path in (cfg, scenario_dir / "paper.net.xml", scenario_dir / "paper.rou.xml",
                 scenario_dir / "paper.add.xml"):
        if not path.is_file():
            raise ConfigError(
                f"paper scenario file missing: {path} "
                "(regenerate the net with `python configs/scenarios/build_paper.py`)"
            )
    return cfg


def build_paper_net(src_dir: Path = PAPER_DIR, out_file: Path | None = None) -> Path:
    """Run netconvert on the paper scenario's plain-XML sources; returns the net file.

    ``out_file`` defaults to ``<src_dir>/paper.net.xml``. Input paths are passed
    relative to ``src_dir`` so the net's header does not record absolute paths.
    """
    sources = {
        "--node-files": "paper.nod.xml",
        "--edge-files": "paper.edg.xml",
        "--connection-files": "paper.con.xml",
        "--tllogic-files": "paper.tll.xml",
    }
    for name in sources.values():
        if not (src_dir / name).is_file():
            raise ConfigError(f"paper scenario source missing: {src_dir / name}")
    out_file = (out_file or src_dir / "paper.net.xml").resolve()
    args = [find_sumo_binary("netconvert")]
    for option, name in sources.items():
        args += [option, name]
    # relative when possible: the net's header records the option values
    args += [*PAPER_NETCONVERT_OPTIONS, "--output-file", os.path.relpath(out_file, src_dir)]
    _run_tool("netconvert", args, cwd=src_dir)
    return out_file


# --------------------------------------------------------------------------- grid scenario

#: Lane length per vehicle the automatic grid size aims at [m]: ~25 veh/km/lane, dense
#: urban traffic that still moves (jam density is ~133 veh/km/lane).
_LANE_M_PER_VEHICLE = 40.0
#: Mean travel speed assumed to predict when a vehicle leaves [m/s]. Measured means
#: (incl. waiting at signals): 4-10 m/s on 5x5/250, 2.5-8 m/s on 9x9/2,500. The high
#: end: a refill vehicle departs no later than its predecessor is likely to arrive, so
#: the count overshoots a little (+2% at 2,500 after 560 s) rather than dropping.
_ASSUMED_TRAVEL_SPEED = 7.0
#: Routes are made long enough to last the whole run at this mean speed [m/s], so
#: vehicles rarely leave and the count stays level without refills.
_ROUTE_SPEED_FOR_LENGTH = 8.0
#: Bump when the generated files change, so stale cache entries are not reused.
_GRID_GENERATOR_VERSION = 3
#: Insertion of every grid vehicle: random lane and free random position, from rest,
#: so thousands can enter at once anywhere in the grid instead of queueing at edge starts.
_GRID_DEPART_ATTRS = 'departLane="random" departPos="random_free" departSpeed="0"'


def grid_size_for(vehicles: int, edge_length: float = 200.0, lanes: int = 2) -> int:
    """Smallest n >= 5 for which an n x n grid has >= 40 m of lane per vehicle."""
    n = 5
    # A n x n grid has 2 n (n-1) streets, each two directed edges of `lanes` lanes.
    while 4 * n * (n - 1) * lanes * edge_length < vehicles * _LANE_M_PER_VEHICLE:
        n += 1
    return n


def _grid_dir_name(vehicles: int, seed: int, grid: int, edge_length: float, end: float,
                   intermediate: int) -> str:
    return (f"grid{grid}x{grid}_len{edge_length:g}_veh{vehicles}_seed{seed}"
            f"_end{end:g}_via{intermediate}_g{_GRID_GENERATOR_VERSION}")


def make_grid_scenario(
    out_dir: Path,
    vehicles: int,
    seed: int = 42,
    grid: int | None = None,
    *,
    edge_length: float = 200.0,
    end: float = 600.0,
    intermediate: int | None = None,
) -> Path:
    """Grid network + random traffic with about ``vehicles`` vehicles in the net at once.

    Returns the ``.sumocfg`` (step length 0.1 s, ``end`` [s]). Cached: a second call
    with the same parameters and ``out_dir`` returns the existing files without
    running any tool.

    - ``grid``: junctions per side; ``None`` picks :func:`grid_size_for` (5x5 up to
      ~400 vehicles, 9x9 for 2,500) so traffic keeps moving instead of gridlocking
      (2,500 vehicles on 5x5 fit but crawl at a mean 0.3-1 m/s).
    - Network: ``netgenerate --grid``, 2 lanes per direction, ``edge_length`` [m]
      between junctions, 13.89 m/s, traffic lights at every junction with 4 arms.
    - Demand: ``randomTrips.py`` + ``duarouter`` (seeded) make ``vehicles`` routes,
      each through ``intermediate`` random via edges; ``None`` picks enough that a
      route lasts until ``end`` at 8 m/s (several km), so vehicles rarely leave.
      All of them depart within the first second at free random positions, so the
      target count is in the network after a few seconds. Each vehicle is then a
      "slot": when it is expected to arrive (route length at 7 m/s) a new vehicle
      departs with another of the routes, until ``end``.
    """
    if vehicles < 1:
        raise ConfigError(f"make_grid_scenario: vehicles must be >= 1, got {vehicles}")
    if grid is None:
        grid = grid_size_for(vehicles, edge_length)
    if grid < 2:
        raise ConfigError(f"make_grid_scenario: grid must be >= 2 junctions per side, got {grid}")
    if edge_length <= 0.0:
        raise ConfigError(f"make_grid_scenario: edge_length must be > 0 m, got {edge_length}")
    if end <= 1.0:
        raise ConfigError(f"make_grid_scenario: end must be > 1 s, got {end}")
    if intermediate is None:
        # mean Manhattan distance between random points of a square of side a: 2a/3
        leg_m = 2.0 * (grid - 1) * edge_length / 3.0
        intermediate = max(0, math.ceil(end * _ROUTE_SPEED_FOR_LENGTH / leg_m) - 1)
    if intermediate < 0:
        raise ConfigError(f"make_grid_scenario: intermediate must be >= 0, got {intermediate}")
    out_dir = Path(out_dir)
    target = out_dir / _grid_dir_name(vehicles, seed, grid, edge_length, end, intermediate)
    cfg = target / "grid.sumocfg"
    if cfg.is_file():
        log.debug("grid scenario cached at %s", target)
        return cfg

    out_dir.mkdir(parents=True, exist_ok=True)
    # Build in a private folder and rename it into place: concurrent callers (test
    # workers, benchmark processes) never see a half-written scenario.
    work = Path(tempfile.mkdtemp(prefix=".build-", dir=out_dir))
    work.chmod(0o755)  # mkdtemp makes it private; the result is a normal shared folder
    try:
        _build_grid(work, vehicles, seed, grid, edge_length, end, intermediate)
        try:
            os.replace(work, target)
        except OSError:
            if not cfg.is_file():  # not a concurrent winner: a real failure
                raise
    finally:
        if work.exists():
            shutil.rmtree(work, ignore_errors=True)
    log.info("grid scenario %dx%d, %d vehicles, seed %d written to %s",
             grid, grid, vehicles, seed, target)
    return cfg


def _build_grid(work: Path, vehicles: int, seed: int, grid: int, edge_length: float,
                end: float, intermediate: int) -> None:
    net = work / "grid.net.xml"
    _run_tool("netgenerate", [
        find_sumo_binary("netgenerate"),
        "--grid", "--grid.number", str(grid), "--grid.length", f"{edge_length:g}",
        "--default.lanenumber", "2", "--default.speed", "13.89",
        "--tls.guess", "true",
        "--seed", str(seed),
        "--output-file", net.name,
    ], cwd=work)

    # `vehicles` departures spread over [0, 1) s (period 1/vehicles); start and end
    # edges weighted by length and lane count so vehicles spread evenly over lanes.
    _run_tool("randomTrips.py", [
        sys.executable, str(sumo_tool("randomTrips.py")), "-n", net.name,
        "-o", "burst.trips.xml", "-r", "burst.rou.xml",
        "--seed", str(seed), "--prefix", "b",
        # end just short of 1 s: randomTrips includes a departure at `end` itself
        "--begin", "0", "--end", f"{(vehicles - 0.5) / vehicles:.9g}",
        "--period", f"{1.0 / vehicles:.9g}",
        "--intermediate", str(intermediate),
        "--length", "--lanes",
        "--trip-attributes", _GRID_DEPART_ATTRS,
        "--validate",
    ], cwd=work)

    routes = _read_routes(work / "burst.rou.xml", net)
    if len(routes) < vehicles:
        log.warning("randomTrips.py made %d of %d routes", len(routes), vehicles)
    replacements = _write_replacements(work / "refill.rou.xml", routes, end)
    log.debug("grid: %d burst routes, %d refill vehicles until %g s",
              len(routes), replacements, end)

    (work / "grid.sumocfg").write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f"<!-- sumoco grid scenario: {grid}x{grid} junctions, {edge_length:g} m edges,\n"
        f"     ~{vehicles} concurrent vehicles, seed {seed}; generated by\n"
        "     sumo_side.scenarios.make_grid_scenario (netgenerate + randomTrips.py). -->\n"
        "<configuration>\n"
        "    <input>\n"
        '        <net-file value="grid.net.xml"/>\n'
        '        <route-files value="burst.rou.xml,refill.rou.xml"/>\n'
        "    </input>\n"
        "    <time>\n"
        '        <begin value="0"/>\n'
        f'        <end value="{end:g}"/>\n'
        '        <step-length value="0.1"/>\n'
        "    </time>\n"
        "    <random_number>\n"
        f'        <seed value="{seed}"/>\n'
        "    </random_number>\n"
        "    <report>\n"
        '        <no-step-log value="true"/>\n'
        '        <duration-log.disable value="true"/>\n'
        "    </report>\n"
        "</configuration>\n"
    )


def _read_routes(route_file: Path, net_file: Path) -> list[tuple[float, str, float]]:
    """(depart [s], edges, length [m]) of every vehicle in a duarouter output."""
    import sumolib  # imported lazily: only grid generation needs it

    try:
        net = sumolib.net.readNet(str(net_file))
        routes = []
        for vehicle in sumolib.xml.parse(str(route_file), "vehicle"):
            edges = vehicle.route[0].edges
            length = sum(net.getEdge(e).getLength() for e in edges.split())
            routes.append((float(vehicle.depart), edges, length))
    except Exception as exc:  # sumolib raises assorted errors on bad files
        raise ConfigError(f"could not read routes {route_file}: {exc}") from exc
    if not routes:
        raise ConfigError(f"randomTrips.py produced no routes in {route_file}")
    return routes


def _write_replacements(out_file: Path, routes: list[tuple[float, str, float]],
                        end: float) -> int:
    """Write the refill vehicles: one new vehicle per slot whenever its predecessor is
    expected to arrive. Returns how many were written."""
    import heapq

    # (expected arrival [s], slot); slot i's next vehicle takes the next route in turn.
    free = [(depart + length / _ASSUMED_TRAVEL_SPEED, i)
            for i, (depart, _, length) in enumerate(routes)]
    heapq.heapify(free)
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             "<!-- refill vehicles: each departs when a previous one is expected to leave -->",
             "<routes>"]
    count = 0
    while free and free[0][0] < end:
        t, slot = heapq.heappop(free)
        _, edges, length = routes[(slot + count + 1) % len(routes)]
        lines.append(f'    <vehicle id="r{count}" depart="{t:.2f}" {_GRID_DEPART_ATTRS}>'
                     f'<route edges="{edges}"/></vehicle>')
        heapq.heappush(free, (t + max(length / _ASSUMED_TRAVEL_SPEED, 1.0), slot))
        count += 1
    lines.append("</routes>")
    out_file.write_text("\n".join(lines) + "\n")
    return count
