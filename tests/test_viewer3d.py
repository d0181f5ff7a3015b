"""The 3D page in a real headless Chromium (WebGL through SwiftShader): map meshes from the
GLB, N agents as instances, traffic-light heads, no console error, pixels that change where
a car is, click-to-follow, draw calls that do not grow with the number of agents, and, read
from the scene graph's instance matrices and colours, bodies' roll and pitch, steered and
spinning wheels, leaning bicycles, walking legs and signal heads in their state.

Runs against a real ``sumoco view`` subprocess fed by a synthetic run over loopback Zenoh
(``tests/test_viewer.py``'s ``LiveRun``); never skips in CI (the ``browser`` fixture fails).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time

import numpy as np
import zenoh

from protocol.codec import decode
from protocol.keys import Keys
from protocol.messages import CameraPose
from synthetic.feed import FakePublisher
from synthetic.traffic import FakeRun
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
    # The browser is shared: the last test's page (its server gone) must not log into this one.
    driver.get("about:blank")
    driver.get_log("browser")
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
        size = browser.execute_script("const c = document.querySelector('#view3d canvas'); return [c.clientWidth, c.clientHeight];")

        def held_capture():
            # Held, so that the agents' screen positions are those of the frame captured: a
            # moving car can leave the square between a render and the capture (once: 16.7 < 20).
            browser.execute_script("window.sumoco3d.pause(true);")
            _next_render(browser, _stats(browser)["renders"])
            c = browser.execute_script(_CAPTURE)
            if c is None:  # nobody in view in this frame: let them move on
                browser.execute_script("window.sumoco3d.pause(false);")
            return c

        with_agents = wait_for(held_capture, 10.0, "an agent in view", 0.2)
        browser.execute_script("window.sumoco3d.setAgentsVisible(false);")
        _next_render(browser, _stats(browser)["renders"])
        without = browser.execute_script(_CAPTURE, with_agents["at"], with_agents["ground"])
        browser.execute_script("window.sumoco3d.setAgentsVisible(true);")
        browser.execute_script("window.sumoco3d.pause(false);")

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


# --------------------------------------------------------------------------- poses in the scene graph

# The scene graph without a hook in the page: three.js announces every Scene it builds to
# window.__THREE_DEVTOOLS__ (its devtools protocol) when that object exists before it loads.
_DEVTOOLS_HOOK = """
window.__THREE_DEVTOOLS__ = new EventTarget();
window.__THREE_DEVTOOLS__.addEventListener('observe', (e) => {
  if (e.detail && e.detail.isScene) (window.__sumocoTestScenes = window.__sumocoTestScenes || []).push(e.detail);
});
"""

# One animation frame's instances (every array written by the same update()): matrices of the
# named instanced meshes, and the signal lamps' colours with the map's head nodes (tls, link, matrix).
_SCENE = """
const sc = (window.__sumocoTestScenes || []).find((x) => x.getObjectByName('wheels'));
if (!sc) return null;
const s = window.sumoco3d;
const out = {renders: s.renders, step: s.step, instance: s.instance, mats: {}, lampRgb: [], heads: []};
for (const name of arguments[0]) {
  const m = sc.getObjectByName(name);
  out.mats[name] = m ? Array.from(m.instanceMatrix.array.subarray(0, m.count * 16)) : null;
}
const lamps = sc.getObjectByName('tls_lamps');
if (lamps) {
  const c = new sc.background.constructor();  // a THREE.Color: getHex() gives sRGB, as the page set it
  for (let k = 0; k < lamps.count; k++) { lamps.getColorAt(k, c); out.lampRgb.push(c.getHex()); }
}
sc.traverse((o) => {
  const x = o.userData || {};
  if (typeof x.tls === 'string' && Number.isInteger(x.link)) out.heads.push([x.tls, x.link, Array.from(o.matrixWorld.elements)]);
});
return out;
"""

_MODEL = {0: "car", 1: "car", 2: "bus", 3: "bicycle", 4: "pedestrian", 5: "car"}
_WHEEL_R = {0: 0.32, 1: 0.32, 2: 0.5, 3: 0.34, 5: 0.45}  # [m] the page's wheel radii
_ROLLS, _PITCHES, _STEERS = (0.0, 7.0, -5.0, 12.0), (0.0, -4.0, 6.0), (0.0, 18.0, -12.0, 25.0)  # [deg], by rank
_TLS_A, _TLS_B, _TLS_STEPS = "rGyrGyrG", "GyrGyrGy", 30  # every head changes letter between the two
_TLS_HEX = {"r": 0xFF1A1A, "y": 0xFFB300, "G": 0x00FF66}  # SUMO's letters as the page colours them


class _PosedRun(FakeRun):
    """The synthetic run with known attitudes: per model class, agent k (in order) has roll
    _ROLLS[k % 4], pitch _PITCHES[k % 3], steering _STEERS[k % 4] (SPEC 2: roll + = right side
    down, pitch + = nose up, steer + = left) and its track's heading; every third stands still
    (speed 0), the others move slowly enough (0.4 m/s; walkers 1.3 m/s) that the wheel turns less
    than half a revolution between two looks. Signal heads: _TLS_A and _TLS_B alternate every
    _TLS_STEPS steps."""

    def __init__(self, **kw) -> None:
        super().__init__(**kw)
        rank = np.zeros(self.n, int)
        seen: dict[str, int] = {}
        for i, c in enumerate(self.cls):
            m = _MODEL[int(c)]
            rank[i] = seen.get(m, 0)
            seen[m] = rank[i] + 1
        self.rank = rank
        # SUMO's angle [deg] of each agent: its track is straight, so the heading is constant
        self.heading = super().step(0).agents.angle.astype(np.float32)
        self.roll = np.array(_ROLLS, np.float32)[rank % 4]
        self.pitch = np.array(_PITCHES, np.float32)[rank % 3]
        self.steer = np.array(_STEERS, np.float32)[rank % 4]
        self.pspeed = np.where(rank % 3 == 0, 0.0, np.where(self.cls == 4, 1.3, 0.4)).astype(np.float32)

    def tls_letters(self, k: int) -> str:
        return _TLS_A if (k // _TLS_STEPS) % 2 == 0 else _TLS_B

    def step(self, k: int):
        m = super().step(k)
        return dataclasses.replace(m, tls=dataclasses.replace(m.tls, state=[self.tls_letters(k)] * len(m.tls.ids)))

    def physics(self, tick: int, t: float, sumo_step: int, gain: float = 1.0):
        m = super().physics(tick, t, sumo_step, gain)
        a = dataclasses.replace(m.agents, roll=self.roll, pitch=self.pitch, steer=self.steer, speed=self.pspeed,
                                heading=self.heading)
        return dataclasses.replace(m, agents=a)


def _mats(flat) -> np.ndarray:
    """three.js instance matrices (column-major, 16 floats each) -> (n, 4, 4) row-major."""
    return np.asarray(flat, float).reshape(-1, 4, 4).transpose(0, 2, 1)


def _rot(m: np.ndarray) -> np.ndarray:
    """The rotation of a rotate-then-scale matrix: its 3 x 3 block with unit columns."""
    r = m[:3, :3]
    return r / np.linalg.norm(r, axis=0)


def _attitude(m: np.ndarray) -> tuple[float, float, float]:
    """Roll (+ = right side down), pitch (+ = nose up), heading (deg cw from north) of a body
    instance; page frame: X east, Y up, Z south, bodies face -Z, their right is +X."""
    r = _rot(m)
    right, up, fwd = r[:, 0], r[:, 1], -r[:, 2]
    return (math.degrees(math.atan2(-right[1], up[1])), math.degrees(math.asin(np.clip(fwd[1], -1, 1))),
            math.degrees(math.atan2(fwd[0], -fwd[2])) % 360.0)


def _wheel(body: np.ndarray, wheel: np.ndarray) -> tuple[float, float]:
    """A wheel in its body's frame: (steering [deg, + = pointing left], spin [rad, growing as
    it rolls forward: the spoke that was on top turns towards the front])."""
    rel = _rot(body).T @ _rot(wheel)
    fwd = np.cross([0.0, 1.0, 0.0], rel[:, 0])  # rolling direction: perpendicular to the axle
    steer = math.degrees(math.atan2(-fwd[0], -fwd[2]))
    spoke = rel[:, 1]
    return steer, math.atan2(float(spoke @ fwd), float(spoke[1]))


def _leg(body: np.ndarray, leg: np.ndarray) -> float:
    """How far a leg swings forward of straight down in its body's frame [rad]."""
    foot = -(_rot(body).T @ _rot(leg))[:, 1]
    return math.atan2(-foot[2], -foot[1])


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _wrap_deg(a):
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def _look(driver, after: int | None = None) -> dict:
    """The scene of a frame rendered after frame ``after`` (or now)."""
    if after is not None:
        _next_render(driver, after)
    return driver.execute_script(_SCENE, ["car", "bus", "bicycle", "pedestrian", "wheels", "legs", "tls_lamps"])


def _held(driver) -> dict:
    """Pause the page and return its scene with the step it holds: ``stats.step`` is refreshed
    at most every 250 ms, so wait for a frame drawn more than 300 ms after the pause."""
    t0 = driver.execute_script("window.sumoco3d.pause(true); return performance.now();")
    wait_for(lambda: driver.execute_script("return performance.now();") > t0 + 300, 5.0, "300 ms of page time", 0.05)
    return _look(driver, _stats(driver)["renders"])


def test_3d_page_shows_attitude_steering_wheel_spin_lean_walking_and_signal_states(browser, tmp_path):  # noqa: F811
    """Reads the page's scene graph (instance matrices and colours) against physics states
    with known roll, pitch, steering and speed: bodies carry their roll and pitch, front wheels
    their steering angle (left positive, zero when straight), wheels spin forward in proportion
    to speed / radius and not at all when standing, bicycles lean, walkers' legs swing in
    opposition and a standing walker's hang still, and each signal head takes the colour of its
    link's letter in the held step, changing with it."""
    n = 60
    fake = _PosedRun(grid=1, n=n, run="viewer-3d-poses")
    models = [_MODEL[int(c)] for c in fake.cls]
    assert all(models.count(m) >= 3 for m in ("car", "bus", "bicycle", "pedestrian"))
    browser.get("about:blank")  # an earlier test's page, reconnecting to its closed viewer, logs errors
    browser.get_log("browser")
    hook = browser.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": _DEVTOOLS_HOOK})
    live = LiveRun(tmp_path, fake)
    try:
        live.wait_ready()
        _open_3d(browser, live, n)
        looks = [_look(browser)]
        assert looks[0] is not None, "no three.js scene announced to the devtools hook"
        for _ in range(4):
            looks.append(_look(browser, looks[-1]["renders"]))

        def bodies(look) -> list[np.ndarray]:
            """Body matrix of agent i (instances per model, in the physics message's order)."""
            per = {m: _mats(look["mats"][m]) for m in ("car", "bus", "bicycle", "pedestrian")}
            return [per[models[i]][fake.rank[i]] for i in range(n)]

        def wheels_of(look) -> list[list[np.ndarray]]:
            w, out, k = _mats(look["mats"]["wheels"]), [], 0
            for i in range(n):
                c = 0 if models[i] == "pedestrian" else 2 if models[i] == "bicycle" else 4
                out.append(list(w[k:k + c]))
                k += c
            assert k == len(w), (k, len(w))
            return out

        # Roll and pitch (and heading) of every body, bicycles' lean among them.
        b0 = bodies(looks[0])
        got = np.array([_attitude(b) for b in b0])
        heading = fake.heading
        assert np.abs(got[:, 0] - fake.roll).max() < 0.05, list(zip(models, got[:, 0], fake.roll))
        assert np.abs(got[:, 1] - fake.pitch).max() < 0.05, list(zip(models, got[:, 1], fake.pitch))
        assert np.abs(_wrap_deg(got[:, 2] - heading)).max() < 0.05
        bikes = np.array(models) == "bicycle"
        assert (np.abs(got[bikes, 0]) > 4).sum() >= 2 and (fake.roll[bikes] == 0).any()  # leaning and upright

        # Steering: front wheels follow the angle and its sign (left +), rear ones never steer.
        w0 = wheels_of(looks[0])
        for i in range(n):
            if not w0[i]:
                continue
            st = [_wheel(b0[i], w)[0] for w in w0[i]]
            front = st[:2] if len(st) == 4 else st[:1]
            rear = st[2:] if len(st) == 4 else st[1:]
            assert all(abs(s - fake.steer[i]) < 0.05 for s in front), (fake.ids[i], fake.steer[i], st)
            assert all(abs(s) < 0.05 for s in rear), (fake.ids[i], st)
        assert {float(np.sign(s)) for s in fake.steer[np.array(models) != "pedestrian"]} == {-1.0, 0.0, 1.0}

        # Spin: between two frames every moving wheel turns forward by speed * dt / radius (the
        # same dt for all), a standing one not at all.
        rolled = []
        for a, b in zip(looks, looks[1:]):
            wa, wb, ba, bb = wheels_of(a), wheels_of(b), bodies(a), bodies(b)
            for i in range(n):
                for x, y in zip(wa[i], wb[i]):
                    d = _wrap(_wheel(bb[i], y)[1] - _wheel(ba[i], x)[1])
                    if fake.pspeed[i] == 0:
                        assert abs(d) < 1e-3, (fake.ids[i], d)
                    else:
                        rolled.append((a["renders"], d * _WHEEL_R[int(fake.cls[i])] / fake.pspeed[i]))
        dts = {}
        for r, dt in rolled:
            dts.setdefault(r, []).append(dt)
        for r, v in dts.items():  # per pair of looks: one dt [s] for every moving wheel
            assert min(v) > 0 and max(v) - min(v) < 1e-3, (r, min(v), max(v))
        assert len(dts) == len(looks) - 1

        # Walking: legs swing in opposition while the walker moves, hang straight when it stands.
        peds = [i for i in range(n) if models[i] == "pedestrian"]
        swings = {i: [] for i in peds}
        for look in looks:
            legs, bs = _mats(look["mats"]["legs"]), bodies(look)
            assert len(legs) == 2 * len(peds)
            for j, i in enumerate(peds):
                left, right = _leg(bs[i], legs[2 * j]), _leg(bs[i], legs[2 * j + 1])
                assert abs(left + right) < 1e-3 and abs(right) <= 1.3 * 0.35 + 1e-3, (fake.ids[i], left, right)
                swings[i].append(right)
        for i in peds:
            if fake.pspeed[i] == 0:
                assert max(map(abs, swings[i])) < 1e-3, (fake.ids[i], swings[i])
            else:
                assert max(swings[i]) - min(swings[i]) > 0.02, (fake.ids[i], swings[i])

        # Signal heads: each lamp sits on a head of the map and has its link's letter's colour.
        seen = set()

        def heads_match(look) -> str:
            letters = fake.tls_letters(look["step"])
            lamps = _mats(look["mats"]["tls_lamps"])[:, :3, 3]
            heads = [(tls, link, _mats(m)[0] @ np.array([0.0, 0.0, 0.2, 1.0])) for tls, link, m in look["heads"]]
            assert len(lamps) == len(look["lampRgb"]) == len(heads) == 8
            for p, rgb in zip(lamps, look["lampRgb"]):
                tls, link, _ = min(heads, key=lambda h: np.linalg.norm(h[2][:3] - p))
                assert tls == "J0_0" and min(np.linalg.norm(h[2][:3] - p) for h in heads) < 1e-3
                want = _TLS_HEX[letters[link]]
                assert all(abs((rgb >> s & 255) - (want >> s & 255)) <= 2 for s in (0, 8, 16)), (
                    look["step"], link, letters, hex(rgb), hex(want))
            return letters

        held_steps: list[int] = []

        def both_states():
            look = _held(browser)
            browser.execute_script("window.sumoco3d.pause(false);")
            held_steps.append(look["step"])
            seen.add(heads_match(look))
            return seen == {_TLS_A, _TLS_B}

        try:
            wait_for(both_states, 60.0, "the signal heads in both states", 0.5)
        except AssertionError:
            print("held steps:", held_steps, "\npage:", json.dumps(_stats(browser))[:2000], "\nviewer log:\n", live.log())
            raise
        assert _stats(browser)["errors"] == 0 and _console_errors(browser) == []
    finally:
        browser.execute_cdp_cmd("Page.removeScriptToEvaluateOnNewDocument", {"identifier": hook["identifier"]})
        browser.get("about:blank")
        live.close()


def test_vendored_three_is_the_pinned_npm_package_with_its_licence():
    """The page ships three.js (no CDN at run time): byte-equal to the version package-lock.json pins."""
    import os
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    vendor = root / "sumoco" / "viewing" / "viewer" / "static" / "vendor" / "three"
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
