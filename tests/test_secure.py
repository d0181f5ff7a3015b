"""The secure profile: certificates, TLS with mutual authentication, the role ACL.

Real pieces only: certificates made by ``sumoco certs init``, the real SUMO side and
physics side as OS processes on loopback TLS, and attacker sessions that hold a valid
certificate of a lesser role. Every attack asserts what the victim received (its counters,
its published state, what a viewer hears), next to a control that shows the same message
from the rightful role does arrive, so a test cannot pass because nothing arrives at all.
"""

from __future__ import annotations

import dataclasses
import json
import socket
import stat
import time

import msgpack
import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from protocol.codec import decode, encode
from protocol.errors import ConfigError
from protocol.keys import Keys
from protocol.messages import CameraPose, EgoPose, PhysicsState, StepAck
from sumoco.orchestrate.certs import init_certs
from sumoco.cli import main as cli
from runtime.config import SecurityConfig, ZenohConfig, load_common
from runtime.transport import access_control, open_session, zenoh_config
from synthetic.traffic import synthetic_step
from tests.harness import PAPER_CFG, ROOT, Daemon, Probe, endpoint, wait_until

FORGED_STEP = 900_000  # a step index the real run never reaches
HALF_OPEN = 200  # connections an attacker holds open without finishing a handshake


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    d = tmp_path_factory.mktemp("certs")
    init_certs(d, renderers=("ego", "ego2"), users=True, router=True)
    return d


def test_certs_init_makes_a_ca_and_one_certificate_per_role(tmp_path):
    assert cli(["certs", "init", str(tmp_path), "--renderer", "ego", "--renderer", "car7", "--quiet"]) == 0
    ca = x509.load_pem_x509_certificate((tmp_path / "ca.pem").read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert not (tmp_path / "router.key").exists()  # a router certificate is opt-in (--router)
    for role in ("sumo", "physics", "viewer", "gateway", "renderer-ego", "renderer-car7"):
        cert = x509.load_pem_x509_certificate((tmp_path / f"{role}.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == role
        assert cert.issuer == ca.subject
        # signed by this CA: verify the signature with the CA's public key
        ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        assert stat.S_IMODE((tmp_path / f"{role}.key").stat().st_mode) == 0o600
    assert stat.S_IMODE((tmp_path / "ca.key").stat().st_mode) == 0o600
    # a second init would silently replace the trust root: refused (exit 2) unless --force
    assert cli(["certs", "init", str(tmp_path), "--quiet"]) == 2
    assert cli(["certs", "init", str(tmp_path), "--force", "--quiet"]) == 0
    assert x509.load_pem_x509_certificate((tmp_path / "ca.pem").read_bytes()).serial_number != ca.serial_number


def test_certs_init_never_writes_through_links_or_over_keys_and_keys_stay_private(tmp_path):
    d = tmp_path / "c"
    assert cli(["certs", "init", str(d), "--quiet"]) == 0
    for f in d.glob("*.key"):
        f.chmod(0o644)  # someone loosened them
    assert cli(["certs", "init", str(d), "--force", "--quiet"]) == 0
    assert {stat.S_IMODE(f.stat().st_mode) for f in d.glob("*.key")} == {0o600}  # new keys are private again
    # a key path that is a symbolic link: refused, the link's target untouched (even with --force)
    target = tmp_path / "elsewhere.txt"
    target.write_text("precious")
    (d / "sumo.key").unlink()
    (d / "sumo.key").symlink_to(target)
    assert cli(["certs", "init", str(d), "--force", "--quiet"]) == 2
    assert target.read_text() == "precious"
    # keys without ca.pem: refused without --force, nothing overwritten
    e = tmp_path / "e"
    e.mkdir()
    (e / "sumo.key").write_text("old key")
    assert cli(["certs", "init", str(e), "--quiet"]) == 2
    assert (e / "sumo.key").read_text() == "old key" and not (e / "ca.pem").exists()
    # onto a file: one line and exit 2, not a traceback
    f = tmp_path / "a-file"
    f.write_text("x")
    assert cli(["certs", "init", str(f), "--quiet"]) == 2
    assert cli(["certs", "init", str(tmp_path / "r"), "--router", "--quiet"]) == 0
    assert (tmp_path / "r" / "router.pem").is_file()


def test_router_rights_only_where_routers_are_part_of_the_run_and_no_plain_links():
    sec = SecurityConfig(certs=ROOT, renderers=("ego",))
    peer = {p["id"]: set(p["rules"]) for p in access_control("sumoco", sec, routed=False)["policies"]}
    assert peer["router"] == {"receive", "read"}  # a peer-to-peer run: a router certificate may only read
    routed = {p["id"]: set(p["rules"]) for p in access_control("sumoco", sec, routed=True)["policies"]}
    assert "router-forward" in routed["router"]
    for ep in ("udp/127.0.0.1:7447", "unixsock-stream//tmp/z.sock"):
        with pytest.raises(ConfigError, match="plain link outside TLS"):
            zenoh_config(ZenohConfig(listen=(ep,), security=sec), role="sumo")


def test_secure_toml_parses_and_errors_name_the_problem(tmp_path, certs):
    common, _, _ = load_common(ROOT / "configs" / "secure.toml")
    sec = common.zenoh.security
    assert sec.enabled and sec.acl and sec.certs == (ROOT / "runs" / "certs").resolve()
    bad = tmp_path / "bad.toml"
    bad.write_text('[zenoh.security]\nusers = "u.txt"\n')
    with pytest.raises(ConfigError, match="users: user/password needs zenoh.security.certs"):
        load_common(bad)
    bad.write_text('[zenoh.security]\ncerts = "c"\nrenderer = ["x"]\n')
    with pytest.raises(ConfigError, match=r"zenoh.security.renderer: unknown key"):
        load_common(bad)
    with pytest.raises(ConfigError, match=r"mallory\.pem not found .*sumoco certs init"):
        zenoh_config(ZenohConfig(security=SecurityConfig(certs=certs)), role="mallory")


def test_policy_denies_unless_allowed_and_grants_each_renderer_its_own_key_only():
    acl = access_control("sumoco", SecurityConfig(certs=ROOT, renderers=("a", "b")))
    assert acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    grants = {p["id"]: set(p["rules"]) for p in acl["policies"]}
    assert grants["viewer"] == {"receive", "read", "camera-viewer", "camera-token-viewer"}
    assert grants["renderer-a"] == {"receive", "read", "ego-a", "camera-renderer-a", "camera-token-renderer-a"}
    assert grants["gateway"] == {"receive", "read", "gateway-ego", "camera-gateway", "camera-token-gateway"}
    assert rules["ego-a"]["key_exprs"] == ["sumoco/*/ego/a"] and rules["ego-a"]["flows"] == ["ingress"]
    # a router forwards what its clients may send under its own CN: it alone may send anything
    assert grants["router"] == {"receive", "read", "router-forward"}
    assert rules["router-forward"]["key_exprs"] == ["sumoco/**"] and rules["router-forward"]["flows"] == ["ingress"]
    assert [p["id"] for p in acl["policies"] if "router-forward" in p["rules"]] == ["router"]
    put_keys = {k for r in rules.values() if "put" in r["messages"] and r["flows"] == ["ingress"]
                and r["id"] != "router-forward" for k in r["key_exprs"]}
    assert put_keys == {"sumoco/*/sumo/step", "sumoco/*/physics/*/state", "sumoco/*/physics/*/ack",
                        "sumoco/*/physics/*/feedback",
                        "sumoco/*/ego/a", "sumoco/*/ego/b", "sumoco/*/ego/*", "sumoco/*/viewer/viewer/*/camera",
                        "sumoco/*/viewer/gateway/*/camera",
                        "sumoco/*/viewer/renderer-a/*/camera", "sumoco/*/viewer/renderer-b/*/camera"}
    assert rules["camera-token-renderer-a"]["key_exprs"] == ["sumoco/*/viewer/renderer-a/*/alive"]


# ------------------------------------------------------------------ real sessions, no daemons


def _bare_session(connect: str, ca: str | None = None, cert: str | None = None, key: str | None = None):
    """A Zenoh session configured by hand (not through sumoco): what an outsider would open."""
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([connect]))
    c.insert_json5("scouting/multicast/enabled", "false")
    for k, v in (("root_ca_certificate", ca), ("connect_certificate", cert), ("connect_private_key", key)):
        if v:
            c.insert_json5(f"transport/link/tls/{k}", json.dumps(v))
    return zenoh.open(c)


def test_a_peer_without_a_valid_certificate_cannot_connect(tmp_path, certs):
    sec = SecurityConfig(certs=certs, renderers=("ego", "ego2"))
    ep = endpoint()
    victim = open_session(ZenohConfig(listen=(ep,), security=sec), role="sumo")
    got = []
    sub = victim.declare_subscriber("sumoco/**", lambda s: got.append(str(s.key_expr)))
    other = tmp_path / "other"
    init_certs(other)  # a valid-looking certificate from a CA the victim does not trust
    tls_ep = "tls/" + ep[4:]
    outsiders = {
        "plain tcp": _bare_session(ep),
        "tls, no certificate": _bare_session(tls_ep, ca=str(certs / "ca.pem")),
        "tls, foreign CA": _bare_session(tls_ep, ca=str(certs / "ca.pem"), cert=str(other / "sumo.pem"),
                                         key=str(other / "sumo.key")),
    }
    insider = open_session(ZenohConfig(connect=(ep,), security=sec), role="sumo")
    try:
        wait_until(lambda: list(insider.info.peers_zid()), 10, "the rightful sumo peer to connect")
        time.sleep(0.5)  # outsiders get the same time to try
        for name, s in outsiders.items():
            assert list(s.info.peers_zid()) == [], f"{name}: a link came up"
            s.put("sumoco/x/sumo/step", name.encode())
        insider.put("sumoco/x/sumo/step", b"insider")
        wait_until(lambda: "sumoco/x/sumo/step" in got, 10, "the insider's step at the victim")
        time.sleep(0.3)
        assert got == ["sumoco/x/sumo/step"], got
        assert {str(z) for z in victim.info.peers_zid()} == {str(insider.info.zid())}
    finally:
        sub.undeclare()
        for s in (*outsiders.values(), insider, victim):
            s.close()


def test_user_password_is_checked_on_top_of_the_certificate(tmp_path, certs):
    sec = SecurityConfig(certs=certs, renderers=("ego", "ego2"), users=certs / "users.txt")
    ep = endpoint()
    victim = open_session(ZenohConfig(listen=(ep,), security=sec), role="sumo")
    wrong = tmp_path / "users.txt"
    wrong.write_text("".join(f"{line.split(':')[0]}:not-the-password\n"
                             for line in (certs / "users.txt").read_text().splitlines()))
    intruder = open_session(ZenohConfig(connect=(ep,), security=SecurityConfig(certs=certs, users=wrong)),
                            role="sumo")
    rightful = open_session(ZenohConfig(connect=(ep,), security=sec), role="sumo")
    try:
        wait_until(lambda: list(rightful.info.peers_zid()), 10, "the peer with the right password")
        time.sleep(0.5)
        assert list(intruder.info.peers_zid()) == []
        assert {str(z) for z in victim.info.peers_zid()} == {str(rightful.info.zid())}
    finally:
        for s in (intruder, rightful, victim):
            s.close()


def test_rust_log_debug_does_not_print_the_password(certs):
    """Zenoh's debug log prints its configuration: with user/password authentication the
    process's password would be in the log. The process warns and keeps Zenoh's log off."""
    import os
    import subprocess
    import sys

    code = ("from pathlib import Path; from runtime.config import SecurityConfig, ZenohConfig; "
            "from runtime.transport import open_session; "
            f"s = open_session(ZenohConfig(listen=('{endpoint()}',), security=SecurityConfig(certs=Path(r'{certs}'), "
            f"users=Path(r'{certs / 'users.txt'}'))), role='sumo'); s.close()")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT,
                       env=dict(os.environ, RUST_LOG="debug"))
    assert r.returncode == 0, r.stderr
    password = next(line.split(":", 1)[1] for line in (certs / "users.txt").read_text().splitlines()
                    if line.startswith("sumo:"))
    assert password not in r.stdout + r.stderr
    assert "would print this process's password" in r.stderr


def test_a_valid_peer_joins_within_2_s_while_200_half_open_connections_are_held(certs):
    """Connections that open TCP and never start TLS must not keep a real peer out."""
    sec = SecurityConfig(certs=certs, renderers=("ego", "ego2"))
    ep = endpoint()
    victim = open_session(ZenohConfig(listen=(ep,), security=sec), role="sumo")
    host, port = ep[4:].rsplit(":", 1)
    held = []
    insider = None
    try:
        for _ in range(HALF_OPEN):
            c = socket.create_connection((host, int(port)), timeout=5)
            c.sendall(b"\x16\x03\x01\x02\x00")  # a TLS record header promising a ClientHello that never comes
            held.append(c)
        time.sleep(0.2)  # every one of them is accepted and waiting for its handshake
        t0 = time.monotonic()
        insider = open_session(ZenohConfig(connect=(ep,), security=sec), role="physics")
        wait_until(lambda: list(insider.info.peers_zid()), 10, "the rightful peer to connect")
        joined_s = time.monotonic() - t0
    finally:
        for c in held:
            c.close()
        for x in (insider, victim):
            if x is not None:
                x.close()
    assert joined_s < 2.0, f"a valid peer took {joined_s:.2f} s to join beside 200 half-open connections"


def test_samples_carry_the_publishers_timestamp():
    ep = endpoint()
    a = open_session(ZenohConfig(listen=(ep,)))
    b = open_session(ZenohConfig(connect=(ep,)))
    got = []
    try:
        sub = a.declare_subscriber("sumoco/ts/**", lambda smp: got.append(smp.timestamp))
        wait_until(lambda: list(b.info.peers_zid()), 10, "the link")
        t0 = time.time()
        wait_until(lambda: (b.put("sumoco/ts/x", b"1"), got)[1], 10, "a sample", poll_s=0.1)
        sub.undeclare()
    finally:
        b.close()
        a.close()
    assert got[0] is not None
    assert abs(got[0].get_time().timestamp() - t0) < 5.0  # the publisher's clock, wall time


# ------------------------------------------------------------------ attacks on the real daemons


def _config(tmp_path, certs) -> str:
    # the bundled scenario runs out of traffic after ~1,400 steps, which lockstep with LOD
    # (nothing in MuJoCo without a camera) finishes in seconds: a flow keeps the run going
    # for every test of this module
    (tmp_path / "long.rou.xml").write_text(
        '<routes><flow id="keep" type="car" route="r_ew" begin="0" end="3600" period="20" '
        'departLane="best"/></routes>\n')
    routes = f"{PAPER_CFG.parent / 'paper.rou.xml'},{tmp_path / 'long.rou.xml'}"
    p = tmp_path / "secure.toml"
    p.write_text(f"""
[run]
id = "sec"
timing = "lockstep"
duration_s = 0.0
lockstep_timeout_s = 20.0
[zenoh.security]
certs = "{certs}"
renderers = ["ego", "ego2"]
[sumo]
sumocfg = "{PAPER_CFG}"
extra_args = ["--route-files", "{routes}", "--end", "3600"]
[physics]
preset = "kinematic"
lod_radius_m = 30.0
""")
    return str(p)


class SecureRun:
    def __init__(self, tmp_path, certs):
        self.certs = certs
        self.sec = SecurityConfig(certs=certs, renderers=("ego", "ego2"))
        self.keys = Keys("sumoco", "sec")
        cfg = _config(tmp_path, certs)
        self.sumo_ep = endpoint()
        self.sumo = Daemon("sumo", ["sumo", "--config", cfg, "--listen", self.sumo_ep, "--quiet"], tmp_path)
        self.physics = Daemon("physics", ["physics", "--config", cfg, "--listen", endpoint(),
                                          "--connect", self.sumo_ep, "--quiet"], tmp_path)
        self.viewer = Probe(self.keys, [self.sumo_ep], security=self.sec, role="viewer")
        wait_until(lambda: self.viewer.last_step() is not None and self.viewer.last_physics() is not None,
                   60, "steps and physics states at a viewer-role probe", procs=[self.sumo, self.physics])

    def client(self, role: str) -> zenoh.Session:
        s = open_session(ZenohConfig(connect=(self.sumo_ep,), security=self.sec), role=role)
        wait_until(lambda: list(s.info.peers_zid()), 10, f"the {role} client to connect")
        return s

    def linked_client(self, role: str) -> zenoh.Session:
        """A client of ``role`` with a link of its own to the viewer probe (peers find each
        other by gossip): what it sends reaches the probe directly, not through a daemon."""
        s = self.client(role)
        probe = str(self.viewer.session.info.zid())
        wait_until(lambda: probe in {str(z) for z in s.info.peers_zid()}, 10, f"the {role} client's link to the viewer")
        return s

    def status(self) -> dict:
        for r in self.viewer.session.get(self.keys.sumo_status, timeout=3.0):
            if r.ok is not None:
                return msgpack.unpackb(r.ok.payload.to_bytes(), raw=False)["counters"]
        return {}

    def close(self):
        codes = {d.name: d.terminate(10) for d in (self.sumo, self.physics)}
        self.viewer.close()
        return codes


@pytest.fixture(scope="module")
def run(tmp_path_factory, certs):
    r = SecureRun(tmp_path_factory.mktemp("secure-run"), certs)
    yield r
    codes = r.close()
    assert codes == {"sumo": 0, "physics": 0}, codes


def test_viewer_role_subscribes_to_steps_states_and_static_data(run):
    static = run.viewer.static()
    assert len(static.lanes.ids) > 10
    n0 = len(run.viewer.steps)
    wait_until(lambda: len(run.viewer.steps) > n0 + 20, 20, "live steps at the viewer", procs=[run.sumo])
    assert run.viewer.last_physics().agents.n > 0


def _forge_steps(run, role: str) -> None:
    """A ``role`` client puts 20 forged steps; none reaches physics or the viewer (never
    delivered, so not even counted as rejected)."""
    attacker = run.client(role)
    try:
        for i in range(20):
            attacker.put(run.keys.step, encode(synthetic_step(5, step=FORGED_STEP + i)))
        s0 = run.viewer.last_physics().tick
        wait_until(lambda: run.viewer.last_physics().tick > s0 + 100, 20, "physics to keep ticking",
                   procs=[run.physics])
    finally:
        attacker.close()
    with run.viewer.lock:
        states = [st for lst in run.viewer.physics.values() for st in lst]
        steps = list(run.viewer.steps)
    assert max(st.sumo_step for st in states) < FORGED_STEP
    assert max(m.step for m in steps) < FORGED_STEP
    assert states[-1].counters.get("rejected", 0) == 0  # not even seen and rejected: never delivered


def test_renderer_cannot_publish_a_step_that_physics_would_follow(run):
    _forge_steps(run, "renderer-ego")


def test_router_certificate_cannot_forge_a_step_in_a_peer_run(run):
    _forge_steps(run, "router")


def test_replayed_steps_and_absurd_jumps_are_refused_even_from_the_sumo_role(run):
    """The red team's replay: a step captured seconds earlier, put again with the ``sumo``
    certificate five times (accepted before protocol 1.4: "went back ... resynchronising"),
    and one with a huge index. Physics refuses and counts them (SPEC 3.1.1) and never
    follows them; the run goes on."""
    captured: list[bytes] = []
    sub = run.viewer.session.declare_subscriber(run.keys.step, lambda smp: captured.append(smp.payload.to_bytes()))
    try:
        wait_until(lambda: len(captured) >= 2, 20, "a step to capture", procs=[run.sumo])
        old = captured[0]
        old_step, epoch = decode(old).step, decode(old).epoch
        assert epoch > 0
        wait_until(lambda: run.viewer.last_physics().sumo_step > old_step + 20, 30, "the run to move on",
                   procs=[run.physics])
    finally:
        sub.undeclare()
    before = run.viewer.last_physics().counters
    attacker = run.client("sumo")
    try:
        jump = encode(dataclasses.replace(synthetic_step(5, step=2**40), run="sec", epoch=epoch))
        sent = {"at": 0.0}

        def put_again():  # (a physics side busy growing its pools may drop queued steps: put them again)
            if time.monotonic() - sent["at"] > 2.0:
                for _ in range(5):
                    attacker.put(run.keys.step, old)
                attacker.put(run.keys.step, jump)
                sent["at"] = time.monotonic()
            return False

        wait_until(lambda: put_again() or (c := run.viewer.last_physics().counters)["replayed_steps"] >= before["replayed_steps"] + 5
                   and c["step_jumps"] >= before["step_jumps"] + 1, 20, "the replays and the jump counted",
                   procs=[run.physics])
    finally:
        attacker.close()
    s0 = run.viewer.last_physics().tick
    wait_until(lambda: run.viewer.last_physics().tick > s0 + 50, 20, "physics to keep ticking", procs=[run.physics])
    with run.viewer.lock:
        states = [st for lst in run.viewer.physics.values() for st in lst]
    seq = [st.sumo_step for st in states]
    assert all(b >= a for a, b in zip(seq, seq[1:])), "physics followed a replayed step back"
    assert max(seq) < 2**40
    assert states[-1].counters["sumo_restarts"] == 0
    assert "went back" not in run.physics.tail(400)
    with run.viewer.lock:  # the probe forgets the steps this test put (later tests read its steps)
        run.viewer.steps[:] = [m for m in run.viewer.steps if m.step < 2**40]


def test_renderer_cannot_acknowledge_steps_for_physics_and_physics_can(run):
    attacker = run.client("renderer-ego")
    try:
        st = run.status()
        for i in range(300):
            attacker.put(Keys("sumoco", "sec", "main").ack, encode(StepAck("sec", st["steps"] + i, 0)))
        time.sleep(1.0)
        after = run.status()
    finally:
        attacker.close()
    # lockstep, one instance: one ack per step; 300 forged acks would put the acks received
    # (taken + replaced by a newer one before they were read) far above the steps
    assert after["acks"] + after["acks_coalesced"] <= after["steps"] + 1, after
    control = run.client("physics")  # the same burst from the physics role does arrive
    try:
        for i in range(300):
            control.put(Keys("sumoco", "sec", "intruder").ack, encode(StepAck("sec", 0, 0)))
        wait_until(lambda: (c := run.status())["acks"] + c["acks_coalesced"] >= c["steps"] + 250, 10,
                   "the physics role's acks")
    finally:
        control.close()


def test_renderer_may_drive_only_its_own_ego(run):
    def pose(ego_id: str) -> bytes:
        m = run.viewer.last_step()
        i = 0  # next to the first agent SUMO has: on the road
        return encode(EgoPose(ego_id, float(m.agents.x[i]) + 3.0, float(m.agents.y[i]), float(m.agents.angle[i]), 0.0))

    attacker = run.client("renderer-ego2")
    try:
        for _ in range(30):
            attacker.put(run.keys.ego("ego"), pose("ego"))
            time.sleep(0.02)
        time.sleep(0.5)
        assert wait_until(run.status, 10, "SUMO status")["ego_poses"] == 0
        with run.viewer.lock:
            assert not any("ego" in m.agents.ids for m in run.viewer.steps)
    finally:
        attacker.close()
    owner = run.client("renderer-ego")
    try:
        def sent_and_seen():
            owner.put(run.keys.ego("ego"), pose("ego"))
            m = run.viewer.last_step()
            return "ego" in m.agents.ids
        wait_until(sent_and_seen, 20, "the rightful renderer's ego in SUMO's steps", poll_s=0.05)
        assert wait_until(run.status, 10, "SUMO status")["ego_poses"] > 0
    finally:
        owner.close()


def _peak_rss_mb(pid: int) -> float:
    """Peak resident memory (VmHWM) of a process [MiB]."""
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 1024


def test_oversized_ego_poses_are_refused_by_length_before_they_are_kept(run):
    """The red team's renderer put 12 ego poses padded to 50 MiB: the SUMO side kept them in its
    ring (256 held) and peaked at 482 MB. Now a pose over 4 KiB is refused by its length on
    Zenoh's thread (``ego_oversized``), never copied, never queued."""
    pad = 4 << 20  # [bytes] each

    def settled():  # no pose of an earlier test still on its way
        a = run.status()
        time.sleep(0.5)
        b = run.status()
        return b if a and a.get("ego_poses") == b.get("ego_poses") else None
    before = wait_until(settled, 20, "the SUMO side's ego counters to settle")
    hwm0 = _peak_rss_mb(run.sumo.proc.pid)
    m = run.viewer.last_step()
    pose = msgpack.unpackb(encode(EgoPose("ego", float(m.agents.x[0]) + 3.0, float(m.agents.y[0]),
                                          float(m.agents.angle[0]), 0.0)), raw=False)
    padded = msgpack.packb({**pose, "pad": bytes(pad)}, use_bin_type=True)
    attacker = run.client("renderer-ego")
    try:
        for _ in range(12):
            # BLOCK: a put is dropped by default when the link is congested, and 4 MiB
            # messages congest it on a loaded machine; the test needs all 12 on the wire
            attacker.put(run.keys.ego("ego"), padded, congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: run.status().get("ego_oversized", 0) >= before.get("ego_oversized", 0) + 12, 30,
                   "the 12 padded poses refused by length", procs=[run.sumo])
    finally:
        attacker.close()
    after = run.status()
    assert after["ego_poses"] == before["ego_poses"]  # none was applied
    # Zenoh reassembles each message (a few in flight at once, measured up to ~24 MiB here);
    # the daemon never holds them all, as the ring of 256 did
    grew = _peak_rss_mb(run.sumo.proc.pid) - hwm0
    # Zenoh reassembles each 4 MiB message before any callback sees it, several at once under
    # load (25 MiB seen): the bound is well under the 48 MiB the 12 poses would hold if kept
    assert grew < 8 * pad / 2**20, f"the SUMO side's peak memory grew {grew:.0f} MiB"


def test_each_role_may_put_only_its_own_cameras(run):
    got: list[tuple[str, float]] = []
    sub = run.viewer.session.declare_subscriber(
        run.keys.viewer_camera_all, lambda s: got.append((str(s.key_expr), decode(s.payload.to_bytes()).x)))
    own, foreign = run.keys.viewer_camera("renderer-ego", "c1"), run.keys.viewer_camera("viewer", "c1")
    renderer = run.client("renderer-ego")
    try:
        def sent_and_seen():
            renderer.put(own, encode(CameraPose("c1", 1.0, 2.0)))
            return (own, 1.0) in got
        wait_until(sent_and_seen, 20, "the renderer's own camera at the viewer", poll_s=0.05)
        # a foreign camera, then an own one from the same session: once the own one is in,
        # the foreign one would have been too
        renderer.put(foreign, encode(CameraPose("c1", 1.0, 2.0)))
        renderer.put(own, encode(CameraPose("c1", 99.0, 2.0)))
        wait_until(lambda: (own, 99.0) in got, 10, "the renderer's second camera")
        assert not [k for k, _ in got if k == foreign], got
    finally:
        renderer.close()
        sub.undeclare()


def test_viewer_role_may_put_nothing_but_its_own_cameras(run):
    """A viewer certificate reads, and puts its own cameras: its ego pose, step, acks and a
    camera under another role never reach the daemons (nor another viewer)."""
    got: list[str] = []
    sub = run.viewer.session.declare_subscriber(run.keys.viewer_camera_all, lambda s: got.append(str(s.key_expr)))
    own, foreign = run.keys.viewer_camera("viewer", "v1"), run.keys.viewer_camera("renderer-ego", "v1")
    m = run.viewer.last_step()
    pose = encode(EgoPose("ego", float(m.agents.x[0]) + 3.0, float(m.agents.y[0]), float(m.agents.angle[0]), 0.0))
    before = wait_until(run.status, 10, "SUMO status")
    attacker = run.client("viewer")
    try:
        for i in range(30):
            attacker.put(run.keys.ego("ego"), pose)
            attacker.put(run.keys.step, encode(synthetic_step(5, step=FORGED_STEP + i)))
            attacker.put(Keys("sumoco", "sec", "main").ack, encode(StepAck("sec", before["steps"] + 10 * i, 0)))
            attacker.put(foreign, encode(CameraPose("v1", 5.0, 6.0)))
            time.sleep(0.02)

        def sent_and_seen():  # control: the same session's own camera does arrive, after all of the above
            attacker.put(own, encode(CameraPose("v1", 1.0, 2.0)))
            return own in got
        wait_until(sent_and_seen, 20, "the viewer's own camera at another viewer", poll_s=0.05)
        t0 = run.viewer.last_physics().tick
        wait_until(lambda: run.viewer.last_physics().tick > t0 + 50, 20, "physics to keep ticking",
                   procs=[run.physics])
        after = wait_until(run.status, 10, "SUMO status")
    finally:
        attacker.close()
        sub.undeclare()
    assert after["ego_poses"] == before["ego_poses"], (before, after)  # not even seen and rejected:
    assert after["rejected"] == before["rejected"], (before, after)    # never delivered
    acks = after["acks"] + after["acks_coalesced"] - before["acks"] - before["acks_coalesced"]
    assert acks <= after["steps"] - before["steps"] + 2, (before, after)  # one ack per step: none forged
    assert foreign not in got, got
    with run.viewer.lock:
        states = [st for lst in run.viewer.physics.values() for st in lst]
        steps = list(run.viewer.steps)
    assert max(st.sumo_step for st in states) < FORGED_STEP and max(s.step for s in steps) < FORGED_STEP
    assert states[-1].counters.get("rejected", 0) == 0


def test_gateway_role_relays_egos_of_any_id(run):
    """The WebSocket gateway relays engines without a Zenoh binding: its certificate may put
    ego poses under any ego key (it caps ids per client itself), which a renderer cannot."""
    before = wait_until(run.status, 10, "SUMO status")["ego_poses"]
    gateway = run.client("gateway")
    try:
        def sent_and_counted():
            m = run.viewer.last_step()
            gateway.put(run.keys.ego("ego"), encode(EgoPose(
                "ego", float(m.agents.x[0]) + 3.0, float(m.agents.y[0]), float(m.agents.angle[0]), 0.0)))
            return wait_until(run.status, 10, "SUMO status")["ego_poses"] >= before + 5
        wait_until(sent_and_counted, 20, "the gateway's ego poses at the SUMO side", poll_s=0.05)
    finally:
        gateway.close()


def _physics_counters(run) -> dict:
    return run.viewer.last_physics().counters


def test_one_role_cannot_pin_every_camera_slot(run):
    """A viewer certificate puts 64 cameras (every slot, kept fresh): before, a renderer's camera
    was then refused; now one role holds at most 16 and its own newest replace its oldest."""
    before = _physics_counters(run)
    flood = run.client("viewer")
    renderer = run.client("renderer-ego")
    try:
        for _ in range(2):  # twice: every flood camera was updated within the last second
            for i in range(64):
                flood.put(run.keys.viewer_camera("viewer", f"flood{i}"), encode(CameraPose(f"flood{i}", 0.0, 0.0)))
        wait_until(lambda: _physics_counters(run)["evicted_cameras"] >= before["evicted_cameras"] + 48, 20,
                   "the flood's oldest cameras replaced by its newest", procs=[run.physics])
        assert _physics_counters(run)["viewer_cameras"] <= 16 + before["viewer_cameras"]
        own = run.keys.viewer_camera("renderer-ego", "r1")

        def counted():
            renderer.put(own, encode(CameraPose("r1", 5.0, 5.0)))
            c = _physics_counters(run)
            return c["viewer_cameras"] >= 17 if before["viewer_cameras"] == 0 else c["viewer_cameras"] > 16
        wait_until(counted, 20, "the renderer's camera among the physics side's cameras", poll_s=0.05,
                   procs=[run.physics])
        assert _physics_counters(run)["rejected_cameras"] == before["rejected_cameras"]
    finally:
        flood.close()
        renderer.close()


def test_gateway_certificate_relays_a_websocket_clients_camera_to_physics(run):
    """The gateway relays its clients' cameras under its own role (``viewer/gateway/``), which
    its certificate may put: before, it used ``viewer/viewer/`` and the access control dropped
    every relayed camera, so none reached physics in the secure profile."""
    import asyncio
    import threading

    from websockets.sync.client import connect

    from sumoco.viewing.gateway import SECURE_CAMERA_ROLE, Gateway, GatewayConfig, pack_frame

    session = run.client("gateway")
    gw = Gateway(session, run.keys, GatewayConfig(port=0), camera_role=SECURE_CAMERA_ROLE)
    ready, loop_of = threading.Event(), {}

    async def serve():
        loop_of["stop"], loop_of["loop"] = asyncio.Event(), asyncio.get_running_loop()
        await gw.run(loop_of["stop"], lambda _: ready.set())
    server = threading.Thread(target=asyncio.run, args=(serve(),), daemon=True)
    server.start()
    try:
        assert ready.wait(20), "the gateway did not start"
        with connect(gw.url(), open_timeout=10) as ws:
            json.loads(ws.recv(timeout=5))  # hello
            # cameras of earlier tests time out first (5 s), so the count is the relayed one
            wait_until(lambda: _physics_counters(run)["viewer_cameras"] == 0, 20, "no camera at physics",
                       procs=[run.physics])

            def relayed_and_counted():
                ws.send(pack_frame("viewer/camera", encode(CameraPose("page", 7.0, 7.0))))
                return _physics_counters(run)["viewer_cameras"] == 1
            wait_until(relayed_and_counted, 20, "the relayed camera at physics, past the access control",
                       poll_s=0.1, procs=[run.physics])
            assert gw.cameras_forwarded > 0 and gw.rejected == 0
    finally:
        loop_of["loop"].call_soon_threadsafe(loop_of["stop"].set)
        server.join(10)
        session.close()


# ------------------------------------------------- rules no other test attacks: serve, state, tokens
#
# Each attack comes from a certificate of a lesser role (renderer or viewer) with its own link to
# the victim (the viewer probe). After the forged message the same session sends something its
# role may (its own camera or camera token, on the same link, in order): once that is in, the
# forged one would have been too. A control from the rightful role shows the same message arrives.

LESSER = ["renderer-ego", "viewer"]


def _sentinel_camera(run, session, role: str, got: list, client: str = "s1") -> None:
    """Put ``role``'s own camera until the probe's subscriber (``got``) has it."""
    own = run.keys.viewer_camera(role, client)

    def sent_and_seen():
        session.put(own, encode(CameraPose(client, 1.0, 2.0)))
        return own in got
    wait_until(sent_and_seen, 20, f"{role}'s own camera at the viewer", poll_s=0.05)


@pytest.mark.parametrize("what", ["static", "sumo_map"])
@pytest.mark.parametrize("role", LESSER)
def test_lesser_role_cannot_serve_static_data_or_the_map_and_sumo_can(run, role, what):
    """The SUMO side's queryables (static data, the glTF map): a lesser role's queryable on
    the same key is never asked, a sumo certificate's is, next to the real SUMO side's."""
    key = getattr(run.keys, what)

    def answers() -> list[bytes]:  # every reply, not consolidated: two answers on one key both count
        return [r.ok.payload.to_bytes() for r in run.viewer.session.get(
            key, consolidation=zenoh.ConsolidationMode.NONE, timeout=3.0) if r.ok is not None]
    real = wait_until(answers, 30, f"the SUMO side's {what} reply at the viewer")
    assert len(real) == 1 and len(real[0]) > 1000
    got_cameras: list[str] = []
    cam_sub = run.viewer.session.declare_subscriber(run.keys.viewer_camera_all,
                                                    lambda s: got_cameras.append(str(s.key_expr)))
    attacker = run.linked_client(role)
    forged_q = attacker.declare_queryable(key, lambda q: q.reply(key, b"forged"))
    control = q = None
    try:
        _sentinel_camera(run, attacker, role, got_cameras)  # a put after the declaration, on the same link
        seen = [answers() for _ in range(3)]
        # control: a sumo certificate serving the same key is answered next to the real SUMO side
        control = run.linked_client("sumo")
        q = control.declare_queryable(key, lambda q: q.reply(key, b"control"))

        def with_control():
            a = answers()
            return a if b"control" in a else None
        both = wait_until(with_control, 20, f"the sumo role's {what} reply at the viewer")
    finally:
        forged_q.undeclare()
        attacker.close()
        cam_sub.undeclare()
        if q is not None:
            q.undeclare()
        if control is not None:
            control.close()
    for a in seen:  # only the real SUMO side answered
        assert len(a) == 1 and b"forged" not in a and len(a[0]) > 1000, [x[:20] for x in a]
    if what == "static":
        assert len(decode(seen[-1][0]).lanes.ids) > 10
    assert b"forged" not in both and len(both) == 2, [x[:20] for x in both]


@pytest.mark.parametrize("role", LESSER)
def test_lesser_role_cannot_put_a_physics_state_and_physics_can(run, role):
    got_cameras: list[str] = []
    cam_sub = run.viewer.session.declare_subscriber(run.keys.viewer_camera_all,
                                                    lambda s: got_cameras.append(str(s.key_expr)))
    real: PhysicsState = run.viewer.last_physics()
    forged = encode(dataclasses.replace(real, sumo_step=FORGED_STEP, tick=FORGED_STEP))
    main, other = run.keys.physics_state, Keys("sumoco", "sec", "forged").physics_state
    attacker = run.linked_client(role)
    try:
        for _ in range(10):
            attacker.put(main, forged)  # on the real instance's key: the viewer would draw it
            attacker.put(other, forged)  # and as a physics instance of its own
        _sentinel_camera(run, attacker, role, got_cameras)
    finally:
        attacker.close()
        cam_sub.undeclare()
    with run.viewer.lock:
        states = {k: list(v) for k, v in run.viewer.physics.items()}
    assert "forged" not in states, sorted(states)
    assert max(st.sumo_step for st in states["main"]) < FORGED_STEP
    assert max(st.tick for st in states["main"]) < FORGED_STEP
    control = run.linked_client("physics")  # the same state from the physics role does arrive
    try:
        key = Keys("sumoco", "sec", "intruder").physics_state

        def sent_and_seen():
            control.put(key, forged)
            return run.viewer.last_physics("intruder")
        assert wait_until(sent_and_seen, 20, "the physics role's state at the viewer", poll_s=0.05).tick == FORGED_STEP
    finally:
        control.close()


@pytest.mark.parametrize("role", LESSER)
def test_lesser_role_cannot_hold_a_physics_or_sumo_token_and_the_rightful_roles_can(run, role):
    ghost = Keys("sumoco", "ghost")  # a run without a SUMO side: a sumo token there is forged for sure
    forged = [Keys("sumoco", "sec", "forged").physics_alive, ghost.sumo_alive, ghost.physics_alive]
    seen: list[tuple[str, str]] = []
    sub = run.viewer.session.liveliness().declare_subscriber(
        "sumoco/**", lambda s: seen.append((str(s.key_expr), str(s.kind))), history=True)

    def alive_now() -> set[str]:
        return {str(r.ok.key_expr) for r in run.viewer.session.liveliness().get("sumoco/**", timeout=3.0)
                if r.ok is not None}
    attacker = run.linked_client(role)
    tokens, rightful = [], []
    control: list[zenoh.Session] = []
    try:
        tokens = [attacker.liveliness().declare_token(k) for k in forged]
        # the attacker's own camera token, declared after them on the same link
        own = run.keys.viewer_alive(role, "t1")
        tokens.append(attacker.liveliness().declare_token(own))
        wait_until(lambda: own in {k for k, _ in seen}, 20, f"{role}'s own camera token at the viewer")
        listed = alive_now()
        assert own in listed and run.keys.sumo_alive in listed, listed
        assert not set(forged) & (listed | {k for k, _ in seen}), (listed, seen)
        # control: the rightful roles' tokens on the same keys do show up
        control = [run.linked_client("physics"), run.linked_client("sumo")]
        rightful = [control[0].liveliness().declare_token(forged[0]),
                    control[1].liveliness().declare_token(ghost.sumo_alive)]
        wait_until(lambda: {forged[0], ghost.sumo_alive} <= {k for k, _ in seen}, 20,
                   "the physics and sumo roles' tokens at the viewer")
        assert ghost.physics_alive not in {k for k, _ in seen}
    finally:
        for t in (*tokens, *rightful):
            t.undeclare()
        attacker.close()
        for c in control:
            c.close()
        sub.undeclare()
