"""The 3D page in a real headless Chromium (WebGL through SwiftShader): map meshes from the
GLB, N agents as instances, traffic-light heads, no console error, pixels that change where
a car is, click-to-follow, and draw calls that do not grow with the number of agents.

Runs against a real ``sumoco view`` subprocess fed by a synthetic run over loopback Zenoh
(``tests/test_viewer.py``'s ``LiveRun``); never skips in CI (the ``browser`` fixture fails).
"""

from __future__ import annotations

import json
import time

import zenoh

from protocol.codec import decode
from protocol.keys import Keys
from protocol.messages import CameraPose
from sumoco.testing.feed import FakePublisher
from sumoco.testing.synthetic import FakeRun
from tests.test_viewer import LiveRun, browser, wait_for  # noqa: F401  (browser is a fixture)

_STATS = ("const s = window.sumoco3d; if (!s) return null; const o = {};"
          "for (const k in s) if (typeof s[k] !== 'function') o[k] = s[k]; return o;")

# Squares of the canvas: around an agent on screen (the longest one, away from the HUD and the
# edges; or around a given point) and on the corner farthest from every agent.
_CAPTURE = """
const s = window.sumoco3d, c = document.querySelector('#view3d canvas');
const w = c.width, h = c.height, k = w / c.clientWidth, W = c.clientWidth, H = c.clientHeight;
const t = document.createElement('canvas'); t.width = w; t.height = h;
const g = t.getContext('2d'); g.drawImage(c, 0, 0);
const box = (p, r) => Array.from(g.getImageData(Math.round(p[0] * k - r), Math.round(p[1] * k - r), 2 * r, 2 * r).data);
const on = s.onScreen();
let at = arguments[0], ground = arguments[1];
if (!at) {
  const ok = on.filter((a) => a.p[0] > 380 && a.p[0] < W - 40 && a.p[1] > 40 && a.p[1] < H - 40);
  if (!ok.length) return null;
  const d = (a) => Math.hypot(a.p[0] - W / 2, a.p[1] - H / 2);  // nearest the centre: big on screen
  ok.sort((a, b) => (a.len < 4) - (b.len < 4) || d(a) - d(b));
  at = ok[0].p;
}
if (!ground) {
  const corners = [[W - 20, H - 20], [20, H - 20], [W - 20, 20]];
  const far = (q) => Math.min(...on.map((a) => Math.hypot(a.p[0] - q[0], a.p[1] - q[1])), 1e9);
  ground = corners.sort((a, b) => far(b) - far(a))[0];
}
return {at, ground, car: box(at, 6), grd: box(ground, 8)};
"""


def _stats(driver) -> dict:
    return driver.execute_script(_STATS)


def _console_errors(driver) -> list[str]:
    return [e["message"] for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def _open_3d(driver, live: LiveRun, n: int, timeout: float = 40.0) -> dict:
    driver.get(live.url3d)

    def ready():
        s = _stats(driver)
        if s and s["errors"]:
            raise AssertionError(f"page error: {s['lastError']}")
        ok = s and s["mapLoaded"] and s["agents"] == n and s["physicsAgents"] == n and s["renders"] > 3
        return s if ok else None

    try:
        return wait_for(ready, timeout, "the 3D page to load the map and draw the agents", 0.3)
    except AssertionError:
        print("page:", json.dumps(_stats(driver))[:2000], "\nconsole:", driver.get_log("browser"),
              "\nviewer log:\n", live.log())
        raise


def _next_render(driver, after: int, timeout: float = 20.0) -> None:
    wait_for(lambda: _stats(driver)["renders"] > after + 1, timeout, "the page to render again", 0.05)


def test_3d_page_shows_map_agents_and_signal_heads(browser, tmp_path):  # noqa: F811
    from selenium.webdriver.common.action_chains import ActionChains

    live = LiveRun(tmp_path, FakeRun(grid=1, n=50, run="viewer-3d"))
    keys = Keys("sumoco", "viewer-3d")
    cams: list = []
    tokens: dict[str, bool] = {}
    live.session.declare_subscriber(keys.viewer_camera_all, lambda x: cams.append(decode(x.payload.to_bytes())))
    live.session.liveliness().declare_subscriber(
        keys.viewer_alive_all, lambda x: tokens.__setitem__(str(x.key_expr), x.kind == zenoh.SampleKind.PUT),
        history=True)
    try:
        live.wait_ready()
        s = _open_3d(browser, live, 50)
        summary = browser.execute_script("return window.sumoco3d.sceneSummary();")
        # The map: ground + every layer of the GLB (junctions, lanes, sidewalks, markings) + 8 heads.
        assert summary["meshes"] >= 5 + 8, summary
        assert s["tlsHeads"] == 8 and summary["instanced"]["tls_lamps"] == 8 == summary["instanced"]["tls_housings"]
        inst = summary["instanced"]
        assert inst["car"] + inst["bus"] + inst["bicycle"] + inst["pedestrian"] == 50, inst
        assert inst["pedestrian"] >= 1 and inst["legs"] == 2 * inst["pedestrian"]
        assert inst["wheels"] == 4 * (inst["car"] + inst["bus"]) + 2 * inst["bicycle"]
        assert inst["lamps"] == 4 * (inst["car"] + inst["bus"])
        assert s["ghosts"] == 50 and s["instance"] == "default"
        # Brake lights and blinkers follow the step's signal bits (vehicles with lamps: not bikes).
        browser.execute_script("window.sumoco3d.pause(true);")
        _next_render(browser, _stats(browser)["renders"])
        held = _stats(browser)
        browser.execute_script("window.sumoco3d.pause(false);")
        sig = live.fake.signals(held["step"])
        lamps = (live.fake.cls != 3) & (live.fake.cls != 4)
        want = {"brake": int(((sig & 8) > 0)[lamps].sum()), "left": int(((sig & 6) > 0)[lamps].sum()),
                "right": int(((sig & 5) > 0)[lamps].sum())}
        assert held["signalled"] == want and want["brake"] > 0 and want["left"] > 0, (held["signalled"], want)
        assert live.status()["map_source"] == "static"  # the synthetic feed serves no GLB: built from static data

        # Pixels: close to a car, the square around it changes when the agents are hidden;
        # a square of plain ground far from every agent does not.
        browser.execute_script("window.sumoco3d.lookAt(0, 0, 70);")
        _next_render(browser, _stats(browser)["renders"])
        # The page's camera reaches Zenoh as a level-of-detail interest point (SPEC 3.7):
        # the point it looks at, in SUMO coordinates, with a liveliness token of its own.
        browser.execute_script("window.sumoco3d.lookAt(31, -12, 70);")
        cam = wait_for(lambda: next((c for c in reversed(cams) if abs(c.x - 31) < 0.01), None), 10.0,
                       "the page's camera on Zenoh", 0.1)
        assert isinstance(cam, CameraPose) and abs(cam.y + 12) < 0.01 and cam.id.startswith("page-")
        assert tokens.get(f"{keys.base}/viewer/viewer/{cam.id}/alive") is True
        browser.execute_script("window.sumoco3d.lookAt(0, 0, 70);")
        _next_render(browser, _stats(browser)["renders"])
        size = browser.execute_script("const c = document.querySelector('#view3d canvas'); return [c.clientWidth, c.clientHeight];")
        with_agents = wait_for(lambda: browser.execute_script(_CAPTURE), 10.0, "an agent in view", 0.2)
        browser.execute_script("window.sumoco3d.setAgentsVisible(false);")
        _next_render(browser, _stats(browser)["renders"])
        without = browser.execute_script(_CAPTURE, with_agents["at"], with_agents["ground"])
        browser.execute_script("window.sumoco3d.setAgentsVisible(true);")

        def diff(a, b):
            return sum(abs(x - y) for i, (x, y) in enumerate(zip(a, b)) if i % 4 != 3) / (len(a) * 3 / 4)

        d_car, d_ground = diff(with_agents["car"], without["car"]), diff(with_agents["grd"], without["grd"])
        print(f"pixel difference where the car is: {d_car:.1f}, on empty ground: {d_ground:.1f}")
        assert d_car > 20, (d_car, with_agents["at"])
        assert d_ground < 2, d_ground

        # Click an agent: the camera follows it.
        canvas = browser.find_element("css selector", "#view3d canvas")

        def clicked():
            browser.execute_script("window.sumoco3d.pause(true);")  # agents hold still under the pointer
            _next_render(browser, _stats(browser)["renders"])
            on = browser.execute_script("return window.sumoco3d.onScreen();")
            ok = [a for a in on if 380 < a["p"][0] < size[0] - 40 and 40 < a["p"][1] < size[1] - 40]
            if not ok:
                return None
            p = max(ok, key=lambda a: a["len"])["p"]
            ActionChains(browser).move_to_element_with_offset(
                canvas, int(p[0] - size[0] / 2), int(p[1] - size[1] / 2)).click().perform()
            time.sleep(0.2)
            st = _stats(browser)
            tries.append((p, st.get("clicks"), st.get("lastPick")))
            browser.execute_script("window.sumoco3d.pause(false);")
            return st["follow"]

        tries: list = []
        try:
            followed = wait_for(clicked, 30.0, "a click on an agent to start following it", 0.2)
        except AssertionError:
            print("clicks:", tries)
            raise
        assert followed, followed
        hud = browser.find_element("id", "hud").text
        assert "following" in hud and "agents" in hud and "real-time factor" in hud and "fps" in hud, hud
        assert _console_errors(browser) == []
        assert _stats(browser)["errors"] == 0
        # The page goes: so does its camera's token.
        browser.get("about:blank")
        wait_for(lambda: tokens.get(f"{keys.base}/viewer/viewer/{cam.id}/alive") is False, 10.0,
                 "the closed page's camera token gone", 0.1)
    finally:
        live.close()


def test_3d_page_draw_calls_do_not_grow_with_the_agents(browser, tmp_path):  # noqa: F811
    """Instanced meshes, one draw call per model class: the same page on the same map (5 x 5
    junctions, 200 signal heads) draws 50 agents, then 2,500 (the run's feed is swapped under
    the open page), with the same number of draw calls. Frames per second are measured by
    ``sumoco bench viewer``, not here (no wall-clock assertions)."""
    small, big = 50, 2500
    live = LiveRun(tmp_path, FakeRun(grid=5, n=small, run="viewer-3d-2500"), physics_hz=10.0)
    size = browser.get_window_size()
    browser.set_window_size(640, 480)  # fewer pixels for SwiftShader to fill; draw calls do not care
    try:
        live.wait_ready(timeout=40.0)
        _open_3d(browser, live, small, timeout=60.0)
        browser.execute_script("window.sumoco3d.fit();")  # the whole map: every agent on screen
        _next_render(browser, _stats(browser)["renders"])
        s_small = _stats(browser)
        summary = browser.execute_script("return window.sumoco3d.sceneSummary();")
        inst = s_small["instances"]
        assert all(inst[k] > 0 for k in ("car", "bus", "bicycle", "pedestrian")), inst  # every model class drawn
        assert s_small["tlsHeads"] == 200
        # Each draw call is one mesh of the scene (map layers, instanced models, ghost outlines):
        # none is per agent.
        meshes = summary["meshes"] + len(summary["instanced"]) + 1
        assert s_small["drawCalls"] <= meshes, (s_small["drawCalls"], summary)

        # The same run id with 50 times the agents: the page keeps its map and grows its instances.
        live.pub.stop()
        live.fake = FakeRun(grid=5, n=big, run="viewer-3d-2500")
        live.pub = FakePublisher(live.session, live.fake, step_hz=10.0, physics_hz=5.0).start()

        def grown():
            s = _stats(browser)
            if s["errors"]:
                raise AssertionError(f"page error: {s['lastError']}")
            return s if s["agents"] == big and s["physicsAgents"] == big else None

        # Stats of one animation frame: its update (every agent's instances) and its render.
        s = wait_for(grown, 90.0, f"the page to draw {big} agents", 0.5)
        inst = s["instances"]
        print(f"{small} -> {big} agents: {s_small['drawCalls']} -> {s['drawCalls']} draw calls, "
              f"{s_small['triangles']} -> {s['triangles']} triangles ({s['glRenderer']}); {inst}")
        assert inst["car"] + inst["bus"] + inst["bicycle"] + inst["pedestrian"] == big, inst
        assert inst["wheels"] == 4 * (inst["car"] + inst["bus"]) + 2 * inst["bicycle"]
        assert s["triangles"] > s_small["triangles"]  # more triangles, not more draw calls
        assert s["drawCalls"] <= s_small["drawCalls"] + 2, (s_small["drawCalls"], s["drawCalls"])
        assert s["mapLoaded"] and s["tlsHeads"] == 200
        assert s["glRenderer"]  # the page names its GL implementation (benchmarks record it)
        assert s["errors"] == 0 and _console_errors(browser) == []
    finally:
        browser.set_window_size(size["width"], size["height"])
        live.close()


def test_vendored_three_is_the_pinned_npm_package_with_its_licence():
    """The page ships three.js (no CDN at run time): byte-equal to the version package-lock.json pins."""
    import os
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    vendor = root / "sumoco" / "app" / "viewer" / "static" / "vendor" / "three"
    lock = json.loads((root / "package-lock.json").read_text())
    pinned = lock["packages"]["node_modules/three"]["version"]
    assert json.loads((root / "package.json").read_text())["dependencies"]["three"] == pinned
    assert "MIT License" in (vendor / "LICENSE").read_text()
    npm = root / "node_modules" / "three"
    if not npm.is_dir():
        assert os.environ.get("CI", "").lower() not in ("1", "true", "yes"), "make install runs npm ci"
        return
    assert json.loads((npm / "package.json").read_text())["version"] == pinned
    files = [p.relative_to(vendor) for p in vendor.rglob("*") if p.is_file()]
    assert len(files) >= 7
    for rel in files:
        assert (vendor / rel).read_bytes() == (npm / rel).read_bytes(), rel
