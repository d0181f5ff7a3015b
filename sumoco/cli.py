"""``sumoco`` command: argument parsing only; every subcommand calls a typed ``main``.

Subcommands import their package lazily so ``sumoco sumo`` never loads MuJoCo and
``sumoco physics`` never loads libsumo.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import sys

from protocol.errors import ConfigError, SumocoError
from protocol.messages import SCHEMA_VERSION
from sumoco import __version__
from runtime.errors import ExitCode, MissingExtraError

#: Optional parts: the top-level module a command needs -> the extra that installs it.
_EXTRAS = {"libsumo": "sumo", "sumo": "sumo", "mujoco": "physics", "matplotlib": "report", "foxglove": "foxglove",
           "cryptography": "secure", "rclpy": "ros2", "rosbags": "ros2", "rosgraph_msgs": "ros2",
           "visualization_msgs": "ros2", "geometry_msgs": "ros2", "nav_msgs": "ros2", "std_msgs": "ros2",
           "builtin_interfaces": "ros2"}


def _env_list(name: str) -> list[str] | None:
    v = os.environ.get(name, "").strip()
    return [x.strip() for x in v.split(",") if x.strip()] or None


_CONFIG_HELP = "TOML config file (configs/*.toml) [env SUMOCO_CONFIG]"
_LISTEN_HELP = "zenoh endpoint to listen on (repeatable) [env SUMOCO_LISTEN, comma-separated]"
_CONNECT_HELP = "zenoh endpoint to connect to (repeatable) [env SUMOCO_CONNECT]"


def _add_logging(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="warnings and errors only")
    p.add_argument("--verbose", action="store_true", help="debug logging")


def _add_zenoh(p: argparse.ArgumentParser, *, config_help: str = _CONFIG_HELP, run: bool = True,
               listen_help: str = _LISTEN_HELP, connect_help: str = _CONNECT_HELP, connect_metavar: str | None = None,
               mode: bool = True) -> None:
    """Where a process meets the run on Zenoh: ``--config`` (its ``[zenoh]`` table), ``--run``,
    ``--listen``, ``--connect``, ``--mode``. Environment variables (SUMOCO_*) give the
    defaults, for containers; flags win (``parse_args`` reads the endpoint lists)."""
    p.add_argument("--config", default=os.environ.get("SUMOCO_CONFIG") or None, help=config_help)
    if run:
        p.add_argument("--run", default=os.environ.get("SUMOCO_RUN") or None,
                       help="run id (overrides [run].id) [env SUMOCO_RUN]")
    p.add_argument("--listen", action="append", default=None, help=listen_help)
    p.add_argument("--connect", action="append", default=None, metavar=connect_metavar, help=connect_help)
    if mode:
        p.add_argument("--mode", choices=["peer", "client", "router"], default=os.environ.get("SUMOCO_MODE") or None,
                       help="zenoh session mode [env SUMOCO_MODE]")


def _add_common(p: argparse.ArgumentParser) -> None:
    """Every daemon's flags: Zenoh, timing, duration, logging."""
    _add_zenoh(p)
    p.add_argument("--timing", choices=["realtime", "lockstep"], help="overrides [run].timing")
    p.add_argument("--duration", type=float, help="simulated seconds to run (overrides [run].duration_s)")
    _add_logging(p)


def _add_authority(p: argparse.ArgumentParser) -> None:
    p.add_argument("--authority", choices=["sumo", "physics", "zones"],
                   help="who owns every vehicle's motion: sumo (physics shadows SUMO), physics (two-way: "
                        "SUMO follows the physical states) or zones (physics inside the level-of-detail "
                        "zones, SUMO outside); overrides [coupling].authority")


def _add_scenario(p: argparse.ArgumentParser) -> None:
    p.add_argument("--begin", type=float, help="start SUMO at this time [s] instead of the scenario's begin; "
                                               "--duration counts from it")
    p.add_argument("--seed", type=int, help="SUMO random seed (default: the scenario's own)")


def _daemon_parser(sub, name: str, help_text: str) -> argparse.ArgumentParser:
    """A subcommand that runs daemons of a run: the common flags and ``--authority``."""
    p = sub.add_parser(name, help=help_text)
    _add_common(p)
    _add_authority(p)
    return p


def _sumo_parser(sub) -> None:
    p = _daemon_parser(sub, "sumo", "run the SUMO side daemon")
    p.add_argument("--sumocfg", help="run this .sumocfg instead of the config's scenario")
    _add_scenario(p)
    p.add_argument("--output-dir", help="folder for SUMO's own outputs and log (default: where the scenario "
                                        "puts them, usually its folder)")
    p.add_argument("--gui", action="store_true", help="use sumo-gui through TraCI (needs a display)")
    p.add_argument("--wait-for", action="append", default=None, metavar="INSTANCE",
                   help="lockstep: physics instance whose acks to wait for (repeatable; "
                        "overrides [sumo].lockstep_instances)")


def _physics_parser(sub) -> None:
    p = _daemon_parser(sub, "physics", "run the physics side daemon")
    p.add_argument("--preset", help="control preset for every agent type (paper|default|kinematic)")
    p.add_argument("--instance", help="physics instance name in the keys (default: [physics].instance or 'main')")
    p.add_argument("--shard", help="i/k: simulate only shard i of k (spatial tiles); the instance becomes "
                                   "<instance>.<i>of<k>")
    p.add_argument("--processes", help="N|auto: run the instance as N shard processes (--shard i/N each) under "
                                       "one supervisor that restarts a crashed one; auto = the cores here minus "
                                       "one for the SUMO side (overrides [physics].processes; default 1)")
    p.add_argument("--expect", help="agents expected at once, to size the pools up front: N passenger cars "
                                    "or type=N,type=N (overrides [physics].expect)")


def _demo_parser(sub) -> None:
    p = _daemon_parser(sub, "demo", "both daemons on loopback, bounded run, report")
    p.add_argument("--sumocfg", help="bring your own SUMO scenario")
    _add_scenario(p)
    p.add_argument("--out", help="output folder (default: runs/demo, or runs/<scenario name> with --sumocfg)")
    p.add_argument("--wall", type=float, help="wall-clock limit [s]")
    p.add_argument("--processes", help="N|auto: run each physics instance as N shard processes under a "
                                       "supervisor; auto shares the cores here minus one among the presets "
                                       "(overrides [physics].processes; default 1)")
    p.add_argument("--compare-authority", dest="compare_authority", action="store_true",
                   help="run the scenario twice, SUMO- and physics-authoritative (OUT/sumo-authority, "
                        "OUT/physics-authority), and compare them in OUT/modes.md")


def _bench_parser(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks, JSON on stdout")
    p.add_argument("what", choices=["sumo", "physics", "coupling", "e2e", "codec", "fidelity", "soak", "record",
                                    "gateway", "scenarios", "generated", "scale", "takeover", "viewer"])
    p.add_argument("--pack", help="scenarios, generated: folder of the scenario pack (default ../shared/scenarios "
                                  "beside the repository)")
    p.add_argument("--net", action="append", default=[],
                   help="generated: also run every default vClass and persons on this SUMO network file "
                        "(repeatable)")
    p.add_argument("--json", action="store_true", help="print JSON rows (the default)")
    p.add_argument("--config", help="soak: run config (default configs/soak.toml)")
    p.add_argument("--minutes", type=float, default=60.0, help="soak: wall-clock minutes to run")
    p.add_argument("--out", help="soak: output folder (default runs/soak); scenarios, generated: folder for the runs "
                                 "(default a temporary one)")
    p.add_argument("--duration", type=float, help="scenarios, generated: simulated seconds per scenario (default 60); "
                                                  "viewer: wall seconds measured per agent count (default 10)")
    p.add_argument("--agents", help="viewer: agent counts, comma-separated (default 500,1000,2500)")
    p.add_argument("--sample-s", dest="sample_s", type=float, help="soak: seconds between rows (default 60)")
    p.add_argument("--quick", action="store_true", help="smaller sizes, for smoke tests")
    p.add_argument("--runs", type=int, help="takeover: take-overs in a row (default 20)")
    p.add_argument("--authority", choices=["sumo", "physics"],
                   help="scenarios: who owns the vehicles' motion in every run (default: the config's, sumo)")
    _add_logging(p)


def _record_parser(sub) -> None:
    p = sub.add_parser("record", help="record every key of a run (and a Foxglove scene) to MCAP")
    _add_common(p)
    p.add_argument("--out", required=True, help="output file, e.g. runs/x/run.mcap")
    p.add_argument("--physics-hz", dest="physics_hz", type=float,
                   help="physics states kept per instance [Hz of simulated time], 0 = all (default 10)")
    p.add_argument("--scene-hz", dest="scene_hz", type=float,
                   help="Foxglove scene updates per key [Hz of simulated time], 0 = all (default 0.5)")
    p.add_argument("--no-scene", dest="no_scene", action="store_true", help="no Foxglove /scene channel")
    p.add_argument("--raw", action="store_true",
                   help="keep step and physics payloads as they came (byte-exact replay, ~5x larger); "
                        "default: compact, quantised (protocol/SPEC.md 11)")


def _report_parser(sub) -> None:
    p = sub.add_parser("report", help="rebuild summary.json, figures and report.md from a recording")
    p.add_argument("recording", help="run.mcap written by `sumoco record` or the demo")
    p.add_argument("--out", help="output folder (default: the recording's folder)")
    p.add_argument("--no-sweep", action="store_true", help="skip the LAD_min replay figure")
    _add_logging(p)


def _compare_parser(sub) -> None:
    p = sub.add_parser("compare", help="shadow against two-way coupling: modes.md from finished runs")
    p.add_argument("runs", nargs="+", help="run folders with summary.json (sumoco demo outputs)")
    p.add_argument("--out", help="output folder (default: the first run's parent)")
    _add_logging(p)


def _replay_parser(sub) -> None:
    p = sub.add_parser("replay", help="republish a recording on Zenoh as the daemons did (no SUMO/MuJoCo needed)")
    p.add_argument("recording", help="run.mcap written by `sumoco record` or the demo")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed factor (1 = as recorded)")
    p.add_argument("--loop", action="store_true", help="start over at the end until stopped")
    p.add_argument("--wait-subscriber", dest="wait_subscriber", type=float, default=0.0, metavar="S",
                   help="hold the first step until a subscriber to the steps appears, at most S seconds")
    # the recording names its run: no --run
    _add_zenoh(p, config_help="TOML config file for the [zenoh] table [env SUMOCO_CONFIG]", run=False)
    p.add_argument("--duration", type=float, help="replay only the first N seconds of the recording [s]")
    _add_logging(p)


def _gateway_parser(sub) -> None:
    p = sub.add_parser("gateway", help="a run's keys over one WebSocket (for engines without Zenoh)")
    _add_common(p)
    p.add_argument("--host", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, help="TCP port (default 8766, 0 = any free port)")
    p.add_argument("--allow-origin", dest="allow_origin", action="append", default=None, metavar="ORIGIN",
                   help="also accept browser pages from this Origin, e.g. http://myhost:8080 (repeatable)")
    p.add_argument("--allow-host", dest="allow_host", action="append", default=None, metavar="HOST",
                   help="also accept this Host header name (when serving on a non-loopback address)")
    p.add_argument("--token-file", dest="token_file",
                   help="write the per-run token here (mode 0600); the token is also in the printed URL "
                        "[env SUMOCO_GATEWAY_TOKEN fixes it]")


def _foxglove_parser(sub) -> None:
    p = sub.add_parser("foxglove", help="live 3D scene of a run for the Foxglove app (needs the foxglove extra)")
    _add_common(p)
    p.add_argument("--host", help="address of the Foxglove WebSocket server (default 127.0.0.1)")
    p.add_argument("--port", type=int, help="its TCP port (default 8767, 0 = any free port)")
    p.add_argument("--scene-hz", dest="scene_hz", type=float,
                   help="scene updates per key at most [Hz of simulated time], 0 = all (default 10)")


def _view_parser(sub) -> None:
    p = sub.add_parser("view", help="live 3D view of a run in the browser (three.js; a 2D page is linked)")
    _add_common(p)
    p.add_argument("--host", help="address to serve the page on (default 127.0.0.1)")
    p.add_argument("--port", type=int, help="TCP port of the page and its WebSocket (default 8765)")
    p.add_argument("--max-hz", dest="max_hz", type=float, help="frames per second to each browser at most")
    # `view --foxglove` is `sumoco foxglove`: the flag swaps the command that runs (args.cmd; argparse
    # copies the sub-parser's values over the parent's), so both share one code path and one exit path.
    p.add_argument("--foxglove", dest="cmd", action="store_const", const="foxglove", default="view",
                   help="serve the live 3D scene to the Foxglove app instead (foxglove-sdk WebSocket server, "
                        "the same as `sumoco foxglove`; needs the foxglove extra); --port then defaults to 8767")
    p.add_argument("--scene-hz", dest="scene_hz", type=float,
                   help="with --foxglove: scene updates per key at most [Hz of simulated time], 0 = all (default 10)")


def _ros2_parser(sub) -> None:
    p = sub.add_parser("ros2", help="the run on ROS 2 topics (RViz), egos driven from ROS 2 (needs the ros2 extra)")
    _add_zenoh(p)
    p.add_argument("--source", choices=["physics", "sumo"],
                   help="where poses come from: a physics instance (default) or SUMO's samples ([ros2].source)")
    p.add_argument("--instance", help="physics instance whose states to use (default: the first that publishes)")
    p.add_argument("--rate", dest="rate_hz", type=float,
                   help="agents, poses and odometry at most this often [Hz of simulated time], 0 = all (default 10)")
    p.add_argument("--odometry", action="append", default=None, metavar="ID",
                   help="also publish agent ID as nav_msgs/Odometry on <prefix>/odom/<ID> (repeatable)")
    p.add_argument("--ego", action="append", default=None, metavar="ID",
                   help="drive ego ID from ROS 2: geometry_msgs/PoseStamped on <prefix>/ego/<ID>/pose, "
                        "nav_msgs/Odometry on <prefix>/ego/<ID>/odom (repeatable)")
    p.add_argument("--domain-id", dest="domain_id", type=int, help="ROS_DOMAIN_ID (default: the environment's)")
    p.add_argument("--duration", type=float, help="stop after this many wall-clock seconds")
    _add_logging(p)


def _export_parser(sub) -> None:
    p = sub.add_parser("export", help="a recording in another format")
    esub = p.add_subparsers(dest="export_cmd", required=True)
    e = esub.add_parser("rosbag2", help="the ROS 2 topics of `sumoco ros2` from a recording, as a rosbag2 "
                                        "(needs the ros2 extra)")
    e.add_argument("recording", help="run.mcap written by `sumoco record` or the demo")
    e.add_argument("--out", required=True, help="rosbag2 folder to create (must not exist)")
    e.add_argument("--config", help="TOML config whose [ros2] table to use")
    e.add_argument("--source", choices=["physics", "sumo"], help="where poses come from (default physics)")
    e.add_argument("--instance", help="physics instance (default: the first in the recording)")
    e.add_argument("--rate", dest="rate_hz", type=float, help="frames per second of simulated time, 0 = all "
                                                               "(default 10)")
    e.add_argument("--odometry", action="append", default=None, metavar="ID", help="nav_msgs/Odometry of agent ID")
    e.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap", help="rosbag2 storage (default mcap)")
    _add_logging(e)


def _map_parser(sub) -> None:
    p = sub.add_parser("map", help="the road network as a file for renderers and game engines")
    msub = p.add_subparsers(dest="map_cmd", required=True)
    m = msub.add_parser("export", help="write a SUMO network as glTF 2.0 binary (GLB)")
    m.add_argument("net", help="SUMO network file (.net.xml or .net.xml.gz)")
    m.add_argument("--out", required=True, help="output file, e.g. map.glb")
    _add_logging(m)


def _certs_parser(sub) -> None:
    p = sub.add_parser("certs", help="certificates for the secure profile (configs/secure.toml)")
    p.add_argument("action", choices=["init"], help="init: a CA and one certificate per role")
    p.add_argument("dir", help="folder to write ca.pem and <role>.pem/.key into")
    p.add_argument("--renderer", action="append", metavar="EGO_ID",
                   help="ego id a renderer certificate may drive (repeatable; default: ego)")
    p.add_argument("--host", action="append", metavar="NAME_OR_IP",
                   help="extra DNS name or IP the certificates are valid for (localhost and 127.0.0.1 always)")
    p.add_argument("--days", type=int, default=365, help="validity [days]")
    p.add_argument("--users", action="store_true", help="also write users.txt (random passwords per role)")
    p.add_argument("--router", action="store_true",
                   help="also a router certificate (only for runs through `sumoco router`: it may forward anything)")
    p.add_argument("--force", action="store_true", help="replace certificates already in DIR")
    _add_logging(p)


def _router_parser(sub) -> None:
    p = sub.add_parser("router", help="a Zenoh router (Python session in router mode)")
    # a router is in router mode and belongs to no run: no --mode, no --run
    _add_zenoh(p, run=False, mode=False,
               config_help="run config whose [zenoh] table to use, with the secure profile's TLS and access "
                           "control (the router presents the 'router' certificate) [env SUMOCO_CONFIG]",
               listen_help="zenoh endpoint to listen on (repeatable; default tcp/127.0.0.1:7447) "
                           "[env SUMOCO_LISTEN, comma-separated]",
               connect_help="another router to connect to (repeatable): routers form a mesh "
                            "[env SUMOCO_CONNECT, comma-separated]", connect_metavar="ENDPOINT")
    _add_logging(p)


#: One parser builder per subcommand, in the order ``sumoco --help`` lists them.
_PARSERS = (_sumo_parser, _physics_parser, _demo_parser, _bench_parser, _record_parser, _report_parser,
            _compare_parser,
            _replay_parser, _gateway_parser, _foxglove_parser, _view_parser, _ros2_parser, _export_parser,
            _map_parser, _certs_parser, _router_parser)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="sumoco", description="SUMO <-> MuJoCo co-simulation over Zenoh")
    ap.add_argument("--version", action="version",
                    version=f"sumoco {__version__} (protocol {SCHEMA_VERSION[0]}.{SCHEMA_VERSION[1]})")
    sub = ap.add_subparsers(dest="cmd", required=True)
    for add in _PARSERS:
        add(sub)
    return ap


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line with the environment's defaults: ``--listen`` / ``--connect`` not
    given come from SUMOCO_LISTEN / SUMOCO_CONNECT (comma-separated)."""
    args = build_parser().parse_args(argv)
    if hasattr(args, "listen") and args.listen is None:
        args.listen = _env_list("SUMOCO_LISTEN")
    if hasattr(args, "connect") and args.connect is None:
        args.connect = _env_list("SUMOCO_CONNECT")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from runtime.logs import setup_logging

    setup_logging(getattr(args, "quiet", False), getattr(args, "verbose", False))
    try:
        return _dispatch(args)
    except ConfigError as e:
        print(f"sumoco {args.cmd}: configuration error: {e}", file=sys.stderr)
        return ExitCode.USAGE
    except MissingExtraError as e:
        print(f"sumoco {args.cmd}: {e}", file=sys.stderr)
        return ExitCode.USAGE
    except SumocoError as e:
        print(f"sumoco {args.cmd}: {e}", file=sys.stderr)
        return ExitCode.FAILURE
    except KeyboardInterrupt:
        return ExitCode.INTERRUPTED
    except OSError as e:
        if e.errno != errno.EADDRINUSE:
            raise
        # a port taken by another program: one line, not a traceback (--port picks another)
        print(f"sumoco {args.cmd}: cannot listen: {e.strerror} ({e}); choose another --port", file=sys.stderr)
        return ExitCode.USAGE


#: Subcommand -> "module:function" it runs; imported only when chosen.
_COMMANDS = {
    "sumo": "sumo_side.daemon:cli_main",
    "physics": "physics_side.processes:cli_main",
    "demo": "sumoco.orchestrate.demo:cli_main",
    "bench": "sumoco.bench.cli:cli_main",
    "record": "sumoco.recording.record:record_cli",
    "report": "sumoco.analysis.report:cli_main",
    "compare": "sumoco.analysis.modes:cli_main",
    "replay": "sumoco.recording.replay:cli_main",
    "gateway": "sumoco.viewing.gateway:cli_main",
    "foxglove": "sumoco.viewing.foxglove_live:cli_main",
    "view": "sumoco.viewing.viewer.server:cli_main",
    "map": "sumoco.orchestrate.mapexport:cli_main",
    "ros2": "sumoco.ros2.node:cli_main",
    "export": "sumoco.ros2.bag:cli_main",
    "router": "sumoco.orchestrate.router:cli_main",
    "certs": "sumoco.orchestrate.certs:cli_main",
}


def _dispatch(args: argparse.Namespace) -> int:
    """Import the subcommand's package (lazily: a bare install lacks the sides' extras)."""
    module, func = _COMMANDS[args.cmd].split(":")
    try:
        cli_main = getattr(importlib.import_module(module), func)
    except ModuleNotFoundError as e:
        extra = _EXTRAS.get((e.name or "").split(".")[0])
        if extra is None:
            raise
        raise MissingExtraError(args.cmd, extra, e.name) from e
    return int(cli_main(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
