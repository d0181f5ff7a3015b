"""Typed configuration: TOML files (read with ``tomllib``) into frozen dataclasses.

One TOML file configures a whole run; each part reads its own table:

- ``[run]`` and ``[zenoh]``: defined here, shared by every process;
- ``[sumo]``: ``sumo_side.config.SumoConfig``;
- ``[physics]`` and ``[control.*]``: ``physics_side.config``;
- ``[coupling]``: who owns each vehicle's motion (``CouplingConfig``, read by both sides);
- ``[demo]``: ``sumoco.orchestrate.demo``;
- ``[ros2]``: ``sumoco.ros2.config.Ros2Config``.

An unknown key or a value of the wrong type is a ``ConfigError`` that names the file,
the dotted key and what was expected; a missing key takes the dataclass default.
Paths in a file are resolved relative to that file, never to the working directory.
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

from protocol.codec import DecodeLimits
from protocol.errors import ConfigError
from runtime.zones import REGION_FIELDS

T = TypeVar("T")

#: Top-level tables a config file may have.
KNOWN_TABLES = ("run", "zenoh", "coupling", "sumo", "physics", "control", "demo", "viewer", "record", "bench", "ros2")


@dataclass(frozen=True)
class RunConfig:
    id: str = "default"  # run id, part of every key expression
    timing: Literal["realtime", "lockstep"] = "realtime"
    duration_s: float = 0.0  # [s] simulated time to run from the scenario's begin; 0 = until the scenario ends
    seed: int | None = None  # SUMO --seed (replaces the scenario's own, logged); none: the scenario's
    lockstep_timeout_s: float = 10.0  # [s] a silent peer in lockstep is an error after this
    max_agents: int = 200_000  # [agents] largest agent table a daemon decodes; bounds every decode (SPEC 5)

    def validate(self) -> None:
        if self.duration_s < 0:
            raise ConfigError(f"run.duration_s: expected >= 0 (0 = until the scenario ends), got {self.duration_s:g}")
        if self.lockstep_timeout_s <= 0:
            raise ConfigError(f"run.lockstep_timeout_s: expected > 0, got {self.lockstep_timeout_s:g}")
        if not 1 <= self.max_agents <= 200_000:
            raise ConfigError(f"run.max_agents: expected 1..200000, got {self.max_agents}")

    @property
    def decode_limits(self) -> DecodeLimits:
        """msgpack length limits of every decode, from ``max_agents``."""
        return DecodeLimits.for_agents(self.max_agents)


@dataclass(frozen=True)
class SecurityConfig:
    """``[zenoh.security]``: the secure profile (README, "Secure profile"); off by default."""

    certs: Path | None = None  # folder from `sumoco certs init`; set = TLS with mutual auth on every link
    acl: bool = True  # with certs: enforce the role access-control policy on everything received
    renderers: tuple[str, ...] = ("ego",)  # ego ids with a renderer certificate (CN renderer-<id>)
    users: Path | None = None  # `role:password` lines (`certs init --users`): user/password auth too
    routers: bool = False  # peers also reach each other through routers: the router CN may forward

    @property
    def enabled(self) -> bool:
        return self.certs is not None

    def validate(self) -> None:
        if self.users is not None and self.certs is None:
            raise ConfigError("zenoh.security.users: user/password needs zenoh.security.certs (TLS) too")
        for r in self.renderers:
            if not r or not all(c.isalnum() or c in "_-." for c in r):
                raise ConfigError(f"zenoh.security.renderers: expected ego ids (letters, digits, _ - .), got {r!r}")


@dataclass(frozen=True)
class ZenohConfig:
    root: str = "sumoco"  # key-expression root
    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()  # endpoints, e.g. "tcp/127.0.0.1:7447"
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False  # off: loopback and explicit endpoints only
    shared_memory: bool = True  # same-host payloads >= 3 KB via shared memory
    max_message_mb: float = 64.0  # [MiB] largest message a session takes in; Zenoh drops bigger ones
    security: SecurityConfig = field(default_factory=SecurityConfig)

    def validate(self) -> None:
        if not 1.0 <= self.max_message_mb <= 1024.0:
            raise ConfigError(f"zenoh.max_message_mb: expected 1..1024 MiB, got {self.max_message_mb}")


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, key: str, base: Path | None) -> Any:
    """Check ``value`` against annotation ``tp``; convert lists to tuples, paths to Path."""
    origin = typing.get_origin(tp)
    if origin is Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(f"{key}: expected one of {list(typing.get_args(tp))}, got {value!r}")
        return value
    if origin in (typing.Union, types.UnionType):
        errors = []
        for arm in typing.get_args(tp):
            if arm is type(None):
                if value is None:
                    return None
                continue
            try:
                return _coerce(value, arm, key, base)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if errors else f"{key}: unexpected {value!r}")
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list):
            raise ConfigError(f"{key}: expected a list, got {type(value).__name__} {value!r}")
        inner = args[0] if args else Any
        return tuple(_coerce(v, inner, f"{key}[{i}]", base) for i, v in enumerate(value))
    if origin is dict:
        kt, vt = typing.get_args(tp)
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a table, got {type(value).__name__}")
        return {k: _coerce(v, vt, f"{key}.{k}", base) for k, v in value.items()}
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a table, got {type(value).__name__}")
        return from_dict(tp, value, key, base)
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {type(value).__name__} {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {type(value).__name__} {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {type(value).__name__} {value!r}")
        return value
    if tp is Path:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a path string, got {type(value).__name__}")
        p = Path(value).expanduser()
        return p if p.is_absolute() or base is None else (base / p).resolve()
    raise ConfigError(f"{key}: unsupported type {_type_name(tp)}")


def from_dict(cls: type[T], data: dict[str, Any], where: str = "", base: Path | None = None) -> T:
    """Build dataclass ``cls`` from a TOML table; unknown keys and wrong types are errors."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    prefix = f"{where}." if where else ""
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(
            f"{prefix}{unknown[0]}: unknown key (expected one of: {', '.join(sorted(names))})"
        )
    kwargs = {k: _coerce(v, hints[k], prefix + k, base) for k, v in data.items()}
    obj = cls(**kwargs)
    check = getattr(obj, "validate", None)
    if check is not None:
        check()
    return obj


def load_toml(path: str | Path) -> tuple[dict[str, Any], Path]:
    """Read a TOML config file; returns its tables and the directory paths resolve against."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: config file not found")
    try:
        with p.open("rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: not valid TOML ({e})") from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{p}: not UTF-8 text (byte {e.start}); TOML files are UTF-8") from None
    except OSError as e:
        raise ConfigError(f"{p}: cannot be read ({e.strerror})") from None
    unknown = sorted(set(data) - set(KNOWN_TABLES))
    if unknown:
        raise ConfigError(
            f"{p}: unknown table [{unknown[0]}] (expected one of: {', '.join(KNOWN_TABLES)})"
        )
    return data, p.resolve().parent


def section(data: dict[str, Any], name: str, cls: type[T], base: Path | None, file: str = "") -> T:
    """Typed view of table ``name`` (defaults when absent); errors are prefixed with the file."""
    raw = data.get(name, {})
    try:
        if not isinstance(raw, dict):
            raise ConfigError(f"{name}: expected a table, got {type(raw).__name__}")
        return from_dict(cls, raw, name, base)
    except ConfigError as e:
        raise ConfigError(f"{file}: {e}" if file else str(e)) from None


def replace(obj: T, **changes: Any) -> T:
    """dataclasses.replace, for command-line overrides."""
    return dataclasses.replace(obj, **changes)  # type: ignore[type-var]


#: vClasses SUMO knows (``sumo_side.netfile``'s list); a typo in ``coupling.classes`` is an error.
VEHICLE_CLASSES = frozenset((
    "private emergency authority army vip passenger hov taxi bus coach delivery truck trailer tram "
    "rail_urban rail rail_electric rail_fast motorcycle moped bicycle evehicle ship container cable_car "
    "subway aircraft wheelchair scooter drone custom1 custom2").split())


@dataclass(frozen=True)
class CouplingConfig:
    """``[coupling]``: who owns each vehicle's motion (README, "Two-way coupling").

    ``"sumo"`` (shadow): SUMO moves the vehicle, physics drives a body after it (and carries
    it where SUMO's motion is beyond the vehicle). ``"physics"`` (two-way): SUMO gives the
    intent (route, lane, target speed); physics drives; the physical pose and speed are
    written back into SUMO before its next step. Pedestrians and egos are never
    physics-authoritative. The SUMO side decides per vehicle and flags it on the wire.
    """

    # owner of every vehicle not selected below; "zones": physics inside the level-of-detail
    # zones (``zone_radius_m`` around each ego, ``zone_regions``), SUMO outside
    authority: Literal["sumo", "physics", "zones"] = "sumo"
    classes: tuple[str, ...] = ()  # vClasses that are physics-authoritative (with authority = "sumo")
    types: tuple[str, ...] = ()  # vType ids that are physics-authoritative
    ids: tuple[str, ...] = ()  # vehicle id patterns (fnmatch: "truck*") that are physics-authoritative
    instance: str = ""  # the physics instance SUMO follows ("": the one running the `default` preset); others shadow
    feedback_steps: int = 1  # [steps] realtime: a state at most this many steps old is written back
    # what SUMO does when physics-authoritative vehicles touch (a crash in physics): "stay" (SUMO
    # warns, both stay where physics has them), "remove" them, or SUMO's own "teleport"
    collision: Literal["stay", "remove", "teleport"] = "stay"
    # The zones of ``authority = "zones"``: by default ``[physics] lod_radius_m`` and
    # ``lod_regions`` (``load_common`` copies them), so physics owns exactly what it simulates
    zone_radius_m: float = 0.0  # [m] around every ego vehicle
    zone_regions: tuple[tuple[float, ...], ...] = ()  # [[x, y, r], ...] [m] fixed regions

    def validate(self) -> None:
        bad = sorted(set(self.classes) - VEHICLE_CLASSES)
        if bad:
            raise ConfigError(f"coupling.classes: unknown vClass {bad[0]!r} (expected one of: "
                              f"{', '.join(sorted(VEHICLE_CLASSES))})")
        if self.instance and not all(c.isalnum() or c in "_-." for c in self.instance):
            raise ConfigError(f"coupling.instance: expected a physics instance name, got {self.instance!r}")
        if not 0 <= self.feedback_steps <= 10:
            raise ConfigError(f"coupling.feedback_steps: expected 0..10, got {self.feedback_steps}")
        if self.zone_radius_m < 0:
            raise ConfigError(f"coupling.zone_radius_m: expected >= 0 [m], got {self.zone_radius_m}")
        for i, r in enumerate(self.zone_regions):
            if len(r) != REGION_FIELDS or r[2] <= 0:
                raise ConfigError(f"coupling.zone_regions[{i}]: expected [x, y, radius] with radius > 0 [m], got {list(r)}")
        if self.authority == "zones" and self.zone_radius_m <= 0 and not self.zone_regions:
            raise ConfigError('coupling.authority = "zones": expected level-of-detail zones, got none '
                              "(set [physics] lod_radius_m > 0 or lod_regions)")

    def sumo_args(self, extra_args: tuple[str, ...]) -> tuple[str, ...]:
        """SUMO options two-way coupling needs (a crash is physics' fact: SUMO keeps the cars,
        ``collision``), unless the scenario's own ``extra_args`` set them."""
        if not self.two_way or any(a.lstrip("-").startswith("collision.action") for a in extra_args):
            return ()
        return ("--collision.action", {"stay": "warn", "remove": "remove", "teleport": "teleport"}[self.collision])

    def follows(self, instance: str, preset: str) -> bool:
        """True when physics instance ``instance`` (shards: ``<base>.<i>of<k>``) running control
        preset ``preset`` is the one SUMO follows."""
        if not self.two_way:
            return False
        if not self.instance:
            return preset == "default"
        base = instance.rsplit(".", 1)[0] if "of" in instance.rsplit(".", 1)[-1] else instance
        return self.instance in (instance, base)

    @property
    def two_way(self) -> bool:
        """True when any vehicle may be physics-authoritative."""
        return self.authority != "sumo" or bool(self.classes or self.types or self.ids)


@dataclass(frozen=True)
class CommonConfig:
    """The tables every process reads."""

    run: RunConfig = field(default_factory=RunConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    coupling: CouplingConfig = field(default_factory=CouplingConfig)


def load_common(path: str | Path) -> tuple[CommonConfig, dict[str, Any], Path]:
    data, base = load_toml(path)
    common = CommonConfig(
        run=section(data, "run", RunConfig, base, str(path)),
        zenoh=section(data, "zenoh", ZenohConfig, base, str(path)),
        coupling=_coupling_with_zones(data, base, str(path)),
    )
    return common, data, base


def _coupling_with_zones(data: dict[str, Any], base: Path, where: str) -> CouplingConfig:
    """``[coupling]`` with the level-of-detail zones of ``[physics]`` unless it sets its own
    (one definition of "where physics runs in full", read by both sides)."""
    raw = data.get("coupling") or {}
    phys = data.get("physics") or {}
    if isinstance(raw, dict) and isinstance(phys, dict):
        raw = dict(raw)
        if "zone_radius_m" not in raw and "lod_radius_m" in phys:
            raw["zone_radius_m"] = phys["lod_radius_m"]
        if "zone_regions" not in raw and "lod_regions" in phys:
            raw["zone_regions"] = phys["lod_regions"]
    return section({**data, "coupling": raw}, "coupling", CouplingConfig, base, where)


def apply_cli(common: CommonConfig, args: Any) -> CommonConfig:
    """Apply the shared command-line overrides (--run, --listen, --connect, --mode, ...)."""
    run, zen = common.run, common.zenoh
    if getattr(args, "run", None):
        run = replace(run, id=args.run)
    if getattr(args, "timing", None):
        run = replace(run, timing=args.timing)
    if getattr(args, "duration", None) is not None:
        run = replace(run, duration_s=float(args.duration))
        run.validate()  # --duration -5 is an error, not a run that never ends
    if getattr(args, "seed", None) is not None:
        run = replace(run, seed=int(args.seed))
    if getattr(args, "listen", None):
        zen = replace(zen, listen=tuple(args.listen))
    if getattr(args, "connect", None):
        zen = replace(zen, connect=tuple(args.connect))
    if getattr(args, "mode", None):
        zen = replace(zen, mode=args.mode)
    coupling = common.coupling
    if getattr(args, "authority", None):
        coupling = replace(coupling, authority=args.authority)
        coupling.validate()  # --authority zones without zones is an error, not a run without them
    return CommonConfig(run=run, zenoh=zen, coupling=coupling)
