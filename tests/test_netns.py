"""Across machines: SUMO, a router and two physics shards in network namespaces of their own.

The test makes four namespaces joined by veth pairs through the router's namespace (the
addresses exist only inside them and go away with them), limits every link with ``tc
tbf``, runs the lockstep run there and on loopback, and compares what both runs did; a
second run cuts the SUMO host's link for 2 s in the middle and must end the same way.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time

import pytest

from tests.harness import PAPER_CFG, ROOT, wait_until

pytestmark = pytest.mark.integration

SIM_S = 20.0  # [s] simulated


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=30)


def _can_make_namespaces() -> str | None:
    if os.geteuid() != 0:
        return "network namespaces need root"
    try:
        _ip("netns", "add", f"sccheck{os.getpid()}")
        _ip("netns", "del", f"sccheck{os.getpid()}")
    except (OSError, subprocess.CalledProcessError) as e:
        return f"cannot make network namespaces here: {e}"
    return None


class Net:
    """Namespaces r (router), s (SUMO), p0, p1 (shards); host ns-x links to r over 10.77.k.0/24."""

    def __init__(self) -> None:
        tag = f"{os.getpid() % 100000}"
        self.ns = {k: f"sc{tag}{k}" for k in ("r", "s", "p0", "p1")}
        self.addr: dict[str, tuple[str, str]] = {}  # host -> (router side, host side)
        self.dev: dict[str, str] = {}
        for k in self.ns.values():
            _ip("netns", "add", k)
            _ip("-n", k, "link", "set", "lo", "up")
        for i, h in enumerate(("s", "p0", "p1"), start=1):
            a, b = f"sc{tag}r{i}", f"sc{tag}h{i}"
            _ip("link", "add", a, "netns", self.ns["r"], "type", "veth", "peer", "name", b, "netns", self.ns[h])
            ra, ha = f"10.77.{i}.1", f"10.77.{i}.2"
            _ip("-n", self.ns["r"], "addr", "add", f"{ra}/24", "dev", a)
            _ip("-n", self.ns[h], "addr", "add", f"{ha}/24", "dev", b)
            for ns, dev in ((self.ns["r"], a), (self.ns[h], b)):
                _ip("-n", ns, "link", "set", dev, "up")
                subprocess.run(["tc", "-n", ns, "qdisc", "add", "dev", dev, "root", "tbf", "rate", "100mbit",
                                "burst", "256kb", "latency", "50ms"], check=True, capture_output=True, timeout=30)
            self.addr[h] = (ra, ha)
            self.dev[h] = b

    def set_link(self, host: str, up: bool) -> None:
        _ip("-n", self.ns[host], "link", "set", self.dev[host], "up" if up else "down")

    def close(self) -> None:
        for k in self.ns.values():
            subprocess.run(["ip", "netns", "del", k], capture_output=True, timeout=30)


def _config(tmp_path) -> str:
    p = tmp_path / "run.toml"
    p.write_text(f"""
[run]
id = "netns"
timing = "lockstep"
duration_s = {SIM_S}
lockstep_timeout_s = 30.0
[sumo]
sumocfg = "{PAPER_CFG}"
lockstep_instances = ["main.0of2", "main.1of2"]
[physics]
preset = "default"
shards = 1
shard_tile_m = 60.0
shard_halo_m = 10.0
""")
    return str(p)


def _start(name: str, args: list[str], logs, ns: str | None):
    logs.mkdir(parents=True, exist_ok=True)
    f = (logs / f"{name}.log").open("wb")
    prefix = ["ip", "netns", "exec", ns] if ns else []
    p = subprocess.Popen([*prefix, sys.executable, "-m", "sumoco.app.cli", *args], stdout=f, stderr=subprocess.STDOUT,
                         stdin=subprocess.DEVNULL, cwd=ROOT, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    p.name, p.logfile = name, logs / f"{name}.log"
    p.tail = lambda: p.logfile.read_text(errors="replace")[-3000:]
    return p


def _outcome(logs) -> dict:
    """What the run did, from the daemons' last lines: SUMO's totals, each shard's counters."""
    sumo = (logs / "sumo.log").read_text()
    m = re.search(r"SUMO side done: (.*)", sumo)
    assert m, sumo[-2000:]
    totals = dict(kv.split("=") for kv in m[1].split(", "))
    out = {k: totals[k] for k in ("steps", "max_agents", "departed", "arrived", "teleports", "persons_departed")}
    for i in (0, 1):
        lines = re.findall(r"agents (\d+) .*\| step (\d+) \| collisions (\d+) placements (\d+)",
                           (logs / f"physics{i}.log").read_text())
        assert lines, f"physics{i}: no status line"
        out[f"physics{i}"] = lines[-1]
    return out


def _run(tmp_path, net: Net | None, cut_s: float = 0.0) -> dict:
    tmp_path.mkdir(parents=True, exist_ok=True)
    cfg = _config(tmp_path)
    logs = tmp_path / "logs"
    if net is None:
        from sumoco.common.transport import free_tcp_port

        port = free_tcp_port()
        router_listen = [f"tcp/127.0.0.1:{port}"]
        connect = {h: f"tcp/127.0.0.1:{port}" for h in ("s", "p0", "p1")}
        ns = {h: None for h in ("r", "s", "p0", "p1")}
    else:
        router_listen = [f"tcp/{ra}:7447" for ra, _ in net.addr.values()]
        connect = {h: f"tcp/{ra}:7447" for h, (ra, _) in net.addr.items()}
        ns = net.ns
    procs = [_start("router", ["router", *[a for ep in router_listen for a in ("--listen", ep)]], logs, ns["r"])]
    try:
        for i in (0, 1):
            procs.append(_start(f"physics{i}", ["physics", "--config", cfg, "--mode", "client", "--connect",
                                                connect[f"p{i}"], "--shard", f"{i}/2"], logs, ns[f"p{i}"]))
        sumo = _start("sumo", ["sumo", "--config", cfg, "--mode", "client", "--connect", connect["s"]], logs, ns["s"])
        procs.append(sumo)
        if cut_s:
            # cut the SUMO host off in the middle of the run, then restore it
            wait_until(lambda: re.search(r"step (\d\d+) t=", sumo.logfile.read_text()), 180, "SUMO stepping",
                       procs=procs)
            net.set_link("s", False)
            time.sleep(cut_s)  # the cut itself: 2 s of no link
            net.set_link("s", True)
        wait_until(lambda: sumo.poll() is not None, 600, "the run to end")
        assert sumo.returncode == 0, sumo.logfile.read_text()[-3000:]
        for p in procs[1:3]:
            wait_until(lambda p=p: p.poll() is not None, 60, f"{p.name} to end")
            assert p.returncode == 0, p.logfile.read_text()[-3000:]
        return _outcome(logs)
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()


def test_lockstep_across_namespaces_matches_loopback_and_survives_a_link_cut(tmp_path):
    why = _can_make_namespaces()
    if why:
        pytest.skip(why)
    loop = _run(tmp_path / "loopback", None)
    net = Net()
    try:
        across = _run(tmp_path / "netns", net)
        cut = _run(tmp_path / "cut", net, cut_s=2.0)
    finally:
        net.close()
    assert int(loop["steps"]) == int(SIM_S / 0.1)
    assert across == loop
    assert cut == loop
