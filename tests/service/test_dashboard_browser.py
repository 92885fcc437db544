"""The dashboard in a real browser: headless Chromium (Debian's chromium + chromium-driver) driven by
Selenium against a real server (uvicorn on a free loopback port, embedded worker, real engine, CPU).

Skips when no Chromium, chromedriver or selenium is installed (.ci/run installs them with apt-get).
With DEMQ_SCREENSHOT_DIR set, the screenshots are also written there (docs/dashboard.png comes from
``DEMQ_SCREENSHOT_DIR=docs python -m pytest tests/service/test_dashboard_browser.py``).
"""

from __future__ import annotations

import os
import shutil
import socket
import threading
from pathlib import Path

import httpx
import pytest

from service.app import create_app
from tests.service.conftest import TINY, make_settings
from tests.waiting import CEILING_S, wait_for

pytestmark = pytest.mark.heavy   # a real browser: the `browser` extra, chromium and chromedriver

TOKEN = "dashboard-test-token"
#: A ceiling that only catches a hang: a first Numba compilation of the CPU kernels in the simulation process
#: on a loaded machine stays far below it (the run itself takes about a second).
DONE_TIMEOUT_S = CEILING_S


def _browser_paths() -> tuple[str, str]:
    chromium = next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)
    driver = "/usr/bin/chromedriver" if os.path.exists("/usr/bin/chromedriver") else shutil.which("chromedriver")
    if not chromium or not driver:
        pytest.skip("no Chromium/chromedriver (apt-get install chromium chromium-driver)")
    return chromium, driver


def make_driver(width: int = 1400, height: int = 1000):
    """A headless Chromium through the system chromedriver (Selenium Manager cannot download here)."""
    chromium, driver_path = _browser_paths()
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                f"--window-size={width},{height}", "--hide-scrollbars"):
        opts.add_argument(arg)
    return webdriver.Chrome(options=opts, service=Service(executable_path=driver_path))


class LiveServer:
    """uvicorn serving ``app`` in a thread on a free loopback port (the app's lifespan runs the worker)."""

    def __init__(self, app):
        import uvicorn

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.bind(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        self.server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    def __enter__(self) -> "LiveServer":
        self.thread.start()
        wait_for(lambda: self.server.started or not self.thread.is_alive(), "the server's start")
        assert self.server.started, "the server did not start"
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=30)
        self.sock.close()


def _fill(driver, name: str, value: str) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    el = driver.find_element(By.NAME, name)
    if el.tag_name == "select":
        Select(el).select_by_visible_text(value)
    else:
        el.clear()
        el.send_keys(value)


def test_submit_watch_and_open_a_job_in_chromium(tmp_path):
    _browser_paths()
    pytest.importorskip("selenium")
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    settings = make_settings(tmp_path, engine_run="engine.driver.simulate:run", token=TOKEN, progress_s=0.1)
    app = create_app(settings, embedded_worker=True)
    with LiveServer(app) as server:
        # without the token nothing leaks: the page is the token form, with a 401
        bare = httpx.get(server.url + "/", headers={"accept": "text/html"})
        assert bare.status_code == 401 and 'name="token"' in bare.text

        auth = {"Authorization": f"Bearer {TOKEN}"}
        batch = httpx.post(server.url + "/batches", headers=auth, json={
            "base": {**TINY, "backend": "cpu"}, "sweep": {"e_n": [0.6, 0.9], "seed": [1, 2]}}).json()
        driver = make_driver()
        try:
            driver.get(server.url + "/")
            assert "Token needed" in driver.find_element(By.TAG_NAME, "h1").text
            _fill(driver, "token", TOKEN)
            driver.find_element(By.ID, "login").click()
            WebDriverWait(driver, 10).until(lambda d: _h1(d) == "Jobs")  # the next page, once it is there
            list_tab = driver.current_window_handle
            driver.execute_script("window.loadedOnce = true")  # survives htmx swaps, not a page reload

            # a second tab submits the tiny job through the form
            driver.switch_to.new_window("tab")
            driver.get(server.url + "/ui/submit")
            for name, value in {**TINY, "seed": 7}.items():
                _fill(driver, name, str(value))
            _fill(driver, "backend", "cpu")
            driver.find_element(By.ID, "submit").click()
            WebDriverWait(driver, 10).until(lambda d: "/ui/jobs/" in d.current_url)
            job_id = driver.current_url.rstrip("/").rsplit("/", 1)[-1]
            WebDriverWait(driver, 10).until(lambda d: job_id in _h1(d))

            # the list, loaded before the job existed, shows its row and the bar reaching done by itself
            driver.switch_to.window(list_tab)
            seen: list = []

            def done(d) -> bool:
                row = _row(d, job_id)  # read in one script: htmx replaces the rows every 2 s
                if row and (not seen or seen[-1] != row):
                    seen.append(row)
                return bool(row) and row["state"] == "done" and row["value"] == "100"

            WebDriverWait(driver, DONE_TIMEOUT_S, poll_frequency=0.25).until(done, f"row states seen: {seen}")
            assert driver.execute_script("return window.loadedOnce === true"), "the list reloaded instead of updating"
            row = _row(driver, job_id)
            assert row["width"] == "100%" and row["cells"][5] == "cpu", row  # the bar is full; backend column
            WebDriverWait(driver, DONE_TIMEOUT_S, poll_frequency=0.25).until(
                lambda d: all((_row(d, j) or {}).get("state") == "done" for j in batch["job_ids"]))
            driver.set_window_size(1400, 680)
            _screenshot(driver, tmp_path, "dashboard.png")
            driver.set_window_size(1400, 1000)

            # the job page: spec, downloads, the cooling plot loaded
            driver.execute_script(f"document.querySelector(\"#job-{job_id} a[href='/ui/jobs/{job_id}']\").click()")
            WebDriverWait(driver, 10).until(lambda d: d.find_elements(By.ID, "cooling-plot"))
            plot_loaded = ("const i = document.getElementById('cooling-plot');"
                           "return i.complete && i.naturalWidth > 0 ? i.naturalWidth : 0;")
            WebDriverWait(driver, 60, poll_frequency=0.25).until(lambda d: d.execute_script(plot_loaded))
            hrefs = {a.get_attribute("href").removeprefix(server.url)
                     for a in driver.find_elements(By.CSS_SELECTOR, ".downloads a")}
            assert hrefs == {f"/jobs/{job_id}/result", f"/jobs/{job_id}/energy?format=csv",
                             f"/jobs/{job_id}/export.gsd", f"/jobs/{job_id}/result.xmf"}
            # the HttpOnly cookie also opens the API's downloads, and scripts cannot read it
            status = driver.execute_async_script(
                "const done = arguments[arguments.length - 1];"
                f"fetch('/jobs/{job_id}/energy?format=csv').then(r => done(r.status), e => done(String(e)));")
            assert status == 200
            assert "demq_token" not in driver.execute_script("return document.cookie")
            assert not driver.find_elements(By.ID, "cancel")  # a done job has nothing to cancel
            snapshot_route = any(getattr(r, "path", "") == "/jobs/{job_id}/snapshot.png" for r in app.routes)
            if snapshot_route:  # the particle picture (its route lands with the visualisation exports)
                WebDriverWait(driver, 60, poll_frequency=0.25).until(lambda d: d.execute_script(
                    "const i = document.getElementById('snapshot'); return i.complete && i.naturalWidth > 0;"))
            _screenshot(driver, tmp_path, "dashboard-job.png")

            # the batch page: the sweep table and the mean curves over the seeds
            driver.get(f"{server.url}/ui/batches/{batch['batch_id']}")
            heads = [th.text for th in driver.find_elements(By.CSS_SELECTOR, "#batch-live thead th")]
            assert heads[1:3] == ["e_n", "seed"], heads
            WebDriverWait(driver, 60, poll_frequency=0.25).until(lambda d: d.execute_script(
                "const i = document.getElementById('batch-plot'); return i && i.complete && i.naturalWidth > 0;"))
            _screenshot(driver, tmp_path, "dashboard-batch.png")
        finally:
            driver.quit()
    for name in ("dashboard.png", "dashboard-job.png", "dashboard-batch.png"):
        assert (tmp_path / name).stat().st_size > 10_000, name


def _h1(driver) -> str:
    """The page's heading, read in one script (no element reference to go stale while a page loads)."""
    return driver.execute_script("const h = document.querySelector('h1'); return h ? h.textContent.trim() : ''")


def _row(driver, job_id: str):
    """State, progress value, bar width and cell texts of a job's row in the list (None if absent)."""
    return driver.execute_script(
        "const r = document.getElementById(arguments[0]); if (!r) return null;"
        "const b = r.querySelector('[role=progressbar]');"
        "return {state: r.dataset.state, value: b.getAttribute('aria-valuenow'), "
        "width: b.firstElementChild.style.width,"
        "        cells: Array.from(r.cells, c => c.innerText.trim())};", f"job-{job_id}")


def _screenshot(driver, tmp_path: Path, name: str) -> None:
    driver.save_screenshot(str(tmp_path / name))
    if os.environ.get("DEMQ_SCREENSHOT_DIR"):
        shutil.copyfile(tmp_path / name, Path(os.environ["DEMQ_SCREENSHOT_DIR"]) / name)
