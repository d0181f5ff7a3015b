"""Map export (``sumoco map export``): geometry, frames, markings, signal heads, and the
Khronos glTF validator on the bundled network and on every network of the scenario pack."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from protocol.errors import ConfigError
from sumo_side.mapmesh import build_map, dashes, map_origin, ribbon
from sumo_side.netfile import read_net

ROOT = Path(__file__).resolve().parents[1]
PAPER_NET = ROOT / "configs" / "scenarios" / "paper" / "paper.net.xml"
VALIDATOR = ROOT / "tests" / "js" / "validate_gltf.mjs"
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def scenario_pack() -> Path | None:
    """The scenario pack: ``shared/scenarios`` beside the repository (or beside a parent)."""
    for base in (ROOT.parent, *ROOT.parent.parents):
        pack = base / "shared" / "scenarios"
        if (pack / "MANIFEST.md").is_file():
            return pack
    return None


def pack_networks() -> list[Path]:
    pack = scenario_pack()
    if pack is None:
        if IN_CI:
            raise AssertionError("scenario pack not found: CI has shared/scenarios beside the clone")
        return []
    nets = sorted(pack.glob("*/*.net.xml")) + sorted(pack.glob("*/*.net.xml.gz"))
    assert nets, f"no networks in {pack}"
    return nets


def _accessor(g: pygltflib.GLTF2, i: int) -> np.ndarray:
    a = g.accessors[i]
    bv = g.bufferViews[a.bufferView]
    dtype = {pygltflib.FLOAT: np.float32, pygltflib.UNSIGNED_INT: np.uint32,
             pygltflib.UNSIGNED_SHORT: np.uint16}[a.componentType]
    width = {"VEC3": 3, "SCALAR": 1}[a.type]
    out = np.frombuffer(g.binary_blob(), dtype, a.count * width, bv.byteOffset)
    return out.reshape(a.count, width) if width > 1 else out


def _load(glb: bytes) -> pygltflib.GLTF2:
    return pygltflib.GLTF2.load_from_bytes(glb)


def _mesh_positions(g: pygltflib.GLTF2, name: str) -> np.ndarray:
    mesh = next(m for m in g.meshes if m.name == name)
    return _accessor(g, mesh.primitives[0].attributes.POSITION)


# ----------------------------------------------------------------------------- geometry


def test_ribbon_has_the_true_width_and_faces_up():
    p = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 10.0]])
    verts, tris = ribbon(p, 1.6, 1.6)
    left, right = verts[0::2], verts[1::2]
    # Miter joins keep the offset lines 1.6 m from every segment, also at the bend.
    for k in range(len(p)):
        assert np.hypot(*(left[k] - right[k])) >= 3.2 - 1e-9
    assert np.allclose(left[0], [0, 1.6]) and np.allclose(right[0], [0, -1.6])
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    assert (cross > 0).all()  # counter-clockwise from above: glTF front faces point up


def test_dashes_have_the_asked_length_and_rhythm():
    p = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 30.0]])
    pieces = dashes(p, 3.0, 6.0)
    assert len(pieces) == 7
    for piece in pieces:
        assert np.hypot(*np.diff(piece, axis=0).T).sum() == pytest.approx(3.0)


def test_origin_is_local_only_for_far_networks():
    assert map_origin((-150, -140, 140, 140)) == (0.0, 0.0)
    assert map_origin((690800.0, 5334800.0, 691210.0, 5335190.0)) == (691000.0, 5335000.0)


# ----------------------------------------------------------------------------- the bundled network


def test_bundled_network_frames_heads_and_markings():
    net = read_net(PAPER_NET)
    mesh = build_map(net)
    g = _load(mesh.glb)
    assert mesh.origin == (0.0, 0.0)
    assert g.scenes[g.scene].extras["sumoco"]["origin"] == [0.0, 0.0]
    # One node per traffic-light head, named by tls id and link index.
    links = {(c.tls, c.link) for c in net.connections if c.tls}
    heads = {n.name for n in g.nodes if n.name and n.name.startswith("tls/")}
    assert heads == {f"tls/{t}/{k}" for t, k in links} and len(heads) == mesh.heads == 16
    # Frame: glTF X = x (east), Z = -y (north is -Z), Y up. A head sits over its lane's end.
    node = next(n for n in g.nodes if n.name == "tls/C/0")
    lane = net.lane(node.extras["lane"])
    assert node.translation[0] == pytest.approx(lane.shape[-1, 0])
    assert node.translation[2] == pytest.approx(-lane.shape[-1, 1])
    assert node.translation[1] > 3.0
    # Road surfaces have the lanes' true widths: mesh area = sum of length x width.
    mesh_lanes = next(m for m in g.meshes if m.name == "lanes").primitives[0]
    pos = _accessor(g, mesh_lanes.attributes.POSITION)[:, [0, 2]].astype(np.float64)
    tri = _accessor(g, mesh_lanes.indices).reshape(-1, 3)
    a, b, c = pos[tri[:, 0]], pos[tri[:, 1]], pos[tri[:, 2]]
    area = 0.5 * np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])).sum()
    want = sum(np.hypot(*np.diff(ln.shape, axis=0).T).sum() * ln.width for ln in net.lanes
               if ln.function in ("normal", "internal") and not ln.pedestrian_only)
    assert area == pytest.approx(want, rel=0.03)
    for name in ("junctions", "lanes", "sidewalks", "crossings", "markings", "tls_heads"):
        assert name in mesh.layers, name
    assert np.allclose(_mesh_positions(g, "lanes")[:, 1], 0.01)


def _one_edge_net(tmp_path: Path, change: str) -> Path:
    net = tmp_path / "two_lanes.net.xml"
    net.write_text(f"""<?xml version="1.0"?>
<net version="1.20">
  <location netOffset="0.00,0.00" convBoundary="0,0,100,0" projParameter="!"/>
  <edge id="E" from="A" to="B">
    <lane id="E_0" index="0" speed="13.9" length="100" width="3.00" shape="0,-1.5 100,-1.5"/>
    <lane id="E_1" index="1" speed="13.9" length="100" width="3.00" shape="0,1.5 100,1.5" {change}/>
  </edge>
  <edge id="E2" from="A" to="B">
    <lane id="E2_0" index="0" speed="13.9" length="100" width="3.00" shape="0,-1.5 100,-1.5" {change.replace('Right', 'Left')}/>
    <lane id="E2_1" index="1" speed="13.9" length="100" width="3.00" shape="0,1.5 100,1.5" {change}/>
  </edge>
</net>
""")
    return net


@pytest.mark.parametrize("change, dashed", [("", True), ('changeRight="passenger bus"', True),
                                            ('changeRight="bus"', False), ('changeRight=""', False)])
def test_lane_separator_is_dashed_only_where_cars_may_change(tmp_path, change, dashed):
    g = _load(build_map(_one_edge_net(tmp_path, change)).glb)
    pos = _mesh_positions(g, "markings")
    # The separator lies on y = 0 (glTF Z = 0); outer lines at |y| = 2.75.
    sep = pos[np.abs(pos[:, 2]) < 0.2]
    xs = np.unique(np.round(sep[:, 0], 3))
    covered = sum(b - a for a, b in zip(xs[0::2], xs[1::2]))
    if dashed:
        assert 25 < covered < 45, xs  # 3 m of line every 9 m over 100 m
    else:
        assert covered == pytest.approx(100, abs=0.01)


def test_far_network_keeps_millimetres(tmp_path):
    """The UTM variant of the pack's grid gives the same mesh as the local one, shifted."""
    pack = scenario_pack()
    if pack is None:
        if IN_CI:
            raise AssertionError("scenario pack missing in CI")
        pytest.skip("scenario pack (shared/scenarios) not beside the repository")
    local = build_map(pack / "synth_utm_grid" / "grid_local.net.xml")
    utm = build_map(pack / "synth_utm_grid" / "grid_utm.net.xml")
    assert local.origin == (0.0, 0.0) and utm.origin[0] > 600_000 and utm.origin[1] > 5_000_000
    a = _mesh_positions(_load(local.glb), "junctions")
    b = _mesh_positions(_load(utm.glb), "junctions")
    off = read_net(pack / "synth_utm_grid" / "grid_utm.net.xml").bounds[0] - read_net(
        pack / "synth_utm_grid" / "grid_local.net.xml").bounds[0]
    shift = np.array([off - utm.origin[0], 0.0], np.float64)
    # Compare the junction outlines' bounding boxes: identical to the millimetre.
    amin, bmin = a.min(axis=0).astype(np.float64), b.min(axis=0).astype(np.float64)
    assert abs(bmin[0] + utm.origin[0] - (amin[0] + off)) < 0.002, (amin, bmin, shift)


def test_bad_network_file_is_a_config_error_naming_it(tmp_path):
    bad = tmp_path / "broken.net.xml"
    bad.write_text("<net><edge id='e'><lane id='e_0' shape='0,0 1,")
    with pytest.raises(ConfigError, match="broken.net.xml"):
        read_net(bad)
    with pytest.raises(ConfigError, match="not found"):
        read_net(tmp_path / "missing.net.xml")
    other = tmp_path / "routes.net.xml"
    other.write_text("<routes/>")
    with pytest.raises(ConfigError, match="expected <net>"):
        read_net(other)


def test_cli_exports_and_reports_errors(tmp_path):
    out = tmp_path / "m" / "map.glb"
    r = subprocess.run([sys.executable, "-m", "sumoco.cli", "map", "export", str(PAPER_NET), "--out", str(out),
                        "--quiet"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert out.stat().st_size > 10_000 and "16 signal heads" in r.stdout
    assert out.read_bytes()[:4] == b"glTF"
    r = subprocess.run([sys.executable, "-m", "sumoco.cli", "map", "export", str(tmp_path / "nope.net.xml"),
                        "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "nope.net.xml" in r.stderr and "not found" in r.stderr


# ----------------------------------------------------------------------------- Khronos validator


def _node() -> str:
    node = shutil.which("node")
    if node is None or not (ROOT / "node_modules" / "gltf-validator").is_dir():
        msg = "node and node_modules/gltf-validator are needed (make install runs npm ci)"
        if IN_CI:
            raise AssertionError(msg)
        pytest.skip(msg)
    return node


def test_khronos_validator_finds_no_error_on_any_network(tmp_path):
    node = _node()
    nets = [PAPER_NET, *pack_networks()]
    files, sizes = [], {}
    for net in nets:
        mesh = build_map(net)
        out = tmp_path / f"{net.parent.name}_{net.name.split('.')[0]}.glb"
        out.write_bytes(mesh.glb)
        files.append(str(out))
        sizes[out.name] = (len(mesh.glb), mesh.vertices, mesh.triangles, mesh.heads, round(mesh.seconds, 3))
    r = subprocess.run([node, str(VALIDATOR), *files], capture_output=True, text=True, cwd=ROOT, timeout=300)
    reports = [json.loads(line) for line in r.stdout.splitlines() if line.startswith("{")]
    assert len(reports) == len(files), r.stdout + r.stderr
    for rep in reports:
        assert rep["errors"] == 0, rep
    assert r.returncode == 0
    for name, row in sorted(sizes.items(), key=lambda kv: -kv[1][0]):
        print(f"{name}: {row[0] / 1024:.0f} KiB, {row[1]} vertices, {row[2]} triangles, {row[3]} heads, {row[4]} s")
    if IN_CI:
        assert len(files) >= 8  # the bundled network and the pack's seven


# ----------------------------------------------------------------------------- served by the SUMO side


@pytest.mark.integration
def test_sumo_side_serves_the_map_once_per_hash(tmp_path):
    """A late joiner gets the GLB with one get, and only the hash when it already has it."""
    import msgpack

    from protocol.keys import Keys
    from runtime.config import ZenohConfig
    from runtime.transport import open_session
    from tests.harness import PAPER_CFG, Daemon, endpoint, wait_until

    ep = endpoint()
    sumo = Daemon("sumo", ["sumo", "--sumocfg", str(PAPER_CFG), "--listen", ep, "--run", "maptest",
                           "--timing", "realtime", "--duration", "60"], tmp_path / "logs")
    try:
        with open_session(ZenohConfig(connect=(ep,))) as s:
            key = Keys("sumoco", "maptest").sumo_map

            def ask(params: str = ""):
                for reply in s.get(key + (f"?{params}" if params else ""), timeout=2.0):
                    if reply.ok is not None:
                        return msgpack.unpackb(reply.ok.payload.to_bytes())
                return None

            doc = wait_until(ask, 30.0, "the map reply", poll_s=0.2, procs=[sumo])
            want = build_map(PAPER_NET)
            assert doc["kind"] == "map" and doc["run"] == "maptest"
            assert doc["sha256"] == want.sha256 and doc["size"] == len(doc["glb"]) == len(want.glb)
            assert doc["glb"] == want.glb
            again = ask(f"sha256={doc['sha256']}")
            assert again["glb"] is None and again["sha256"] == doc["sha256"]
            assert ask("sha256=0000")["glb"] == want.glb
            # The viewer's feed takes the SUMO side's map (not one rebuilt from static data).
            from sumoco.viewing.viewer.server import LatestStore, ViewerConfig, ZenohFeed

            store = LatestStore()
            feed = ZenohFeed(s, Keys("sumoco", "maptest"), store, ViewerConfig()).start()
            try:
                wait_until(lambda: store.static is not None and store.map_glb is not None, 20.0,
                           "the viewer feed's static data and map", procs=[sumo])
                assert store.map_source == "sumo" and store.map_sha256 == want.sha256
                assert store.map_glb == want.glb
            finally:
                feed.stop()
        assert sumo.poll() is None, sumo.tail()
    finally:
        assert sumo.terminate() == 0, sumo.tail()
