"""``sumoco bench viewer --json``: frames per second of the 3D page in headless Chromium.

For each agent count: a synthetic run (``FakeRun`` on a 5 x 5 junction grid, the same map at
every count) published over loopback Zenoh from this process (``FakePublisher``: steps at
10 Hz, two physics instances at 20 Hz), ``sumoco view`` as a subprocess, and its 3D page in
headless Chromium (Selenium with the system's chromium and chromedriver; WebGL through
SwiftShader, as in the browser tests). Once the page has the map and every agent, the
camera fits the whole map (every agent on screen) and, after a second to settle, the page's
own counters (``window.sumoco3d``) are read over ``seconds`` of wall time:

- ``fps``: frames the page rendered per second (its requestAnimationFrame loop counts every
  ``renderer.render``); ``frame_ms_p50/p95/max``: intervals between animation frames;
- ``draw_calls``, ``triangles``: ``renderer.info.render`` of a frame (min and max over the
  samples); one instanced mesh per model class, so draw calls do not grow with the agents;
- ``agents_drawn``: body instances (car + bus + bicycle + pedestrian), ``instances`` per mesh;
- ``frames_received_hz``: WebSocket frames the page got from the server (at most the
  viewer's ``max_hz``; ``frame_kib`` each: a step and two physics states),
  ``frames_applied_hz``: those the page applied to the scene;
- ``decode_ms``, ``update_ms``, ``render_ms``: mean CPU time of the page's main thread per
  frame: decoding a received frame (step + every physics instance), the per-frame update
  (the instance matrices) and ``renderer.render`` (submitting; SwiftShader rasterises in
  the GPU process);
- ``gl_renderer``: ``UNMASKED_RENDERER_WEBGL``: "SwiftShader" means software rendering on
  the CPU, so the fps say little about a browser with a GPU; ``browser_cores`` (CPU
  seconds of the browser's processes per wall second), ``loadavg_1min`` and ``cpus`` tell
  how much of the machine it got.

Needs selenium (the ``test`` extra) and chromium + chromedriver (``.ci/install-browser.sh``;
``SUMOCO_CHROMIUM`` / ``SUMOCO_CHROMEDRIVER`` point elsewhere).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from typing import Any, NamedTuple

import numpy as np

from protocol.codec import encode
from runtime.config import ZenohConfig
from runtime.errors import MissingExtraError, SumocoError
from runtime.transport import free_tcp_port, open_session
from synthetic.feed import FakePublisher
from synthetic.traffic import FakeRun

log = logging.getLogger(__name__)

GRID = 5  # junctions per side at every agent count: the same map, so draw calls compare
BODY_MESHES = ("car", "bus", "bicycle", "pedestrian")
WINDOW = (1280, 860)  # CSS pixels, device pixel ratio 1

# Every number in window.sumoco3d (functions and nested objects left out but `instances`).
_STATS = ("const s = window.sumoco3d; if (!s) return null; const o = {now: performance.now()};"
          "for (const k in s) if (typeof s[k] !== 'function') o[k] = s[k]; return o;")
# A second requestAnimationFrame loop that only records the frame timestamps (the page's
# own loop gets the same timestamp in the same frame).
_RAF_PROBE = ("window.__benchFrames = []; const f = (t) => { window.__benchFrames.push(t);"
              "if (window.__benchFrames.length < 100000) requestAnimationFrame(f); }; requestAnimationFrame(f);")


def _find(env: str, *names: str) -> str | None:
    if os.environ.get(env):
        return os.environ[env]
    for n in names:
        p = shutil.which(n) or (f"/usr/bin/{n}" if os.path.exists(f"/usr/bin/{n}") else None)
        if p:
            return p
    return None


def start_browser(profile: str) -> Any:
    """Headless Chromium with WebGL through SwiftShader (no GPU needed), the test's options."""
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError as e:
        raise MissingExtraError("bench viewer", "test", "selenium") from e
    chromium = _find("SUMOCO_CHROMIUM", "chromium", "chromium-browser", "google-chrome")
    driver_exe = _find("SUMOCO_CHROMEDRIVER", "chromedriver")
    if not chromium or not driver_exe:
        raise SumocoError("`sumoco bench viewer` needs chromium and chromedriver (.ci/install-browser.sh, or "
                          "SUMOCO_CHROMIUM and SUMOCO_CHROMEDRIVER)")
    os.environ.setdefault("SE_OFFLINE", "true")  # never let Selenium Manager download anything
    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
              "--disable-background-networking", "--disable-component-update", "--disable-sync",
              "--disable-dev-shm-usage", f"--user-data-dir={profile}", f"--window-size={WINDOW[0]},{WINDOW[1]}",
              "--force-device-scale-factor=1",
              "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"):
        opts.add_argument(a)
    driver = webdriver.Chrome(service=Service(driver_exe), options=opts)
    driver.set_page_load_timeout(30)
    driver.set_script_timeout(30)
    return driver


def _tree_cpu_s(root: int) -> float | None:
    """CPU seconds (user + system) of ``root``'s descendants so far (Linux ``/proc``; else None)."""
    try:
        tick = os.sysconf("SC_CLK_TCK")
        parent, cpu = {}, {}
        for d in os.listdir("/proc"):
            if not d.isdigit():
                continue
            try:
                with open(f"/proc/{d}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            parent[int(d)] = int(fields[1])
            cpu[int(d)] = (int(fields[11]) + int(fields[12])) / tick
        total, todo = 0.0, [root]
        while todo:
            pid = todo.pop()
            kids = [c for c, pp in parent.items() if pp == pid]
            total += sum(cpu[c] for c in kids)
            todo += kids
        return total
    except (OSError, ValueError, IndexError):
        return None


def _wait(cond, timeout: float, what: str, interval: float = 0.2):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(interval)
    raise SumocoError(f"bench viewer: timed out after {timeout:.0f} s waiting for {what}")


class _Viewer:
    """``sumoco view`` as a subprocess on a free port, connected to ``endpoint``."""

    def __init__(self, run: str, endpoint: str, log_path: str) -> None:
        self._log = open(log_path, "wb")
        self.log_path = log_path
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sumoco.cli", "view", "--run", run, "--connect", endpoint,
             "--port", "0", "--quiet"], stdout=subprocess.PIPE, stderr=self._log, text=True)
        line = self.proc.stdout.readline()  # "sumoco view: open http://127.0.0.1:PORT/?token=..."
        if "http" not in line:
            self.close()
            raise SumocoError(f"sumoco view did not start: {line!r} {self.log()[-2000:]}")
        self.url = line[line.index("http"):].strip()
        self.base, self.token = self.url.split("/?token=")

    def log(self) -> str:
        with open(self.log_path, errors="replace") as f:
            return f.read()

    def status(self) -> dict | None:
        try:
            with urllib.request.urlopen(f"{self.base}/status?token={self.token}", timeout=2.0) as r:
                return json.loads(r.read())
        except OSError:
            return None

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        self.proc.stdout.close()
        self._log.close()


class _Watch(NamedTuple):
    """What the page and the server said over one row's window."""

    first: dict  # the page's stats at the start of the window
    samples: list[dict]  # ... every 0.5 s after it (the last one ends the window)
    cpu_s: tuple[float | None, float | None]  # the browser's CPU time [s] at the start and the end
    stamps: np.ndarray  # the page's frame times [ms]
    server: dict  # sumoco view's /status at the end
    info: dict  # the browser's viewport and user agent


def _watch(driver: Any, viewer: _Viewer, agents: int, seconds: float, load_timeout: float) -> _Watch:
    """Load the page, wait until it draws every agent, then watch it for ``seconds``."""
    _wait(lambda: (st := viewer.status()) and st["static"] and st["steps_received"] > 0, 60.0,
          "sumoco view to have static data and steps")
    driver.get(viewer.url)

    def ready():
        s = driver.execute_script(_STATS)
        if s and s["errors"]:
            raise SumocoError(f"bench viewer: page error: {s['lastError']}")
        return s if (s and s["mapLoaded"] and s["agents"] == agents and s["physicsAgents"] == agents
                     and s["renders"] > 3) else None

    _wait(ready, load_timeout, f"the 3D page to load the map and draw {agents} agents")
    driver.execute_script("window.sumoco3d.fit();")  # the whole map: every agent on screen
    time.sleep(1.0)
    driver.execute_script(_RAF_PROBE)
    browser_pid = driver.service.process.pid  # chromedriver: chromium runs under it
    cpu0 = _tree_cpu_s(browser_pid)
    first = driver.execute_script(_STATS)
    samples = []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        time.sleep(min(0.5, max(0.0, t_end - time.monotonic())))
        samples.append(driver.execute_script(_STATS))
    cpu1 = _tree_cpu_s(browser_pid)
    stamps = np.asarray(driver.execute_script("return window.__benchFrames;"), float)
    server = viewer.status() or {}
    info = driver.execute_script(
        "return {dpr: window.devicePixelRatio, w: innerWidth, h: innerHeight, ua: navigator.userAgent};")
    return _Watch(first, samples, (cpu0, cpu1), stamps, server, info)


def measure(driver: Any, agents: int, seconds: float, tmp: str, load_timeout: float = 120.0) -> dict:
    """One row: the 3D page drawing ``agents`` agents, measured over ``seconds``."""
    fake = FakeRun(grid=GRID, n=agents, run=f"bench-viewer-{agents}")
    frame_bytes = len(encode(fake.step(10))) + 2 * len(encode(fake.physics(20, 1.0, 10)))  # step + 2 instances
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_session(ZenohConfig(listen=(ep,))) as session:
        pub = FakePublisher(session, fake, step_hz=10.0, physics_hz=20.0).start()
        viewer = _Viewer(fake.run, ep, os.path.join(tmp, f"view-{agents}.log"))
        try:
            w = _watch(driver, viewer, agents, seconds, load_timeout)
        finally:
            try:
                driver.get("about:blank")
            finally:
                viewer.close()
                pub.stop()
    return _row(agents, frame_bytes, w)


def _row(agents: int, frame_bytes: int, w: _Watch) -> dict:
    a, b, samples, stamps, server, info = w.first, w.samples[-1], w.samples, w.stamps, w.server, w.info
    cpu0, cpu1 = w.cpu_s
    dt = (b["now"] - a["now"]) / 1000.0
    gaps = np.diff(stamps[(stamps >= a["now"]) & (stamps <= b["now"])]) if len(stamps) > 1 else np.zeros(0)
    inst = b["instances"] or {}
    mean = lambda k: round(float(np.mean([s[k] for s in samples])), 2)  # noqa: E731
    return {
        "bench": "viewer",
        "agents": agents,
        "grid": f"{GRID}x{GRID}",
        "seconds": round(dt, 2),
        "fps": round((b["renders"] - a["renders"]) / dt, 2),
        "frame_ms_p50": round(float(np.percentile(gaps, 50)), 1) if len(gaps) else None,
        "frame_ms_p95": round(float(np.percentile(gaps, 95)), 1) if len(gaps) else None,
        "frame_ms_max": round(float(gaps.max()), 1) if len(gaps) else None,
        "draw_calls": b["drawCalls"],
        "draw_calls_min": min(s["drawCalls"] for s in samples),
        "draw_calls_max": max(s["drawCalls"] for s in samples),
        "triangles": b["triangles"],
        "agents_drawn": sum(int(inst.get(k, 0)) for k in BODY_MESHES),
        "agents_in_step": b["agents"],
        "instances": inst,
        "frame_kib": round(frame_bytes / 1024, 1),
        "frames_received_hz": round((b["framesReceived"] - a["framesReceived"]) / dt, 2),
        "frames_applied_hz": round((b["framesDrawn"] - a["framesDrawn"]) / dt, 2),
        "server_max_hz": (b.get("hello") or {}).get("max_hz"),
        "server_frames_dropped": server.get("frames_dropped"),
        "decode_ms": mean("decodeMs"),
        "update_ms": mean("updateMs"),
        "render_ms": mean("renderMs"),
        "page_errors": b["errors"],
        "gl_renderer": b.get("glRenderer", ""),
        "gl_vendor": b.get("glVendor", ""),
        "software_gl": "swiftshader" in str(b.get("glRenderer", "")).lower(),
        "browser": next((p for p in info["ua"].split() if p.startswith(("HeadlessChrome/", "Chrome/"))), info["ua"]),
        "viewport": f"{info['w']}x{info['h']}@{info['dpr']}",
        # Cores the browser got (its processes' CPU seconds per wall second): on a shared
        # machine fps scale with this more than with anything on the page.
        "browser_cores": round((cpu1 - cpu0) / dt, 2) if cpu0 is not None and cpu1 is not None else None,
        "cpus": os.cpu_count(),
        "loadavg_1min": round(os.getloadavg()[0], 2),
    }


def run_viewer_bench(agents: tuple[int, ...] | None = None, seconds: float | None = None,
                     quick: bool = False) -> list[dict]:
    agents = agents or ((500,) if quick else (500, 1000, 2500))
    seconds = seconds or (3.0 if quick else 10.0)
    rows = []
    with tempfile.TemporaryDirectory(prefix="sumoco-bench-viewer-") as tmp:
        profile = os.path.join(tmp, "chromium")
        driver = start_browser(profile)
        try:
            for n in agents:
                rows.append(measure(driver, n, seconds, tmp))
                log.info("viewer bench: %s", rows[-1])
        finally:
            driver.quit()
    return rows
