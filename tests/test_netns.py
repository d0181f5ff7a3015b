"""Across machines: SUMO, a router and two physics shards in network namespaces of their own.

The test makes four namespaces joined by veth pairs through the router's namespace (the
addresses exist only inside them and go away with them), limits every link with ``tc
tbf``, runs the lockstep run there and on loopback, and compares what both runs did; a
second run cuts the SUMO host's link for 2 s in the middle and must end the same way, the
run still going when the link comes back.

Needs root, ``ip`` and ``tc`` with the tbf qdisc: without them the test is skipped with
the reason, except as root with ``CI=true``, where a missing piece is a failure (a CI
runner that is root is meant to run it). The measured numbers (wall time per run, steps,
the cut) are printed (``pytest -s``).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time

import pytest

from tests.harness import PAPER_CFG, ROOT, wait_until

pytestmark = pytest.mark.integration

SIM_S = 20.0  # [s] simulated
CUT_S = 2.0  # [s] the SUMO host's link is down this long
#: Every veth end: 100 Mbit/s through a token bucket (tc-tbf(8)).
TBF = ["tbf", "rate", "100mbit", "burst", "256kb", "latency", "50ms"]
_STATUS = re.compile(r"step (\d+) t=")


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=30)


def _tc(ns: str, dev: str, qdisc: list[str]) -> None:
    subprocess.run(["tc", "-n", ns, "qdisc", "add", "dev", dev, "root", *qdisc], check=True, capture_output=True,
                   timeout=30)


def _why(e: BaseException) -> str:
    err = getattr(e, "stderr", None)
    text = (err.decode(errors="replace").strip() if isinstance(err, bytes) else "") or str(e)
    return text.splitlines()[0] if text else repr(e)


def _unavailable() -> str | None:
    """Why namespaces with tbf-limited veth links cannot be made here, or None."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    for tool in ("ip", "tc"):
        if shutil.which(tool) is None:
            return f"`{tool}` (iproute2) is not installed"
    ns = f"sccheck{os.getpid()}"
    try:
        _ip("netns", "add", ns)
    except (OSError, subprocess.CalledProcessError, subprocess.TimeoutExpired) as e:
        return f"cannot make network namespaces here: {_why(e)}"
    try:
        try:
            _ip("-n", ns, "link", "add", "name", "sccheck0", "type", "veth", "peer", "name", "sccheck1")
            _ip("-n", ns, "link", "set", "sccheck0", "up")
        except (OSError, subprocess.CalledProcessError, subprocess.TimeoutExpired) as e:
            return f"cannot make veth pairs here: {_why(e)}"
        try:
            _tc(ns, "sccheck0", TBF)
        except (OSError, subprocess.CalledProcessError, subprocess.TimeoutExpired) as e:
            return f"the tbf qdisc is unavailable (kernel module sch_tbf?): {_why(e)}"
    finally:
        subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)
    return None


def _require_namespaces() -> None:
    why = _unavailable()
    if why is None:
        return
    if os.environ.get("CI", "").lower() in ("true", "1") and os.geteuid() == 0:
        pytest.fail(f"CI=true and root, yet: {why}")
    pytest.skip(why)


def _namespaces() -> set[str]:
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=30).stdout
    return {line.split()[0] for line in out.splitlines() if line.strip()}


class Net:
    """Namespaces r (router), s (SUMO), p0, p1 (shards); host ns-x links to r over 10.77.k.0/24.

    ``build`` makes them; ``close`` removes every one of them (the veth pairs live inside
    and go with them), also after a ``build`` that failed halfway: call both in one try.
    """

    def __init__(self, tbf: list[str] = TBF) -> None:
        self.tag = f"{os.getpid() % 100000}"
        self.ns = {k: f"sc{self.tag}{k}" for k in ("r", "s", "p0", "p1")}
        self.tbf = tbf
        self.addr: dict[str, tuple[str, str]] = {}  # host -> (router side, host side)
        self.dev: dict[str, str] = {}

    def build(self) -> None:
        for k in self.ns.values():
            _ip("netns", "add", k)
            _ip("-n", k, "link", "set", "lo", "up")
        for i, h in enumerate(("s", "p0", "p1"), start=1):
            a, b = f"sc{self.tag}r{i}", f"sc{self.tag}h{i}"
            _ip("link", "add", a, "netns", self.ns["r"], "type", "veth", "peer", "name", b, "netns", self.ns[h])
            ra, ha = f"10.77.{i}.1", f"10.77.{i}.2"
            _ip("-n", self.ns["r"], "addr", "add", f"{ra}/24", "dev", a)
            _ip("-n", self.ns[h], "addr", "add", f"{ha}/24", "dev", b)
            for ns, dev in ((self.ns["r"], a), (self.ns[h], b)):
                _ip("-n", ns, "link", "set", dev, "up")
                _tc(ns, dev, self.tbf)
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
status_period_s = 0.25
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
    prefix = ["ip", "netns", "exec", ns] if ns else []  # ip execs the command: same pid, signals reach it
    p = subprocess.Popen([*prefix, sys.executable, "-m", "sumoco.cli", *args], stdout=f, stderr=subprocess.STDOUT,
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


def _last_status_step(text: str) -> int:
    steps = _STATUS.findall(text)
    return int(steps[-1]) if steps else -1


def _run(tmp_path, net: Net | None, cut_s: float = 0.0) -> tuple[dict, dict]:
    """One lockstep run; returns (what it did, measurements: wall time, the cut)."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    cfg = _config(tmp_path)
    logs = tmp_path / "logs"
    if net is None:
        from runtime.transport import free_tcp_port

        port = free_tcp_port()
        router_listen = [f"tcp/127.0.0.1:{port}"]
        connect = {h: f"tcp/127.0.0.1:{port}" for h in ("s", "p0", "p1")}
        ns = {h: None for h in ("r", "s", "p0", "p1")}
    else:
        router_listen = [f"tcp/{ra}:7447" for ra, _ in net.addr.values()]
        connect = {h: f"tcp/{ra}:7447" for h, (ra, _) in net.addr.items()}
        ns = net.ns
    meas: dict = {}
    t0 = time.monotonic()
    router = _start("router", ["router", *[a for ep in router_listen for a in ("--listen", ep)]], logs, ns["r"])
    procs = [router]
    try:
        for i in (0, 1):
            procs.append(_start(f"physics{i}", ["physics", "--config", cfg, "--mode", "client", "--connect",
                                                connect[f"p{i}"], "--shard", f"{i}/2"], logs, ns[f"p{i}"]))
        sumo = _start("sumo", ["sumo", "--config", cfg, "--mode", "client", "--connect", connect["s"]], logs, ns["s"])
        procs.append(sumo)
        if cut_s:
            # cut the SUMO host off in the middle of the run (past step 10), then restore it
            wait_until(lambda: _last_status_step(sumo.logfile.read_text()) >= 10, 180, "SUMO stepping",
                       procs=procs)
            meas["steps_at_cut"] = _last_status_step(sumo.logfile.read_text())
            t_down = time.monotonic()
            net.set_link("s", False)
            try:
                time.sleep(cut_s)  # the outage itself, not a wait for a condition
            finally:
                net.set_link("s", True)
            t_up = time.monotonic()
            at_up = sumo.logfile.read_text()
            meas.update(cut_s=round(t_up - t_down, 3), sumo_running_at_link_up=sumo.poll() is None,
                        steps_at_link_up=_last_status_step(at_up), log_offset_at_link_up=len(at_up))
        wait_until(lambda: sumo.poll() is not None, 600, "the run to end", poll_s=0.1)
        meas["wall_s"] = round(time.monotonic() - t0, 2)
        assert sumo.returncode == 0, sumo.tail()
        for p in procs[1:3]:
            wait_until(lambda p=p: p.poll() is not None, 60, f"{p.name} to end")
            assert p.returncode == 0, p.tail()
        router.terminate()
        router.wait(15)
        assert router.returncode == 0, router.tail()
        if cut_s:
            after = sumo.logfile.read_text()[meas.pop("log_offset_at_link_up"):]
            later = [int(s) for s in _STATUS.findall(after)]
            meas["status_steps_after_link_up"] = later[:3] + (["..."] if len(later) > 5 else []) + later[3:][-2:]
            meas["max_status_step_after_link_up"] = max(later, default=-1)
        return _outcome(logs), meas
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(5)


def test_a_set_up_that_fails_halfway_removes_what_it_made():
    _require_namespaces()
    net = Net(tbf=["tbf", "rate", "no-such-rate"])  # tc refuses it after the namespaces and a veth exist
    try:
        with pytest.raises(subprocess.CalledProcessError):
            net.build()
        assert set(net.ns.values()) <= _namespaces()  # made before the failure ...
    finally:
        net.close()
    assert not set(net.ns.values()) & _namespaces()  # ... and gone


def test_lockstep_across_namespaces_matches_loopback_and_survives_a_link_cut(tmp_path):
    _require_namespaces()
    loop, m_loop = _run(tmp_path / "loopback", None)
    net = Net()
    try:
        net.build()
        across, m_across = _run(tmp_path / "netns", net)
        cut, m_cut = _run(tmp_path / "cut", net, cut_s=CUT_S)
    finally:
        net.close()
    assert not set(net.ns.values()) & _namespaces()
    print(json.dumps({"loopback": {**m_loop, **loop}, "netns": {**m_across, **across}, "cut": {**m_cut, **cut}}))
    final = int(loop["steps"])
    assert final == int(SIM_S / 0.1)
    assert across == loop
    assert cut == loop
    # the cut fell in the middle of the run: SUMO was still running and short of its last
    # step when the link came back, and stepped on after it (status lines past that step)
    assert m_cut["cut_s"] >= CUT_S
    assert m_cut["sumo_running_at_link_up"], m_cut
    assert 10 <= m_cut["steps_at_cut"] <= m_cut["steps_at_link_up"] < final, m_cut
    assert m_cut["max_status_step_after_link_up"] > m_cut["steps_at_link_up"], m_cut
