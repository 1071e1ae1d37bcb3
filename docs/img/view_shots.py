"""The index and plot screenshots of docs/view.md: `hammer view` on a folder of finished runs, drawn by
headless Debian chromium (the live run page is saved by tests/test_view_browser.py with
HAMMER_VIEW_SCREENSHOTS=docs/img).

    python docs/img/view_shots.py RUNS_DIR RUN_WITH_CURVE [SWEEP_RUN]"""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

from selenium import webdriver
from selenium.webdriver.chrome.service import Service

HERE = Path(__file__).resolve().parent


def main(runs: str, curve_run: str, sweep_run: str | None = None) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    view = subprocess.Popen([sys.executable, "-m", "hammer.cli", "view", runs, "--addr", f"127.0.0.1:{port}"])
    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1500,900"):
        opts.add_argument(a)
    d = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)
    try:
        time.sleep(3)
        d.get(f"http://127.0.0.1:{port}/#/")
        time.sleep(2)
        d.save_screenshot(str(HERE / "view-index.png"))
        for name, run in (("view-curve.png", curve_run), ("view-sweep.png", sweep_run)):
            if run:
                d.get(f"http://127.0.0.1:{port}/#/run/{run}")
                time.sleep(3)
                d.save_screenshot(str(HERE / name))
    finally:
        d.quit()
        view.terminate()
        view.wait()


if __name__ == "__main__":
    main(*sys.argv[1:])
