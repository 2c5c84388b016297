"""The operator's tablet end to end in a real browser: a twin cell (`cellctl serve`), the tablet app
(`cellctl tablet`) and Debian's headless Chromium driven by playwright. Nothing is mocked.

Tests of: cellctl.tablet.pages, cellctl.tablet.app, cellctl.tablet.yard, cellctl.tablet.loopback.
Screenshots of every page go to $SCRAPCELL_SCREENSHOTS (`make screenshots`: docs/img) or the test's tmp dir."""

from __future__ import annotations

import io
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from cellctl.service.loopback import ServiceProcess
from cellctl.tablet.loopback import TabletProcess

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
OPERATOR, VIEWER = ("ana", "cut-steel-42"), ("vic", "just-watch-7")
LIVE_S = 300_000  # ms: bounds on a hang, many times what each step takes on a loaded 2-core machine


def _shots(tmp_path: Path) -> Path:
    d = Path(os.environ.get("SCRAPCELL_SCREENSHOTS") or tmp_path / "screenshots")
    d.mkdir(parents=True, exist_ok=True)
    return d


def _login(page, url: str, user: tuple[str, str]) -> None:
    page.goto(url + "/")
    page.get_by_test_id("user").fill(user[0])
    page.get_by_test_id("password").fill(user[1])
    page.get_by_test_id("login").click()


def _colour_pixels(png: bytes) -> dict[str, int]:
    """Pixels of the drawing (red), the cut (blue) and the torch axes (orange) in a screenshot."""
    import matplotlib.image as mpimg

    r, g, b = np.moveaxis(mpimg.imread(io.BytesIO(png), format="png")[..., :3], -1, 0)
    return {"red": int(np.count_nonzero((r > 0.6) & (g < 0.3) & (b < 0.3))),
            "blue": int(np.count_nonzero((b > 0.6) & (b - r > 0.3) & (b - g > 0.2))),
            "orange": int(np.count_nonzero((r > 0.8) & (g > 0.3) & (g < 0.6) & (b < 0.2)))}


@pytest.mark.timeout(900)
def test_a_worker_scans_cancels_and_a_viewer_only_watches_in_a_real_browser(tmp_path):
    if not Path(CHROMIUM).exists():
        pytest.fail("no chromium: `make test` installs it (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    shots = _shots(tmp_path)
    users = {OPERATOR[0]: ("operator", OPERATOR[1]), VIEWER[0]: ("viewer", VIEWER[1])}
    cell = {"svc": ServiceProcess(tmp_path / "cell").start()}  # the tour restarts it: stop whichever runs
    try:
        with TabletProcess(tmp_path / "tablet", cell["svc"].endpoint, users) as tab, sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=[
                "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
            page = browser.new_page(viewport={"width": 1280, "height": 860})
            page.set_default_timeout(60_000)
            try:
                _tour(page, tab, cell, shots, tmp_path)
            except BaseException:
                page.screenshot(path=shots / "tablet-failure.png", full_page=True)
                print(f"the page at the failure: {shots / 'tablet-failure.png'}\n{tab.log.read_text()[-3000:]}")
                raise
            browser.close()
    finally:
        cell["svc"].stop()


def _tour(page, tab, cell: dict, shots: Path, tmp_path: Path) -> None:
    from playwright.sync_api import expect

    svc = cell["svc"]
    if True:
        if True:

            # a wrong password is refused
            _login(page, tab.url, (OPERATOR[0], "not-the-password"))
            expect(page.get_by_test_id("login-error")).to_have_text("Wrong user or password.")
            page.screenshot(path=shots / "tablet-login.png")

            # the cells: sim-1 is online, ready and idle
            _login(page, tab.url, OPERATOR)
            card = page.get_by_test_id("cell-sim-1")
            expect(card).to_contain_text("Ready")
            expect(card).to_contain_text("Idle")
            expect(card).to_contain_text("Queue: 0 waiting")
            page.screenshot(path=shots / "tablet-cells.png")

            # start a scan of the T-piece; progress comes from the events
            card.click()
            expect(page.get_by_test_id("planner")).to_contain_text("gnbv")
            expect(page.get_by_test_id("no-jobs")).to_be_visible()  # a fresh cell says so, not a bare heading
            page.get_by_test_id("scene").click()
            page.get_by_role("option", name="t_piece", exact=True).click()
            expect(page.get_by_role("listbox")).to_be_hidden()
            page.screenshot(path=shots / "tablet-cell.png")
            page.get_by_test_id("start").click()
            expect(page).to_have_url(re.compile(r"/cell/sim-1/job/\d{8}T\d{6}Z-[0-9a-f]{6}$"))
            first_job = page.url.rsplit("/", 1)[1]
            expect(page.get_by_test_id("coverage")).to_contain_text("%", timeout=LIVE_S)
            expect(page.get_by_test_id("elapsed")).to_contain_text("Running for")
            page.screenshot(path=shots / "tablet-progress.png")

            # done: what will be cut, and the 3-D view drawn by WebGL with the red drawing in it
            expect(page.get_by_test_id("job-state")).to_have_text("done", timeout=LIVE_S)
            expect(page.get_by_test_id("cut-fraction")).to_have_text(
                re.compile(r"^\d+ % of the \d+ cm line will be cut$"))
            expect(page.get_by_test_id("cuts")).to_have_text(re.compile(r"^\d+ cuts?"))
            expect(page.get_by_test_id("scan-line")).to_contain_text("% of the line seen in")
            # every view's picture with what it took as paint, loaded (not a broken image)
            first = page.get_by_test_id("paint-paint_view0")
            expect(first).to_be_visible(timeout=LIVE_S)
            expect(page.get_by_test_id("paint-views")).to_contain_text("What the camera took as paint")
            views = page.locator("[data-testid^=paint-paint_view]")
            assert views.count() >= 2, "a scan has several views, each with its paint picture"
            img = first.locator("img").first
            page.wait_for_function("e => e.complete && e.naturalWidth > 0", arg=img.element_handle(), timeout=LIVE_S)
            canvas = page.get_by_test_id("scene3d").locator("canvas").first
            expect(canvas).to_be_visible(timeout=LIVE_S)
            for _ in range(60):  # three.js draws what it was sent within a few frames
                seen = _colour_pixels(canvas.screenshot(path=shots / "tablet-3d.png"))
                if seen["blue"] > 100 and seen["orange"] > 20:
                    break
                page.wait_for_timeout(500)
            assert seen["blue"] > 100 and seen["orange"] > 20, f"the cut is not drawn in the 3-D view: {seen}"
            page.screenshot(path=shots / "tablet-result.png", full_page=True)

            # a second job, cancelled while it scans
            page.get_by_test_id("home").click()
            page.get_by_test_id("cell-sim-1").click()
            page.get_by_test_id("scene").click()
            page.get_by_role("option", name="basket", exact=True).click()  # the longest scan: several views
            page.get_by_test_id("start").click()
            expect(page).not_to_have_url(re.compile(first_job))
            expect(page.get_by_test_id("phase")).to_have_text("Scanning the piece", timeout=LIVE_S)
            button = page.get_by_test_id("cancel").element_handle()
            page.wait_for_timeout(2500)  # the live figures are redrawn every second; the button is not
            assert button.evaluate("e => e.isConnected"), "the Cancel button was redrawn: a tap on it can be lost"
            page.get_by_test_id("cancel").click()
            expect(page.get_by_test_id("job-state")).to_have_text("cancelled", timeout=LIVE_S)

            # the history lists both; the first opens again with its result
            page.get_by_test_id("home").click()
            page.get_by_test_id("cell-sim-1").click()
            row = page.get_by_test_id(f"job-{first_job}")
            expect(row).to_contain_text("done")
            expect(page.get_by_text("cancelled", exact=True)).to_be_visible()
            page.screenshot(path=shots / "tablet-history.png")
            row.click()
            expect(page.get_by_test_id("cut-fraction")).to_be_visible()

            # the paint commissioned from the tablet: white on zinc is refused with the picture, red on rust taken
            page.get_by_test_id("home").click()
            page.get_by_test_id("cell-sim-1").click()
            expect(page.get_by_test_id("paint-now")).to_contain_text("lines of red paint", timeout=LIVE_S)
            page.get_by_test_id("paint-name").fill("white")
            page.get_by_test_id("paint-finish").fill("galvanized")
            page.get_by_test_id("commission").click()
            expect(page.get_by_test_id("paint-refused")).to_contain_text("cannot be told from this metal",
                                                                          timeout=LIVE_S)
            expect(page.get_by_test_id("paint-picture")).to_be_visible()
            expect(page.get_by_test_id("paint-now")).to_contain_text("lines of red paint")
            page.get_by_test_id("paint-name").fill("red")
            page.get_by_test_id("paint-finish").fill("rust_red")
            page.get_by_test_id("commission").click()
            expect(page.get_by_test_id("paint-ok")).to_contain_text("now finds lines of red paint", timeout=LIVE_S)
            expect(page.get_by_test_id("paint-now")).to_contain_text("cellctl calibrate paint")
            page.screenshot(path=shots / "tablet-paint.png", full_page=True)

            # the cell goes away: the page says so, and recovers when it is back, without a reload
            page.get_by_test_id("home").click()
            expect(page.get_by_test_id("cell-sim-1")).to_contain_text("Ready")
            svc.stop()
            expect(page.get_by_test_id("cell-sim-1")).to_contain_text("Offline", timeout=LIVE_S)
            expect(page.get_by_test_id("network")).to_be_visible(timeout=LIVE_S)
            page.screenshot(path=shots / "tablet-offline.png")
            svc = cell["svc"] = ServiceProcess(tmp_path / "cell", port=svc.port).start()
            expect(page.get_by_test_id("cell-sim-1")).to_contain_text("Ready", timeout=LIVE_S)
            expect(page.get_by_test_id("network")).to_be_hidden()

            # a viewer sees a running job and cannot start or cancel
            page.get_by_role("button", name="Log out").click()
            # the server navigates to the login page over its websocket: a goto started before that
            # navigation lands is aborted by it (net::ERR_ABORTED), so wait for it to land
            expect(page).to_have_url(re.compile(r"/login$"))
            expect(page.get_by_test_id("login")).to_be_visible()
            _login(page, tab.url, VIEWER)
            expect(page.get_by_test_id("who")).to_have_text("vic (viewer)")
            with svc.client() as c:
                job = c.submit({"scene": "t_piece", "planner": "gnbv"}).job_id
                page.get_by_test_id("cell-sim-1").click()
                expect(page.get_by_test_id("viewer-note")).to_be_visible()
                expect(page.get_by_test_id("start")).to_have_count(0)
                page.goto(f"{tab.url}/cell/sim-1/job/{job}")
                expect(page.get_by_test_id("phase")).to_be_visible(timeout=LIVE_S)
                expect(page.get_by_test_id("cancel")).to_have_count(0)
                page.screenshot(path=shots / "tablet-viewer.png")
                c.cancel(job)
