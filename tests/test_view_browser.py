"""`hammer serve --realtime --view` watched in a real browser: Debian's chromium, headless, driven by
Selenium through Debian's chromedriver (installed by .ci/run; a browser that downloads itself at run
time cannot be fetched here). A real 20 Hz fleet of a trained cn3 team, real processes: one robot
frozen (SIGSTOP) turns its row missing within 2 s and back after SIGCONT, a push shows on every row,
and a view that stops answering makes the page say it is stale.

HAMMER_VIEW_SCREENSHOTS=DIR also saves the live run page there (docs/img/view-run.png was made so; the
index and the plots: docs/img/view_shots.py)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest

from tests.runtime_helpers import ENV, ROOT, trained_pair

pytestmark = pytest.mark.timeout(300)

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"


def _browser():
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    if not (Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists()):
        pytest.fail("Debian's chromium and chromium-driver are needed (apt-get install -y chromium chromium-driver; "
                    ".ci/run installs them)")
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu", "--window-size=1500,1000"):
        opts.add_argument(a)
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)


def _until(cond, timeout: float, step: float = 0.05):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = cond()
        if got:
            return got
        time.sleep(step)
    return None


class Fleet:
    """`hammer serve BUNDLE --realtime 20 --view 0` as a process, its stderr collected."""

    def __init__(self, bundle: Path, run: Path) -> None:
        self.run = run
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hammer.cli", "serve", str(bundle), "--realtime", "20", "--seconds", "240",
             "--run-dir", str(run), "--view", "0", "--no-dashboard"],
            cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        threading.Thread(target=lambda: self.lines.extend(iter(self.proc.stdout.readline, "")), daemon=True).start()

    def url(self) -> str:
        found = _until(lambda: next((m.group(1) for line in self.lines if (m := re.search(r"view: (http://\S+)", line))),
                                    None), 60)
        assert found, "".join(self.lines)
        return found

    def pid_of(self, role: str) -> int:
        for p in psutil.Process(self.proc.pid).children(recursive=True):
            cmd = p.cmdline()
            if role == "view" and "view" in cmd:
                return p.pid
            if role.startswith("local-") and "--agent" in cmd and cmd[cmd.index("--agent") + 1] == role[6:]:
                return p.pid
        raise AssertionError(f"no process of {role}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def test_a_live_fleet_in_headless_chromium(tmp_path):
    from selenium.webdriver.common.by import By

    bundle, pushed = trained_pair(tmp_path / "team", episodes=16)
    run = tmp_path / "runs" / "fleet"
    fleet = Fleet(bundle, run)
    driver = None
    try:
        url = fleet.url()
        driver = _browser()
        driver.get(url)

        def rows() -> dict[str, dict]:  # read in one script: the page redraws its table on every update
            return driver.execute_script(
                "const o = {}; document.querySelectorAll('tr.row').forEach((r) => { o[r.id.slice(4)] = {"
                "state: r.dataset.state, acted: r.dataset.acted, policy: r.querySelector('td.policy').textContent, "
                "seen: r.querySelector('td.seen').textContent, color: getComputedStyle(r).color}; }); return o;")

        def states() -> dict[str, str]:
            return {n: r["state"] for n, r in rows().items()}

        robots = ["local-0", "local-1", "local-2"]
        assert _until(lambda: all(states().get(r) == "ok" for r in robots), 90), (states(), "".join(fleet.lines))
        # nothing the page loads comes from elsewhere
        outside = [e.get_attribute("src") or e.get_attribute("href") for e in
                   driver.find_elements(By.CSS_SELECTOR, "script[src], link[href], img[src]")]
        assert not [u for u in outside if u and not u.startswith(url.split("#")[0])], outside

        # a frozen robot: missing within 2 s, greyed with its last-seen age; back after it resumes
        frozen = fleet.pid_of("local-1")
        os.kill(frozen, signal.SIGSTOP)
        t0 = time.monotonic()
        try:
            assert _until(lambda: states().get("local-1") == "missing", 5.0), states()
            took = time.monotonic() - t0
            now = rows()
            assert "last seen" in now["local-1"]["seen"], now
            assert now["local-1"]["color"] != now["local-0"]["color"], now  # greyed
            assert now["local-0"]["state"] != "missing" and now["local-2"]["state"] != "missing", now
        finally:
            os.kill(frozen, signal.SIGCONT)
        assert took <= 2.0, f"row turned missing {took:.2f} s after SIGSTOP"
        assert _until(lambda: states().get("local-1") in ("ok", "late"), 10.0), states()
        assert _until(lambda: states().get("local-1") == "ok", 10.0), states()
        events = driver.find_element(By.ID, "events").text
        assert "missing" in events and "back" in events, events

        # a push shows on every row: each robot and the central agent acts with version 1
        from hammer.serve.push import push

        push(pushed, run)
        acting = ["central", *robots]

        def acted() -> dict[str, str]:
            now = rows()
            return {n: now.get(n, {}).get("acted") for n in acting}

        assert _until(lambda: all(v == "1" for v in acted().values()), 60.0, 0.2), acted()
        assert _until(lambda: all(rows()[n]["policy"] == "v1 / v1" for n in robots), 10.0), rows()
        assert "push v1" in driver.find_element(By.ID, "events").text

        shots = os.environ.get("HAMMER_VIEW_SCREENSHOTS")
        time.sleep(5.5)  # the plots redraw every 5 s
        driver.save_screenshot(str(tmp_path / "run.png"))
        if shots:
            Path(shots).mkdir(parents=True, exist_ok=True)
            driver.save_screenshot(str(Path(shots) / "view-run.png"))

        # the server stops answering: the page says it is stale
        stale = driver.find_element(By.ID, "stale")
        assert not stale.is_displayed()
        view = psutil.Process(fleet.pid_of("view"))
        view.terminate()

        def gone() -> bool:  # the launcher reaps its view only at its own end: a zombie is gone enough
            try:
                return view.status() == psutil.STATUS_ZOMBIE
            except psutil.NoSuchProcess:
                return True

        assert _until(gone, 10.0), "the view did not stop on SIGTERM"
        assert _until(lambda: stale.is_displayed(), 8.0), "no stale banner"
        assert "this page is stale" in stale.text
        assert fleet.proc.poll() is None  # the fleet itself does not notice its view going
    finally:
        if driver is not None:
            driver.quit()
        fleet.stop()
    assert fleet.proc.returncode == 0, "".join(fleet.lines[-20:])
