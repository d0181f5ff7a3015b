#!/usr/bin/env python3
"""A sumoco client written from protocol/SPEC.md alone: eclipse-zenoh + msgpack + stdlib.

It late-joins a run, fetches the static data with one query, follows the live SUMO steps
and physics states, and (optionally) drives an ego vehicle along a lane by publishing ego
poses at 20 Hz. It imports nothing of sumoco; use it as the template for a renderer.

    python client.py --connect tcp/127.0.0.1:7447 --run demo --duration 10 \
        [--ego-id ego --ego-lane E0_0 --ego-speed 8 --ego-stop-at 60]

Prints one JSON document with what it saw.
"""

from __future__ import annotations

import argparse
import array
import json
import math
import sys
import threading
import time

import msgpack
import zenoh

MAJOR = 1  # SPEC.md section 6: reject other major versions (this client reads 1.2)

# SPEC.md section 3: column types of the agent tables (little-endian).
STEP_COLUMNS = {"cls": "B", "vtype": "H", "x": "d", "y": "d", "angle": "f", "speed": "f",
                "accel": "f", "signals": "H", "la_dx": "f", "la_dy": "f", "length": "f",
                "width": "f", "lane": "i", "flags": "B"}
PHYSICS_COLUMNS = {"cls": "B", "mode": "B", "x": "d", "y": "d", "z": "f", "heading": "f",
                   "roll": "f", "pitch": "f", "speed": "f", "steer": "f", "drive": "f",
                   "brake": "f", "err_lon": "f", "err_lat": "f"}


def column(raw: bytes, code: str, n: int) -> list:
    a = array.array(code)
    a.frombytes(raw)
    if sys.byteorder != "little":
        a.byteswap()
    if len(a) != n:
        raise ValueError(f"column has {len(a)} values, expected {n}")
    return a.tolist()


def polylines(p: dict, n: int, anchors: tuple[list, list] | None = None) -> list[list[tuple[float, float]]]:
    """Polylines of SPEC.md section 3: static shapes (``xy64``) or paths (``dxy`` + anchors)."""
    off = column(p["off"], "I", n + 1)
    if anchors is not None:  # path ahead: float32 offsets from each agent's (x, y)
        xy = array.array("f")
        xy.frombytes(p["dxy"])
        ax, ay = anchors
        return [[(ax[i] + xy[2 * j], ay[i] + xy[2 * j + 1]) for j in range(off[i], off[i + 1])]
                for i in range(n)]
    xy = array.array("d")
    xy.frombytes(p["xy64"])
    if sys.byteorder != "little":
        xy.byteswap()
    return [[(xy[2 * j], xy[2 * j + 1]) for j in range(off[i], off[i + 1])] for i in range(n)]


def decode(payload: bytes) -> dict:
    doc = msgpack.unpackb(payload, raw=False)
    if not isinstance(doc, dict) or doc.get("v", [None])[0] != MAJOR:
        raise ValueError(f"unsupported message version {doc.get('v') if isinstance(doc, dict) else '?'}")
    kind = doc["kind"]
    if kind in ("step", "physics"):
        a = doc["agents"]
        cols = STEP_COLUMNS if kind == "step" else PHYSICS_COLUMNS
        for k, code in cols.items():
            a[k] = column(a[k], code, a["n"])
        if kind == "step":
            a["la_x"] = [x + d for x, d in zip(a["x"], a["la_dx"])]
            a["la_y"] = [y + d for y, d in zip(a["y"], a["la_dy"])]
            if "path" in a:
                a["path"] = polylines(a["path"], a["n"], (a["x"], a["y"]))
    elif kind == "static":
        ln = doc["lanes"]
        ln["width"] = column(ln["width"], "f", ln["n"])
        ln["length"] = column(ln["length"], "f", ln["n"])
        ln["shape"] = polylines(ln["shape"], ln["n"])
        jn = doc["junctions"]
        jn["shape"] = polylines(jn["shape"], jn["n"])
    return doc


class Client:
    def __init__(self, connect: list[str], root: str, run: str) -> None:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        conf.insert_json5("scouting/multicast/enabled", "false")
        # started before the SUMO side: retry at least every 0.5 s, not Zenoh's 4 s (SPEC 3.1.1)
        conf.insert_json5("connect/retry", '{"period_init_ms": 125, "period_max_ms": 500, "period_increase_factor": 2}')
        self.session = zenoh.open(conf)
        self.base = f"{root}/{run}"
        self.lock = threading.Lock()
        self.steps: list[tuple[int, int]] = []  # (epoch, step) of every step taken
        self.epoch: int | None = None  # the SUMO side's incarnation followed (SPEC 3.1.1)
        self.restarts = 0
        self.missed_at_join = 0
        self.steps_refused = 0
        self.last_step: dict | None = None
        self.physics: dict[str, dict] = {}
        self.physics_count = 0
        self.rejected = 0
        self.vtypes: list | None = None  # SPEC 3.1: the table travels only when it changes
        self.static_version = -1  # "sv" of the static data we hold
        self.step_version = -1  # "sv" of the newest step

    def fetch_static(self, timeout_s: float = 10.0) -> dict | None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for reply in self.session.get(f"{self.base}/sumo/static", timeout=2.0):
                if reply.ok is not None:
                    return decode(reply.ok.payload.to_bytes())
            time.sleep(0.1)
        return None

    def _on_step(self, sample) -> None:
        try:
            doc = decode(sample.payload.to_bytes())
        except Exception:
            self.rejected += 1
            return
        epoch, step = doc.get("epoch", 0), doc["step"]
        with self.lock:
            # SPEC 3.1.1: a newer epoch is a restarted SUMO side (its static data may differ);
            # an older one, or a step behind the last one, is a replay: refused
            if self.epoch is None:
                self.missed_at_join = step  # steps of this incarnation before we joined
            elif epoch > self.epoch:
                self.restarts += 1
                self.missed_at_join = step
                self.static_version = -1  # query the new incarnation's static data
                self.vtypes = None
            elif epoch < self.epoch or step <= self.steps[-1][1]:
                self.steps_refused += 1
                return
            self.epoch = epoch
            self.steps.append((epoch, step))
            self.last_step = doc
            self.step_version = doc.get("sv", 0)
            if "vtypes" in doc:
                self.vtypes = doc["vtypes"]
                self.static_version = max(self.static_version, self.step_version)

    def static_stale(self) -> bool:
        """SPEC 3.2: a step refers to static tables we do not hold: query them again."""
        with self.lock:
            return self.step_version >= 0 and self.step_version != self.static_version

    def _on_physics(self, sample) -> None:
        try:
            doc = decode(sample.payload.to_bytes())
        except Exception:
            self.rejected += 1
            return
        inst = str(sample.key_expr).split("/")[-2]
        with self.lock:
            self.physics[inst] = doc
            self.physics_count += 1

    def follow(self) -> None:
        self.subs = [
            self.session.declare_subscriber(f"{self.base}/sumo/step", self._on_step),
            self.session.declare_subscriber(f"{self.base}/physics/*/state", self._on_physics),
        ]

    def publish_ego(self, ego_id: str, x: float, y: float, angle: float, speed: float, vtype: str = "") -> None:
        doc = {"v": [1, 2], "kind": "ego", "id": ego_id, "x": x, "y": y, "angle": angle,
               "speed": speed, "t": time.time(), "vtype": vtype}
        self.session.put(f"{self.base}/ego/{ego_id}", msgpack.packb(doc, use_bin_type=True))


def point_along(shape: list[tuple[float, float]], s: float) -> tuple[float, float, float]:
    """Point and SUMO angle (deg clockwise from north) at distance s along a polyline."""
    for (x0, y0), (x1, y1) in zip(shape, shape[1:]):
        seg = math.hypot(x1 - x0, y1 - y0)
        if s <= seg or (x1, y1) == shape[-1]:
            f = min(s / seg, 1.0) if seg else 0.0
            angle = (90.0 - math.degrees(math.atan2(y1 - y0, x1 - x0))) % 360.0
            return x0 + f * (x1 - x0), y0 + f * (y1 - y0), angle
        s -= seg
    x, y = shape[-1]
    return x, y, 0.0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--connect", action="append", required=True)
    ap.add_argument("--root", default="sumoco")
    ap.add_argument("--run", default="default")
    ap.add_argument("--duration", type=float, default=10.0, help="wall seconds to follow the run")
    ap.add_argument("--ego-id", help="drive an ego vehicle with this id")
    ap.add_argument("--ego-lane", help="lane id to drive along (default: the longest car lane)")
    ap.add_argument("--ego-speed", type=float, default=8.0, help="[m/s]")
    ap.add_argument("--ego-start", type=float, default=5.0, help="start distance along the lane [m]")
    ap.add_argument("--ego-stop-at", type=float, help="stop at this distance along the lane [m]")
    ap.add_argument("--ego-pause", type=float, nargs=2, metavar=("FROM", "TO"),
                    help="stop publishing between these wall seconds")
    ap.add_argument("--ego-rate", type=float, default=20.0, help="ego poses per second [Hz]")
    args = ap.parse_args(argv)

    c = Client(args.connect, args.root, args.run)
    static = c.fetch_static()
    if static:
        c.static_version = static.get("sv", 0)
        c.vtypes = [list(p) for p in zip(static["vtypes"]["id"], static["vtypes"]["vclass"])]
    c.follow()
    requeried = 0
    last_query = 0.0
    report = {"static": None, "ego": None}
    if static:
        report["static"] = {"lanes": static["lanes"]["n"], "junctions": static["junctions"]["n"],
                            "tls": len(static["tls"]), "dt": static["dt"]}
    shape = None
    if args.ego_id and static:
        ln = static["lanes"]
        if args.ego_lane:
            shape = ln["shape"][ln["id"].index(args.ego_lane)]
        else:
            cars = [i for i in range(ln["n"]) if "passenger" in ln["allow"][i] and not ln["id"][i].startswith(":")]
            shape = ln["shape"][max(cars, key=lambda i: ln["length"][i])]
    t0 = time.monotonic()
    s = args.ego_start
    published = 0
    while time.monotonic() - t0 < args.duration:
        el = time.monotonic() - t0
        if c.static_stale() and el - last_query >= 1.0:  # at most once a second
            last_query = el
            fresh = c.fetch_static(timeout_s=2.0)
            if fresh:
                requeried += 1
                with c.lock:
                    c.static_version = fresh.get("sv", 0)
                    c.vtypes = [list(p) for p in zip(fresh["vtypes"]["id"], fresh["vtypes"]["vclass"])]
        if shape is not None and not (args.ego_pause and args.ego_pause[0] <= el < args.ego_pause[1]):
            stop = args.ego_stop_at is not None and s >= args.ego_stop_at
            v = 0.0 if stop else args.ego_speed
            x, y, ang = point_along(shape, s)
            c.publish_ego(args.ego_id, x, y, ang, v)
            published += 1
            s += v / args.ego_rate
        time.sleep(1.0 / args.ego_rate)
    with c.lock:
        last = c.last_step
        report.update({
            "steps_received": len(c.steps),
            "steps_increasing": all(b > a for a, b in zip(c.steps, c.steps[1:])),
            "last_step": last["step"] if last else None,
            "epoch": c.epoch,
            "sumo_restarts": c.restarts,
            "missed_at_join": c.missed_at_join,
            "steps_refused": c.steps_refused,
            "agents_last_step": last["agents"]["n"] if last else 0,
            "agent_ids_last_step": last["agents"]["id"] if last else [],
            "ego_in_step": bool(last and args.ego_id in last["agents"]["id"]),
            "physics_instances": sorted(c.physics),
            "physics_states_received": c.physics_count,
            "ego_in_physics": any(args.ego_id in d["agents"]["id"] for d in c.physics.values()) if args.ego_id else False,
            "rejected": c.rejected,
            "static_version": c.static_version,
            "static_requeried": requeried,
            "ego_poses_published": published,
        })
    c.session.close()
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
