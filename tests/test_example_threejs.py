"""``examples/threejs_replay``: a recording replayed through the gateway into a three.js page.

The renderer author's path end to end: ``sumoco replay`` (with the recorded glTF map) ->
``sumoco gateway`` -> the example page in headless Chromium loads the map's meshes, places
every agent and moves them (two screenshots differ).
"""

from __future__ import annotations

import functools
import json
import threading
import time
import urllib.parse
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from tests.harness import PAPER_CFG, ROOT, Daemon, endpoint, wait_until
from tests.recording_fixture import make_recording
from tests.test_viewer import browser  # noqa: F401  (the headless Chromium fixture)

pytestmark = pytest.mark.integration
AGENTS = 20


class _Quiet(SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


def _png(driver) -> np.ndarray:
    import io

    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"), dtype=np.int16)


def test_example_page_shows_the_map_and_moving_agents(tmp_path, browser):  # noqa: F811
    assert (ROOT / "node_modules" / "three" / "build" / "three.module.js").is_file(), \
        "three.js is missing: run `make install` (npm ci)"
    from sumo_side.mapmesh import MapService

    svc = MapService(PAPER_CFG.parent / "paper.net.xml", "synth")
    assert svc.wait(60.0), svc.error
    rec = tmp_path / "run.mcap"
    make_recording(rec, steps=30, agents=AGENTS, map_reply=svc.reply(""))
    ep = endpoint()
    replay = Daemon("replay", ["replay", str(rec), "--loop", "--listen", ep, "--quiet"], tmp_path)
    gw = Daemon("gateway", ["gateway", "--run", "synth", "--connect", ep, "--listen", endpoint(), "--port", "0"],
                tmp_path)
    http = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet, directory=str(ROOT)))
    threading.Thread(target=http.serve_forever, daemon=True).start()
    try:
        line = wait_until(lambda: next((ln for ln in gw.tail(50).splitlines() if ln.startswith('{"url"')), None),
                          20.0, "the gateway's URL", procs=[gw, replay])
        url = json.loads(line)["url"]
        page = (f"http://127.0.0.1:{http.server_address[1]}/examples/threejs_replay/index.html?gw="
                + urllib.parse.quote(url, safe=""))
        browser.get(page)
        try:
            st = wait_until(lambda: browser.execute_script(
                "const s = window.sumocoExample; return s && s.mapMeshes > 0 && s.agents > 0 && s;"),
                30.0, "the map and the agents in the page", procs=[gw, replay])
        except AssertionError as e:  # say what the page had got so far
            raise AssertionError(f"{e}; page state: {browser.execute_script('return window.sumocoExample')}; "
                                 f"gateway log: {gw.tail(20)}") from None
        assert st["error"] == "" and st["mapMeshes"] >= 3 and st["agents"] == AGENTS
        count = browser.execute_script("return window.sumocoExample.agents")
        assert count == AGENTS
        a = _png(browser)
        time.sleep(1.0)
        b = _png(browser)
        changed = np.abs(a - b).sum(axis=2) > 30
        assert changed.mean() > 1e-4, "nothing moved between two screenshots"
        assert (a.std(axis=(0, 1)) > 5).any()  # not a blank canvas
        browser.save_screenshot(str(tmp_path / "example.png"))
    finally:
        http.shutdown()
        codes = gw.terminate(5), replay.terminate(5)
    assert codes == (0, 0), gw.tail() + replay.tail()
