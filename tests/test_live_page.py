"""The live page (GET /v1/sessions/{id}/view) in a real headless browser against a real server.

Debian's chromium and chromedriver, driven by Selenium (no browser download: the paths are given).
The test streams chunks into a session over HTTP and asserts that what the page shows follows:
the step and the mean printed on the page equal the API's, the canvas pixels change, a 2-D session
gets a heat map, a degenerate session says why, a deleted one says so.  Screenshots are saved under
$YAUYAU_SCREENSHOTS (docs/img/live-*.png come from there) or the test's temporary directory.

If the browser cannot start, the test fails with the reason (install: apt-get install chromium
chromium-driver; `python3 dev.py test` does it when it can).
"""

from __future__ import annotations

import base64
import io
import os
import shutil
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import EXAMPLES, precompute_into
from test_service_server import Server
from yauyau.solver.model import compile_model
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec

CHROMIUM = os.environ.get("YAUYAU_CHROMIUM", "/usr/bin/chromium")
CHROMEDRIVER = os.environ.get("YAUYAU_CHROMEDRIVER", "/usr/bin/chromedriver")


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    from selenium import webdriver
    from selenium.common.exceptions import WebDriverException
    from selenium.webdriver.chrome.service import Service

    for path in (CHROMIUM, CHROMEDRIVER):
        if not (Path(path).exists() or shutil.which(path)):
            pytest.fail(f"{path} is missing: apt-get install chromium chromium-driver (python3 dev.py test "
                        "installs them when it runs as root)")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--window-size=900,800",
                 f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}"):
        options.add_argument(flag)
    try:
        driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=options)
    except WebDriverException as exc:
        pytest.fail(f"chromium did not start: {exc.msg}")
    driver.set_page_load_timeout(30)
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    store = tmp_path_factory.mktemp("live-store")
    ids = {name: precompute_into(store, EXAMPLES / f"{name}.toml") for name in ("cubic_sensor", "range_2d")}
    srv = Server(store, tmp_path_factory.mktemp("live-db") / "sessions.sqlite3")
    yield srv, ids
    srv.kill()


def _shots() -> Path | None:
    target = os.environ.get("YAUYAU_SCREENSHOTS")
    return Path(target) if target else None


def _wait(driver, condition, what: str, timeout: float = 20.0):
    from selenium.common.exceptions import TimeoutException
    from selenium.webdriver.support.ui import WebDriverWait

    try:
        return WebDriverWait(driver, timeout, poll_frequency=0.05).until(lambda d: condition(d))
    except TimeoutException:
        status = driver.find_element("id", "status").text
        pytest.fail(f"the page did not show {what} within {timeout} s (status: {status!r})")


def _canvas(driver) -> np.ndarray:
    """The canvas pixels (H, W, 4) as the page drew them."""
    import matplotlib.image

    url = driver.execute_script("return document.getElementById('density').toDataURL('image/png');")
    return matplotlib.image.imread(io.BytesIO(base64.b64decode(url.split(",", 1)[1])), format="png")


def _numbers(text: str) -> list[float]:
    return [float(v) for v in text.strip("[]").split(",")]


def _increments(spec_name: str, steps: int, seed: int) -> list[list[float]]:
    model = compile_model(load_spec(EXAMPLES / f"{spec_name}.toml"))
    return simulate(model, steps, np.random.default_rng(seed)).increments.tolist()


def _at_step(step: int):
    return lambda d: d.find_element("tag name", "body").get_attribute("data-step") == str(step)


def _open_page(browser, server, model: str, **options):
    """A new session of ``model`` (with session ``options``) and its live page, shown at step 0;
    (client, session id)."""
    srv, ids = server
    client = httpx.Client(base_url=srv.url, timeout=30)
    sid = client.post("/v1/sessions", json={"model": ids[model], **options}).json()["id"]
    browser.get(f"{srv.url}/v1/sessions/{sid}/view")
    _wait(browser, _at_step(0), "step 0")
    return client, sid


def test_page_follows_a_1d_stream(browser, server, tmp_path):
    client, sid = _open_page(browser, server, "cubic_sensor", gate=0)  # the gate off: 1e6 degenerates
    before = _canvas(browser)
    assert (before[..., :3].sum(axis=-1) < 2.5).mean() > 0.01  # a curve is drawn, not a blank canvas
    rows = _increments("cubic_sensor", 300, seed=2)
    last = None
    for seq in range(3):
        last = client.post(f"/v1/sessions/{sid}/observations",
                           json={"seq": seq, "increments": rows[seq * 100:(seq + 1) * 100]}).json()
        _wait(browser, _at_step(last["step"]), f"step {last['step']}")
    assert browser.find_element("id", "step").text == "300"
    shown = _numbers(browser.find_element("id", "mean").text)
    assert shown[0] == pytest.approx(last["estimates"][-1]["mean"][0], rel=1e-4, abs=1e-5)
    info = client.get(f"/v1/sessions/{sid}", params={"mode": "true"}).json()
    assert _numbers(browser.find_element("id", "mode").text)[0] == pytest.approx(
        info["estimate"]["mode"][0], rel=1e-4, abs=1e-5)
    after = _canvas(browser)
    changed = np.abs(after[..., :3] - before[..., :3]).sum(axis=-1) > 0.1
    assert changed.mean() > 0.01, "the density drawn changed with the data"
    assert "live" in browser.find_element("id", "status").text
    browser.save_screenshot(str((_shots() or tmp_path) / "live-1d.png"))
    # a degenerate step is said, with the reason; a deleted session too
    client.post(f"/v1/sessions/{sid}/observations", json={"seq": 3, "increments": [[1e6]]})
    _wait(browser, lambda d: "degenerate" in d.find_element("id", "status").text, "the degenerate status")
    assert client.delete(f"/v1/sessions/{sid}").status_code == 204
    _wait(browser, lambda d: "deleted" in d.find_element("id", "status").text, "the deleted status")


def test_page_draws_a_2d_heat_map_and_ellipse(browser, server, tmp_path):
    client, sid = _open_page(browser, server, "range_2d")
    rows = _increments("range_2d", 60, seed=3)
    last = client.post(f"/v1/sessions/{sid}/observations", json={"seq": 0, "increments": rows}).json()
    _wait(browser, _at_step(60), "step 60")
    shown = _numbers(browser.find_element("id", "mean").text)
    np.testing.assert_allclose(shown, last["estimates"][-1]["mean"], rtol=1e-4, atol=1e-5)
    pixels = _canvas(browser)[..., :3]
    heat = pixels[25:375, 65:375]  # the heat-map panel
    assert (heat.sum(axis=-1) < 0.3).mean() > 0.2  # dark background of the colour map
    assert (heat.sum(axis=-1) > 1.5).mean() > 0.002  # and the bright peak
    orange = (np.abs(pixels - np.array([1.0, 0.5, 0.055])) < 0.12).all(axis=-1)
    assert orange.sum() > 30, "the covariance ellipse is drawn"
    browser.save_screenshot(str((_shots() or tmp_path) / "live-2d.png"))


def test_view_and_events_of_an_unknown_session_are_404(server):
    srv, _ = server
    for path in ("view", "events"):
        r = httpx.get(f"{srv.url}/v1/sessions/nope/{path}", timeout=10)
        assert r.status_code == 404 and r.headers["content-type"].startswith("application/problem+json")
