"""``sumoco router``: routers as real OS processes that form a mesh, plain and secure.

A publisher that is a client of router A and a subscriber that is a client of router B
(B connects to A) only meet through the A-B link. The secure mesh runs the same with
the certificates of ``sumoco certs init`` and the role policy, where the routers present
the ``router`` certificate and a forged message is stopped at the first router.
"""

from __future__ import annotations

import argparse
import signal
import socket

import pytest
import zenoh

from protocol.codec import decode, encode
from protocol.keys import Keys
from protocol.messages import EgoPose, StepAck
from sumoco.orchestrate.router import router_config
from runtime.config import SecurityConfig, ZenohConfig
from runtime.transport import open_session
from synthetic.traffic import synthetic_step
from tests.harness import ROOT, Daemon, endpoint, wait_until

pytestmark = pytest.mark.integration


def _listening(ep: str) -> bool:
    host, port = ep.split("/", 1)[1].rsplit(":", 1)
    try:
        with socket.create_connection((host, int(port)), timeout=0.5):
            return True
    except OSError:
        return False


def _router(name: str, tmp_path, listen: str, connect: str | None = None, config: str | None = None) -> Daemon:
    args = ["router", "--listen", listen, *(["--connect", connect] if connect else []),
            *(["--config", config] if config else [])]
    d = Daemon(name, args, tmp_path / "logs")
    wait_until(lambda: _listening(listen), 30, f"{name} to listen on {listen}", procs=[d])
    return d


def _client(ep: str, sec: SecurityConfig | None = None, role: str = "viewer") -> zenoh.Session:
    cfg = ZenohConfig(mode="client", connect=(ep,)) if sec is None else \
        ZenohConfig(mode="client", connect=(ep,), security=sec)
    s = open_session(cfg, role=role)
    wait_until(lambda: list(s.info.routers_zid()), 10, f"the {role} client to reach its router")
    return s


def _plain_client(ep: str) -> zenoh.Config:
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("connect/endpoints", f'["{ep}"]')
    c.insert_json5("scouting/multicast/enabled", "false")
    return c


def _stop(a: Daemon, b: Daemon) -> dict:
    """SIGTERM to A, SIGINT (Ctrl-C) to B: both routers must leave cleanly."""
    a_code = a.terminate(10)
    b.proc.send_signal(signal.SIGINT)
    try:
        b.proc.wait(10)
    finally:
        b_code = b.terminate(5)
    return {a.name: a_code, b.name: b_code}


def test_router_config_takes_the_files_security_but_only_its_own_endpoints():
    def args(*argv):
        ns = argparse.Namespace(config=None, listen=None, connect=None)
        for k, v in zip(argv[::2], argv[1::2]):
            setattr(ns, k, v)
        return ns

    z = router_config(args()).zenoh
    assert (z.mode, z.listen, z.connect) == ("router", ("tcp/127.0.0.1:7447",), ())
    # docker.toml's [zenoh] is the daemons' (mode client, connect to this very router)
    z = router_config(args("config", str(ROOT / "configs" / "docker.toml"))).zenoh
    assert (z.mode, z.listen, z.connect) == ("router", ("tcp/127.0.0.1:7447",), ())
    z = router_config(args("config", str(ROOT / "configs" / "secure.toml"), "listen", ["tcp/127.0.0.1:9"],
                           "connect", ["tcp/127.0.0.1:8", "tcp/127.0.0.1:7"])).zenoh
    assert (z.mode, z.listen, z.connect) == ("router", ("tcp/127.0.0.1:9",), ("tcp/127.0.0.1:8", "tcp/127.0.0.1:7"))
    assert z.security.enabled and z.security.acl


def test_two_routers_form_a_mesh(tmp_path):
    ep_a, ep_b = endpoint(), endpoint()
    a = _router("router-a", tmp_path, ep_a)
    b = _router("router-b", tmp_path, ep_b, connect=ep_a)
    pub = sub = None
    got: list[bytes] = []
    try:
        pub, sub = _client(ep_a), _client(ep_b)
        # each client knows its own router only: what reaches one from the other crossed A-B
        ra, rb = {str(z) for z in pub.info.routers_zid()}, {str(z) for z in sub.info.routers_zid()}
        assert len(ra) == len(rb) == 1 and ra != rb, (ra, rb)
        s = sub.declare_subscriber("sumoco/mesh/**", lambda x: got.append(x.payload.to_bytes()))

        def sent_and_seen():  # until B has learnt of the subscription and told A
            pub.put("sumoco/mesh/sumo/step", b"over the mesh")
            return got
        wait_until(sent_and_seen, 20, "the sample from A's client at B's client", poll_s=0.1, procs=[a, b])
        assert set(got) == {b"over the mesh"}
        # and the other way round, a query from B's client answered by A's client
        q = pub.declare_queryable("sumoco/mesh/sumo/static", lambda query: query.reply(query.key_expr, b"static"))

        def answered():
            return [r.ok.payload.to_bytes() for r in sub.get("sumoco/mesh/sumo/static", timeout=2.0)
                    if r.ok is not None]
        assert wait_until(answered, 20, "the queryable behind A to answer B's client", procs=[a, b]) == [b"static"]
        q.undeclare()
        s.undeclare()
    finally:
        for x in (pub, sub):
            if x is not None:
                x.close()
        codes = _stop(a, b)
    assert codes == {"router-a": 0, "router-b": 0}, (codes, a.tail(), b.tail())


def test_secure_routers_mesh_with_tls_and_stop_a_forged_step_at_the_first_router(tmp_path):
    from sumoco.orchestrate.certs import init_certs

    certs = tmp_path / "certs"
    init_certs(certs, renderers=("ego",), router=True)
    cfg = tmp_path / "secure.toml"
    cfg.write_text(f'[run]\nid = "mesh"\n[zenoh]\nmode = "peer"\n[zenoh.security]\ncerts = "{certs}"\n'
                   'renderers = ["ego"]\n')
    sec = SecurityConfig(certs=certs, renderers=("ego",))
    keys = Keys("sumoco", "mesh")
    ep_a, ep_b = endpoint(), endpoint()
    a = _router("router-a", tmp_path, ep_a, config=str(cfg))
    b = _router("router-b", tmp_path, ep_b, connect=ep_a, config=str(cfg))
    sessions: list[zenoh.Session] = []
    steps: list[int] = []
    acks: list[int] = []
    egos: list[str] = []
    try:
        for r in (a, b):
            wait_until(lambda r=r: "(TLS, mutual authentication, access control)" in r.log.read_text(), 10,
                       f"{r.name}'s start line", procs=[a, b])
        with pytest.raises(zenoh.ZError):  # no certificate from the run's CA: no link to a router
            zenoh.open(_plain_client(ep_a)).close()
        sumo = _client(ep_a, sec, "sumo")
        renderer = _client(ep_a, sec, "renderer-ego")
        physics = _client(ep_b, sec, "physics")
        viewer = _client(ep_b, sec, "viewer")
        sessions += [sumo, renderer, physics, viewer]
        subs = [
            viewer.declare_subscriber(keys.step, lambda s: steps.append(decode(s.payload.to_bytes()).step)),
            sumo.declare_subscriber(keys.ack_all, lambda s: acks.append(decode(s.payload.to_bytes()).step)),
            viewer.declare_subscriber(keys.ego_all, lambda s: egos.append(str(s.key_expr))),
        ]

        def step_seen():  # the sumo role's step crosses A -> B (both routers: TLS, policy)
            sumo.put(keys.step, encode(synthetic_step(3, step=7)))
            return 7 in steps
        wait_until(step_seen, 30, "sumo's step at the viewer behind router B", poll_s=0.1, procs=[a, b])

        def ack_seen():  # the physics role's ack crosses B -> A
            physics.put(Keys("sumoco", "mesh", "main").ack, encode(StepAck("mesh", 7, 0)))
            return 7 in acks
        wait_until(ack_seen, 30, "physics' ack at the sumo client behind router A", poll_s=0.1, procs=[a, b])

        # a renderer's forged step, then its own ego pose from the same session: once the
        # pose is through, the step would have been too, had router A let it in
        renderer.put(keys.step, encode(synthetic_step(3, step=900_000)))
        renderer.put(Keys("sumoco", "mesh", "main").ack, encode(StepAck("mesh", 900_000, 0)))

        def ego_seen():
            renderer.put(keys.ego("ego"), encode(EgoPose("ego", 1.0, 2.0, 0.0, 0.0)))
            return keys.ego("ego") in egos
        wait_until(ego_seen, 30, "the renderer's own ego pose at the viewer behind router B", poll_s=0.1,
                   procs=[a, b])
        assert 900_000 not in steps and 900_000 not in acks, (steps[-5:], acks[-5:])
        for s in subs:
            s.undeclare()
    finally:
        for x in sessions:
            x.close()
        codes = _stop(a, b)
    assert codes == {"router-a": 0, "router-b": 0}, (codes, a.tail(), b.tail())
