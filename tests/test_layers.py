"""The architecture holds: import layers, no cycles, a bare install without the sides' extras.

The layer and independence contracts themselves are in ``pyproject.toml``
(``[tool.importlinter]``) and run as ``lint-imports`` in ``make test``; here we check
what import-linter has no contract for (cycles) and that the contracts are enforced.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import venv
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("protocol", "runtime", "synthetic", "sumo_side", "physics_side", "sumoco")


def _cycles(graph) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, it = work[-1]
            nxt = next(it, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter
                    counter += 1
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph.find_modules_directly_imported_by(nxt)))))
                elif nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    comp.append(m)
                    if m == node:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_no_import_cycles_between_modules():
    graph = grimp.build_graph(*PACKAGES)
    assert len(graph.modules) > 40  # the whole tree was analysed
    assert _cycles(graph) == []


def test_cycle_finder_finds_a_cycle():
    g = grimp.ImportGraph()
    for a, b in (("x.a", "x.b"), ("x.b", "x.c"), ("x.c", "x.a"), ("x.c", "x.d")):
        g.add_import(importer=a, imported=b)
    assert _cycles(g) == [["x.a", "x.b", "x.c"]]


def _lint(tree: Path) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("lint-imports")
    env = os.environ | {"PYTHONPATH": str(tree)}
    return subprocess.run([str(exe), "--config", str(tree / "pyproject.toml"), "--no-cache"], cwd=tree,
                          env=env, capture_output=True, text=True, timeout=120)


def test_lint_imports_passes_and_fails_on_a_forbidden_import(tmp_path):
    ok = _lint(ROOT)
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert "0 broken" in ok.stdout
    # no exception hides an arrow: every layer is a folder of its own and the contracts hold as written
    assert "ignore_imports" not in (ROOT / "pyproject.toml").read_text()
    # The same tree with one forbidden import (the SUMO side reaching into the physics side).
    for pkg in PACKAGES:
        subprocess.run(["cp", "-r", str(ROOT / pkg), str(tmp_path / pkg)], check=True)
    (tmp_path / "pyproject.toml").write_text((ROOT / "pyproject.toml").read_text())
    bridge = tmp_path / "sumo_side" / "bridge.py"
    bridge.write_text(bridge.read_text() + "\nfrom physics_side import control  # noqa: E402,F401\n")
    bad = _lint(tmp_path)
    assert bad.returncode != 0
    assert "BROKEN" in bad.stdout and "sumo_side.bridge -> physics_side.control" in bad.stdout
    # ... and with the common runtime reaching up into the application instead
    bridge.write_text(bridge.read_text().replace("\nfrom physics_side import control  # noqa: E402,F401\n", "\n"))
    logs = tmp_path / "runtime" / "logs.py"
    logs.write_text(logs.read_text() + "\nfrom sumoco.orchestrate import demo  # noqa: E402,F401\n")
    bad = _lint(tmp_path)
    assert bad.returncode != 0
    assert "BROKEN" in bad.stdout and "runtime.logs -> sumoco.orchestrate.demo" in bad.stdout
    assert "sumo_side.bridge -> physics_side.control" not in bad.stdout


@pytest.mark.integration
def test_bare_wheel_installs_without_libsumo_and_mujoco(tmp_path):
    """`pip install sumoco` (no extras): protocol decodes the golden vectors; the sides ask for their extra;
    a recording replays and `sumoco view` serves the 3D page with its three.js."""
    dist = tmp_path / "dist"
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--wheel-dir", str(dist),
                        str(ROOT)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    wheel = next(dist.glob("sumoco-*.whl"))
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    py = env_dir / "bin" / "python"
    r = subprocess.run([str(py), "-m", "pip", "install", "--quiet", str(wheel)], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    check = r'''
import importlib.util, json, sys
from pathlib import Path
import protocol
from protocol.codec import decode
gold = Path(protocol.__file__).parent / "golden"
decoded = sorted(p.name for p in gold.glob("*.msgpack") if not p.name.startswith("invalid"))
for name in decoded:
    decode((gold / name).read_bytes())
print(json.dumps({"decoded": decoded,
                  "libsumo": importlib.util.find_spec("libsumo") is not None,
                  "mujoco": importlib.util.find_spec("mujoco") is not None,
                  "client": importlib.util.find_spec("sumoco.examples.client") is not None}))
'''
    r = subprocess.run([str(py), "-c", check], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    facts = json.loads(r.stdout)
    assert len(facts["decoded"]) >= 5 and not facts["libsumo"] and not facts["mujoco"] and facts["client"]
    exe = env_dir / "bin" / "sumoco"
    v = subprocess.run([str(exe), "--version"], capture_output=True, text=True, timeout=60)
    assert v.returncode == 0 and "protocol" in v.stdout
    for cmd, extra in (("sumo", "sumo"), ("physics", "physics"), ("record --out r.mcap", "foxglove"),
                       ("foxglove", "foxglove")):
        r = subprocess.run([str(exe), *cmd.split()], capture_output=True, text=True, timeout=60, cwd=tmp_path)
        assert r.returncode == 2, (cmd, r.returncode, r.stderr)
        assert f"pip install 'sumoco[{extra}]'" in r.stderr, r.stderr
    # The map export needs no SUMO: a renderer author gets the GLB from the bare install.
    net = Path(__file__).resolve().parents[1] / "configs" / "scenarios" / "paper" / "paper.net.xml"
    r = subprocess.run([str(exe), "map", "export", str(net), "--out", "m.glb", "--quiet"], capture_output=True,
                       text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "m.glb").read_bytes()[:4] == b"glTF"
    _bare_replay_reaches_a_subscriber(exe, tmp_path)


def _bare_replay_reaches_a_subscriber(exe: Path, tmp_path: Path) -> None:
    """A renderer author's path: the bare install replays a recording; a Zenoh client gets the steps."""
    from protocol.codec import decode
    from protocol.keys import Keys
    from protocol.messages import StepMessage
    from runtime.config import ZenohConfig
    from runtime.transport import open_session
    from tests.harness import endpoint, wait_until
    from tests.recording_fixture import make_recording

    rec = tmp_path / "run.mcap"
    make_recording(rec, steps=10)  # written here (the recorder needs the foxglove extra)
    keys = Keys("sumoco", "synth")
    ep = endpoint()
    proc = subprocess.Popen([str(exe), "replay", str(rec), "--loop", "--listen", ep, "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    got: list[bytes] = []
    try:
        with open_session(ZenohConfig(listen=(endpoint(),), connect=(ep,))) as s:
            s.declare_subscriber(keys.step, lambda smp: got.append(smp.payload.to_bytes()))
            wait_until(lambda: len(got) >= 5 or proc.poll() is not None, 30.0, "steps from the bare replay")
            assert proc.poll() is None, proc.communicate()[1]
            static = [r.ok.payload.to_bytes() for r in s.get(keys.static, timeout=5.0) if r.ok is not None]
        assert len(static) == 1
        assert all(isinstance(decode(g), StepMessage) for g in got[:5])
        _bare_view_serves_the_3d_page(exe, tmp_path, ep)
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert json.loads(out.strip().splitlines()[-1])["steps"] >= 5


def _bare_view_serves_the_3d_page(exe: Path, tmp_path: Path, replay_ep: str) -> None:
    """`sumoco view` from the bare install, on the bare replay: the 3D page, its three.js and the map."""
    import urllib.request

    from tests.harness import endpoint, wait_until

    proc = subprocess.Popen([str(exe), "view", "--run", "synth", "--connect", replay_ep, "--listen", endpoint(),
                             "--port", "0", "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path)
    try:
        line = proc.stdout.readline()  # "sumoco view: open http://127.0.0.1:PORT/?token=..."
        assert "?token=" in line, (line, proc.poll())
        url = line[line.index("http"):].strip()
        base, token = url.split("/?token=")

        def get(path: str) -> tuple[int, bytes]:
            with urllib.request.urlopen(f"{base}{path}?token={token}", timeout=10) as r:
                return r.status, r.read()

        status, page = get("/")
        assert status == 200 and b"viewer3d.js" in page and b"vendor/three/build/three.module.js" in page
        for path in ("/viewer3d.js", "/decode.js", "/vendor/three/build/three.module.js",
                     "/vendor/three/build/three.core.js", "/vendor/three/examples/jsm/loaders/GLTFLoader.js",
                     "/vendor/three/examples/jsm/controls/OrbitControls.js", "/2d.html"):
            status, body = get(path)
            assert status == 200 and len(body) > 1000, (path, status, len(body))
        def fed() -> dict | None:
            st = json.loads(get("/status")[1])
            return st if st["static"] and st["steps_received"] and st["map_bytes"] else None

        st = wait_until(fed, 30.0, "the bare view to get the replay's static data, steps and a map", 0.2)
        status, glb = get("/map.glb")
        assert status == 200 and glb[:4] == b"glTF", (status, glb[:4], st)
        assert proc.poll() is None
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
