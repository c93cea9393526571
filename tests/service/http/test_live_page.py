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
from helpers import EXAMPLES, precompute_into
from helpers.server import Server
from yauyau.solver.model import compile_model
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec

pytestmark = pytest.mark.service  # a real `yauyau serve` process

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
    options.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})  # console, network
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


@pytest.mark.browser
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


@pytest.mark.browser
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


# -- with tenants: the token is typed once, sent in a header, never in a URL --------------------------
@pytest.fixture(scope="module")
def tenant_server(tmp_path_factory, example_store):
    """A server with tenants alice and bob (tokens random, the file holds their SHA-256)."""
    import hashlib
    import secrets

    store, ids = example_store
    tokens = {name: secrets.token_urlsafe(24) for name in ("alice", "bob")}
    path = tmp_path_factory.mktemp("tenants") / "tenants.toml"
    path.write_text("".join(f'[[tenant]]\nname = "{name}"\n'
                            f'token_sha256 = "{hashlib.sha256(t.encode()).hexdigest()}"\n'
                            for name, t in tokens.items()))
    srv = Server(store, tmp_path_factory.mktemp("tenant-db") / "sessions.sqlite3",
                 env={"YAUYAU_TENANTS_FILE": str(path)})
    yield srv, ids, tokens
    srv.kill()


def _requests(driver) -> list[dict]:
    """Every request the browser sent since the last call (Chrome's performance log)."""
    import json

    out = []
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message["method"] == "Network.requestWillBeSent":
            out.append(message["params"]["request"])
    return out


def _token_field(driver):
    field = driver.find_element("id", "token")
    return field if field.is_displayed() else None


def _csp_violations(driver) -> list[str]:
    return [e["message"] for e in driver.get_log("browser") if "Content Security Policy" in e["message"]]


@pytest.mark.browser
def test_page_with_tenants_asks_the_token_once_and_keeps_it_out_of_urls(browser, tenant_server, tmp_path):
    srv, ids, tokens = tenant_server
    alice = {"Authorization": f"Bearer {tokens['alice']}"}
    client = httpx.Client(base_url=srv.url, timeout=30, headers=alice)
    sid = client.post("/v1/sessions", json={"model": ids["cubic_sensor"]}).json()["id"]
    shell = httpx.get(f"{srv.url}/v1/sessions/{sid}/view", headers={"Accept": "text/html"}, timeout=10)
    assert shell.status_code == 401
    csp = shell.headers["content-security-policy"]
    for directive in ("default-src 'none'", "connect-src 'self'", "frame-ancestors 'none'", "base-uri 'none'",
                      "form-action 'none'", "script-src 'sha256-", "style-src 'sha256-"):
        assert directive in csp, (directive, csp)
    assert "unsafe-inline" not in csp
    assert shell.headers["x-content-type-options"] == "nosniff"
    assert shell.headers["referrer-policy"] == "no-referrer"
    browser.get_log("performance"), browser.get_log("browser")  # start the logs here

    browser.get(f"{srv.url}/v1/sessions/{sid}/view")
    field = _wait(browser, _token_field, "the token field")
    status = browser.execute_script("return performance.getEntriesByType('navigation')[0].responseStatus")
    assert status == 401
    field.send_keys(tokens["alice"])
    browser.find_element("css selector", "#auth button").click()
    _wait(browser, _at_step(0), "step 0")
    rows = _increments("cubic_sensor", 200, seed=5)
    for seq in range(2):
        last = client.post(f"/v1/sessions/{sid}/observations",
                           json={"seq": seq, "increments": rows[seq * 100:(seq + 1) * 100]}).json()
        _wait(browser, _at_step(last["step"]), f"step {last['step']}")
    shown = _numbers(browser.find_element("id", "mean").text)
    assert shown[0] == pytest.approx(last["estimates"][-1]["mean"][0], rel=1e-4, abs=1e-5)
    # reloaded, the page goes on with the token of this tab: not asked again
    browser.refresh()
    _wait(browser, _at_step(200), "step 200 after a reload")
    assert not browser.find_element("id", "token").is_displayed()
    browser.save_screenshot(str((_shots() or tmp_path) / "live-tenant.png"))

    sent = _requests(browser)
    events = [r for r in sent if r["url"].endswith(f"/v1/sessions/{sid}/events")]
    assert len(events) >= 2 and all(r["headers"].get("Authorization") == alice["Authorization"]
                                    for r in events[-2:])  # after the token was typed, and after the reload
    urls = [r["url"] for r in sent] + browser.execute_script(
        "return performance.getEntries().map((e) => e.name).concat([location.href, document.referrer])")
    assert not [u for u in urls if tokens["alice"] in u], urls
    assert browser.execute_script("return sessionStorage.getItem('yauyau-token')") == tokens["alice"]
    assert browser.execute_script("return localStorage.length + document.cookie.length") == 0
    assert _csp_violations(browser) == []
    # the console does report violations (so the empty list above means something): an image is not allowed
    injected = "document.body.append(Object.assign(document.createElement('img'), {src: '/x.png'}))"
    browser.execute_script(injected)
    _wait(browser, lambda d: bool(_csp_violations(d)), "a CSP violation for an injected image")

    # another tenant's token: the session does not exist for it
    browser.execute_script("sessionStorage.clear()")
    browser.refresh()
    field = _wait(browser, _token_field, "the token field")
    field.send_keys(tokens["bob"])
    browser.find_element("css selector", "#auth button").click()
    _wait(browser, lambda d: d.find_element("id", "status").text == "no such session", "no such session")
    browser.execute_script("sessionStorage.clear()")
