"""The live page of jobs in a real browser: headless Chromium (Debian's chromium and
chromium-driver, which `.ci/run` installs) driven by Selenium against a real `ocpar serve`
on 127.0.0.1 with the serial backend.

A formation job submitted through the API is followed on the page until `succeeded`; its
convergence plot must hold the cost of every progress line of the job's log (read
separately through `GET /jobs/{id}/log`), its result plot must load (at the PNG's own width)
and its result.json link must download the server's bytes. A pursuit job's plot grows while
it runs; a job queued behind it (`--max-running 1`) is cancelled with its button, and the
pursuit job's Cancel and Resume buttons stop it and run it on. The plot's y axis is checked
apart: logarithmic across decades, linear within one.
"""

from __future__ import annotations

import itertools
import os
import re
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists() or not CHROMEDRIVER.exists(),
    reason="no /usr/bin/chromium or /usr/bin/chromedriver (Debian: apt-get install -y "
           "chromium chromium-driver; .ci/run does it as root)")

COST_LINE = re.compile(r"^superstep\s+(\d+)\s+cost\s+(\S+)", re.MULTILINE)


def ocpar(*args: str, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ocpar", *args], capture_output=True,
                          text=True, check=True, timeout=60, **kwargs)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str, Path]]:
    """A real `ocpar serve` (serial backend, one job at a time), a token and the server's
    output: (URL, token, log file)."""
    state = tmp_path_factory.mktemp("server")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    token = ocpar("serve", "token", "add", "page", "--state-dir", str(state),
                  env=env).stdout.split()[-1]
    port = free_port()
    output = state / "serve.log"
    log = output.open("w")
    process = subprocess.Popen(
        [sys.executable, "-m", "ocpar", "serve", "--host", "127.0.0.1", "--port", str(port),
         "--state-dir", str(state), "--backend", "serial", "--max-running", "1"],
        stdout=log, stderr=subprocess.STDOUT, env=env)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 30
        while True:
            assert process.poll() is None, output.read_text()
            try:
                if httpx.get(f"{url}/openapi.json", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, "ocpar serve did not answer within 30 s"
            time.sleep(0.2)
        yield url, token, output
    finally:
        process.terminate()
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        log.close()


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory):
    """Headless Chromium through the system chromedriver; downloads go to
    ``browser.download_dir``."""
    from selenium import webdriver

    downloads = tmp_path_factory.mktemp("downloads")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu",
                     "--disable-dev-shm-usage", "--disable-background-networking",
                     "--disable-component-update", "--disable-sync", "--no-first-run",
                     "--window-size=1400,1400",
                     f"--user-data-dir={tmp_path_factory.mktemp('chromium')}"):
        options.add_argument(argument)
    options.add_experimental_option("prefs", {
        "download.default_directory": str(downloads), "download.prompt_for_download": False})
    driver = webdriver.Chrome(
        service=webdriver.ChromeService(executable_path=str(CHROMEDRIVER)), options=options)
    driver.download_dir = downloads
    try:
        yield driver
    finally:
        driver.quit()


def open_page(browser, url: str, token: str) -> None:
    """Load the page and give it the token."""
    from selenium.webdriver.common.by import By

    browser.get(url)
    field = browser.find_element(By.ID, "token")
    field.clear()
    field.send_keys(token)
    browser.find_element(By.ID, "save-token").click()


def submit_and_show(server, browser, request: dict):
    """Submit ``request`` through the API, open the page and show the job's panel: the API
    client, the job id, the CSS selector of its row and a 60 s waiter."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    url, token, output = server
    api = httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"},
                       timeout=30)
    submitted = api.post("/jobs", json=request)
    assert submitted.status_code == 201, f"{submitted.text}\n{output.read_text()}"
    job = submitted.json()["id"]
    open_page(browser, url, token)
    row = f'#job-rows tr[data-job-id="{job}"]'
    wait = WebDriverWait(browser, 60, poll_frequency=0.1)
    wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, row))
    browser.find_element(By.CSS_SELECTOR, f'{row} button[data-action="show"]').click()
    return api, job, row, wait


PLOT = """const svg = document.getElementById("convergence-plot");
    return [svg.dataset.figure, [...svg.querySelectorAll("circle.pt")].map(
        (c) => [Number(c.dataset.x), Number(c.dataset.y)]), Number(svg.dataset.points)];"""


def plotted(browser) -> tuple[str, list[tuple[float, float]], int]:
    """The convergence plot's figure, its markers' (x, y) and its number of points, read
    at once (the SVG is redrawn as points arrive)."""
    figure, markers, count = browser.execute_script(PLOT)
    return figure, [tuple(marker) for marker in markers], count


def png_width(data: bytes) -> int:
    """The width of a PNG from its IHDR chunk (bytes 16-20, big-endian)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">I", data[16:20])[0]


def test_page_follows_a_job_to_its_result(server, browser):
    from selenium.webdriver.common.by import By

    api, job, row, wait = submit_and_show(server, browser, {"config": "formation-60",
                                                             "set": {"agents": 8}})
    # the followed job, shown in the detail panel, reaches succeeded on the page
    wait.until(lambda d: d.find_element(By.CSS_SELECTOR, row)
               .get_attribute("data-state") == "succeeded")
    record = api.get(f"/jobs/{job}").json()
    assert record["state"] == "succeeded" and record["result_status"] == "converged"
    assert browser.find_element(By.CSS_SELECTOR, f"{row} td.state").text == "succeeded"
    assert browser.find_element(By.ID, "detail-state").text == "succeeded"
    assert browser.find_element(By.CSS_SELECTOR, f"{row} td.headline").text == \
        (record["headline"] or record["reason"] or record["result_status"])
    assert int(browser.find_element(By.CSS_SELECTOR, row).get_attribute("data-supersteps")) \
        == record["supersteps"]
    assert browser.execute_script(  # a final job's bar is full
        f"const p = document.querySelector('{row} progress'); return p.value === p.max")

    # the convergence plot holds one point per cost line of the job's log, at its superstep
    log = api.get(f"/jobs/{job}/log").json()["text"]
    costs = [(int(step), float(cost)) for step, cost in COST_LINE.findall(log)]
    assert len(costs) >= 3
    wait.until(lambda d: plotted(d)[2] == len(costs))
    figure, points, _ = plotted(browser)
    assert figure == "cost"
    assert points == costs
    summary = api.get(f"/jobs/{job}/files/result.json").json()
    assert costs[-1][1] == pytest.approx(summary["total_cost"], rel=1e-11)

    # the result's plot loads at the PNG's width; result.json downloads the server's bytes
    files = {f["name"] for f in api.get(f"/jobs/{job}/files").json()["files"]}
    png = sorted(name for name in files if name.endswith(".png"))[0]
    image = f'img.result-plot[data-file="{png}"]'
    wait.until(lambda d: d.execute_script(
        f"const i = document.querySelector('{image}'); return i !== null && i.complete "
        "&& i.naturalWidth > 0"))
    width = browser.execute_script(f"return document.querySelector('{image}').naturalWidth")
    assert width == png_width(api.get(f"/jobs/{job}/files/{png}").content)
    shown = {link.get_attribute("data-file")
             for link in browser.find_elements(By.CSS_SELECTOR, "#files a.file-link")}
    assert shown == files
    browser.find_element(By.CSS_SELECTOR, '#files a.file-link[data-file="result.json"]').click()
    saved = browser.download_dir / "result.json"
    wait.until(lambda d: saved.exists() and saved.stat().st_size > 0)
    assert saved.read_bytes() == api.get(f"/jobs/{job}/files/result.json").content


def test_page_cancels_queued_and_running_jobs_and_resumes_one(server, browser):
    from selenium.webdriver.common.by import By

    output = server[2]
    api, job, row, wait = submit_and_show(server, browser,
                                          {"config": "pursuit-case1"})  # minutes of supersteps

    def points() -> int:
        return plotted(browser)[2]

    # while it runs, the plot grows (pursuit's figure: the last agent's final mass) and the
    # progress bar is indeterminate
    wait.until(lambda d: points() >= 5)
    assert browser.find_element(By.CSS_SELECTOR, row).get_attribute("data-state") == "running"
    assert browser.execute_script(
        f"return !document.querySelector('{row} progress').hasAttribute('value')")
    assert plotted(browser)[0] == "last final mass"
    before = points()
    wait.until(lambda d: points() > before)

    # a job queued behind it (one job at a time) is cancelled from its row's button
    queued = api.post("/jobs", json={"config": "formation-60", "set": {"agents": 6}})
    assert queued.status_code == 201, f"{queued.text}\n{output.read_text()}"
    other = f'#job-rows tr[data-job-id="{queued.json()["id"]}"]'
    wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, other))
    assert browser.find_element(By.CSS_SELECTOR, other).get_attribute("data-state") == "queued"
    browser.find_element(By.CSS_SELECTOR, f'{other} button[data-action="cancel"]').click()
    wait.until(lambda d: d.find_element(By.CSS_SELECTOR, other)
               .get_attribute("data-state") == "cancelled")
    record = api.get(f"/jobs/{queued.json()['id']}").json()
    assert record["state"] == "cancelled" and record["started"] is None
    assert browser.find_element(By.CSS_SELECTOR, f"{other} td.state").text == "cancelled"
    assert not browser.find_element(
        By.CSS_SELECTOR, f'{other} button[data-action="cancel"]').is_enabled()
    assert browser.find_element(By.CSS_SELECTOR, row).get_attribute("data-state") == "running"

    # Cancel stops the running job at a superstep boundary; Resume runs it on from its checkpoint
    browser.find_element(By.CSS_SELECTOR, f'{row} button[data-action="cancel"]').click()
    wait.until(lambda d: d.find_element(By.CSS_SELECTOR, row)
               .get_attribute("data-state") == "cancelled")
    cancelled = api.get(f"/jobs/{job}").json()
    assert cancelled["state"] == "cancelled" and cancelled["reason"]
    wait.until(lambda d: d.find_element(By.CSS_SELECTOR, f"{row} td.headline").text
               == cancelled["reason"])  # why it stopped, in words
    resume = browser.find_element(By.CSS_SELECTOR, f'{row} button[data-action="resume"]')
    assert resume.is_enabled()
    resume.click()
    wait.until(lambda d: d.find_element(By.CSS_SELECTOR, row)
               .get_attribute("data-state") == "running")
    wait.until(lambda d: int(d.find_element(By.CSS_SELECTOR, row)
                             .get_attribute("data-supersteps")) > cancelled["supersteps"])
    assert browser.find_element(By.ID, "detail-state").text == "running"
    before = points()
    wait.until(lambda d: points() > before)  # the stream, opened again, feeds the plot
    assert api.delete(f"/jobs/{job}").status_code == 204
    wait.until(lambda d: d.find_element(By.CSS_SELECTOR, row)
               .get_attribute("data-state") == "cancelled")


def test_plot_turns_logarithmic_across_decades(server, browser):
    """Values spanning decades go on a log axis: 10^0 .. 10^-6 at equal heights apart;
    values within a decade stay linear: equal differences at equal heights apart."""
    browser.get(server[0])
    draw = """
        const box = document.createElement("div"), caption = document.createElement("p");
        const plot = new ConvergencePlot(box, caption);
        arguments[0].forEach((y, i) => plot.add(i, y, "cost", "superstep"));
        plot.render();
        const svg = box.querySelector("svg");
        return [svg.dataset.scale, [...svg.querySelectorAll("circle.pt")].map(
            (c) => Number(c.getAttribute("cy")))];"""
    scale, heights = browser.execute_script(draw, [10.0 ** -k for k in range(7)])
    assert scale == "log"
    steps = [b - a for a, b in itertools.pairwise(heights)]
    assert min(steps) > 0 and max(steps) == pytest.approx(min(steps), rel=1e-9)
    scale, heights = browser.execute_script(draw, [5.0, 4.0, 3.0, 1.0])
    assert scale == "linear"
    assert heights[3] - heights[2] == pytest.approx(2 * (heights[1] - heights[0]), rel=1e-9)
