"""Screenshots of the 3D view for the docs: a real run (SUMO side, physics side, ``sumoco view``
as OS processes on loopback) drawn by headless Chromium.

    .venv/bin/python docs/screenshots.py                      # the bundled demo -> docs/view3d_demo.png
    .venv/bin/python docs/screenshots.py --sumocfg X.sumocfg --out docs/view3d_x.png --at X,Y --dist 120

``--at`` points the camera at a place in SUMO's frame (default: the whole map); ``--wait``
is the simulated time to let pass first [s].
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "docs-screenshot-token-0123456789"


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sumocfg", default=str(ROOT / "configs" / "scenarios" / "paper" / "paper.sumocfg"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "view3d_demo.png"))
    ap.add_argument("--at", help="camera target x,y [m, SUMO frame]")
    ap.add_argument("--dist", type=float, default=90.0, help="camera distance [m]")
    ap.add_argument("--wait", type=float, default=25.0, help="simulated seconds before the shot")
    ap.add_argument("--follow", help="follow this agent id (camera behind it)")
    a = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="sumoco-shot-"))
    zport, vport = free_port(), free_port()
    ep = f"tcp/127.0.0.1:{zport}"
    cfg = work / "shot.toml"
    cfg.write_text(f'[run]\nid = "shot"\ntiming = "realtime"\nduration_s = 600.0\n\n'
                   f'[viewer]\nport = {vport}\ntoken = "{TOKEN}"\n')
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cli = [sys.executable, "-m", "sumoco.cli"]
    logs = [open(work / f"{n}.log", "wb") for n in ("sumo", "physics", "view")]
    procs = [
        subprocess.Popen([*cli, "sumo", "--config", str(cfg), "--sumocfg", a.sumocfg, "--listen", ep],
                         stdout=logs[0], stderr=subprocess.STDOUT, env=env, cwd=ROOT),
        subprocess.Popen([*cli, "physics", "--config", str(cfg), "--connect", ep, "--preset", "default",
                          "--instance", "default"], stdout=logs[1], stderr=subprocess.STDOUT, env=env, cwd=ROOT),
        subprocess.Popen([*cli, "view", "--config", str(cfg), "--connect", ep],
                         stdout=logs[2], stderr=subprocess.STDOUT, env=env, cwd=ROOT),
    ]
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    os.environ.setdefault("SE_OFFLINE", "true")
    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                "--disable-dev-shm-usage", f"--user-data-dir={work / 'profile'}", "--window-size=1600,1000",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"):
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)
    try:
        url = f"http://127.0.0.1:{vport}/?token={TOKEN}"
        import urllib.request

        for _ in range(600):  # load the page once the viewer serves it (an error page never retries)
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{vport}/status?token={TOKEN}", timeout=1).close()
                break
            except OSError:
                time.sleep(0.2)
        driver.get(url)
        deadline = time.monotonic() + 300
        stats = None
        said = time.monotonic()
        while time.monotonic() < deadline:
            dead = [(n, p.returncode) for n, p in zip(("sumo", "physics", "view"), procs)
                    if p.poll() is not None and (p.returncode != 0 or n == "view")]
            if dead:
                for f in logs:
                    f.flush()
                tails = "\n".join(f"--- {n} (exit {rc}):\n" + (work / f"{n}.log").read_text(errors="replace")[-1500:]
                                  for n, rc in dead)
                raise SystemExit(f"a daemon exited early:\n{tails}")
            try:
                stats = driver.execute_script("const s = window.sumoco3d; return s ? {map: s.mapLoaded, t: s.simTime,"
                                              " phys: s.physicsAgents, agents: s.agents} : null;")
            except Exception:
                stats = None
            if stats and stats["map"] and stats["t"] and stats["t"] >= a.wait and stats["phys"] > 0:
                driver.execute_script("window.sumoco3d.pause(true);")  # hold this moment for the shot
                break
            if time.monotonic() - said > 10:
                said = time.monotonic()
                print("waiting:", stats, file=sys.stderr, flush=True)
            time.sleep(0.3)
        else:
            raise SystemExit(f"no picture after 300 s ({stats}); logs in {work}")
        if a.at:
            x, y = (float(v) for v in a.at.split(","))
            driver.execute_script("window.sumoco3d.lookAt(arguments[0], arguments[1], arguments[2]);", x, y, a.dist)
        if a.follow:
            driver.execute_script("window.sumoco3d.lookAtAgent(arguments[0], arguments[1]);"
                                  "window.sumoco3d.follow_(arguments[0]);", a.follow, a.dist)
        r0 = driver.execute_script("return window.sumoco3d.renders;")
        while driver.execute_script("return window.sumoco3d.renders;") < r0 + 3:
            time.sleep(0.2)
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(a.out)
        print(a.out, driver.execute_script("const s = window.sumoco3d; return {agents: s.agents, physics: s.physicsAgents,"
                                           " fps: s.fps, drawCalls: s.drawCalls, t: s.simTime, rtf: s.rtf};"))
    finally:
        driver.quit()
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
        for f in logs:
            f.close()
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
