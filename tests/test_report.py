"""report.html (eval/report.py): its figures, and the page in a real headless browser
(Chromium over the DevTools protocol on a pipe): no console errors, and the per-view table
sorts when a header is clicked. The browser test is skipped, saying why, without Chromium."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from nerfgauge.core.images import read_exr_single, read_png, write_exr, write_png
from nerfgauge.methods.baselines import write_baseline
from nerfgauge.eval.evaluate import evaluate
from nerfgauge.eval.report import per_view_table, write_report

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


@pytest.fixture(scope="module")
def report(tmp_path_factory, make_dataset):
    root = tmp_path_factory.mktemp("report")
    data = make_dataset(root / "data", views=4, val_views=0, test_views=3, width=16, height=16, spp=2)
    renders = root / "renders"
    (renders / "test").mkdir(parents=True)
    for k, png in enumerate(sorted((data / "test").glob("r_???.png"))):
        image = np.round(read_png(png) * 255).astype(np.uint8)
        image[k: k + 2, :, :3] = 90  # a different error per view, so sorting changes the order
        write_png(renders / "test" / png.name, image)
        depth = read_exr_single(data / "test" / (png.stem + "_distance.exr"))
        write_exr(renders / "test" / (png.stem + "_depth.exr"), {"Z": depth * np.float32(1.02)})
    write_baseline(data, "nearest", root / "nearest")
    documents = {"ours": evaluate(data, renders, out=root / "ours.json"),
                 "nearest": evaluate(data, root / "nearest", out=root / "nearest.json")}
    log = root / "log.jsonl"
    log.write_text("".join(json.dumps({"seconds": s, "val_psnr": p}) + "\n" for s, p in ((1, 15.0), (2, 18.0))))
    page = write_report(root / "out" / "report.html", "tiny report", data, renders, documents, log_path=log,
                        ours="ours", train_seconds=2.5)
    return page, documents


def test_report_files_and_per_view_table(report):
    page, documents = report
    folder = page.parent
    for name in ("grid.png", "curve.png", "cameras.png"):
        assert (folder / name).stat().st_size > 1000
    text = page.read_text()
    assert text.count("<table class='sortable'>") == 2 and "ground truth" not in text  # labels are in the grid PNG
    table = per_view_table(documents)
    assert len(table) == 1 + 3 * 2 and table[0][:2] == ["frame", "method"]
    assert [row[0] for row in table[1:4]] == [f["name"] for f in documents["ours"]["frames"]]


def _browser():
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


class DevTools:
    """Chromium's DevTools protocol over --remote-debugging-pipe (fd 3 in, fd 4 out; JSON
    messages ended by NUL): no websocket library needed."""

    def __init__(self, browser: str, profile: Path):
        to_browser_read, self._write = os.pipe()
        self._read, from_browser_write = os.pipe()
        # Move the browser's ends to 10 and above so that dup2 onto 3 and 4 cannot clobber them.
        child_in, child_out = fcntl_high(to_browser_read), fcntl_high(from_browser_write)

        def wire():
            os.dup2(child_in, 3)
            os.dup2(child_out, 4)

        self.process = subprocess.Popen(
            [browser, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-extensions",
             f"--user-data-dir={profile}", "--remote-debugging-pipe", "about:blank"],
            pass_fds=(3, 4), preexec_fn=wire, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(child_in)
        os.close(child_out)
        self._buffer, self._next, self.events = b"", 0, []

    def send(self, method: str, params=None, session=None, timeout: float = 30.0) -> dict:
        self._next += 1
        message = {"id": self._next, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        os.write(self._write, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            reply = self._receive(deadline)
            if reply.get("id") == self._next:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)
        raise TimeoutError(method)

    def wait_for(self, method: str, timeout: float = 30.0) -> dict:
        deadline = time.monotonic() + timeout
        for event in self.events:
            if event.get("method") == method:
                return event
        while time.monotonic() < deadline:
            event = self._receive(deadline)
            self.events.append(event)
            if event.get("method") == method:
                return event
        raise TimeoutError(method)

    def _receive(self, deadline: float) -> dict:
        import select

        while b"\0" not in self._buffer:
            ready, _, _ = select.select([self._read], [], [], max(deadline - time.monotonic(), 0))
            if not ready:
                raise TimeoutError("no message from the browser")
            chunk = os.read(self._read, 1 << 16)
            if not chunk:
                raise RuntimeError("the browser closed the pipe")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def close(self):
        self.process.kill()
        self.process.wait()
        os.close(self._write)
        os.close(self._read)


def fcntl_high(fd: int) -> int:
    import fcntl

    high = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
    os.close(fd)
    return high


def open_page(tools: DevTools, url: str) -> str:
    target = tools.send("Target.createTarget", {"url": "about:blank"})["targetId"]
    session = tools.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
    for domain in ("Runtime", "Log", "Page"):
        tools.send(f"{domain}.enable", session=session)
    tools.send("Page.navigate", {"url": url}, session=session)
    tools.wait_for("Page.loadEventFired")
    return session


def console_errors(tools: DevTools) -> list:
    errors = []
    for event in tools.events:
        method, params = event.get("method"), event.get("params", {})
        if method == "Runtime.exceptionThrown":
            errors.append(params["exceptionDetails"].get("exception", {}).get("description", "exception"))
        elif method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
            errors.append(str(params.get("args")))
        elif method == "Log.entryAdded" and params.get("entry", {}).get("level") == "error":
            errors.append(params["entry"].get("text"))
    return errors


def evaluate_js(tools: DevTools, session: str, expression: str):
    result = tools.send("Runtime.evaluate", {"expression": expression, "returnByValue": True}, session=session)
    if "exceptionDetails" in result:
        raise AssertionError(result["exceptionDetails"])
    return result["result"].get("value")


PER_VIEW_COLUMN = """(function () {
  var table = document.querySelectorAll("table.sortable")[1];
  var headers = Array.prototype.map.call(table.tHead.rows[0].cells, function (c) { return c.textContent; });
  return headers.indexOf("PSNR dB");
})()"""

COLUMN_VALUES = """(function (col) {
  var table = document.querySelectorAll("table.sortable")[1];
  return Array.prototype.map.call(table.tBodies[0].rows, function (r) { return parseFloat(r.cells[col].textContent); });
})(%d)"""


@pytest.fixture
def chromium(tmp_path):
    """A headless Chromium over DevTools, closed after the test; skipped, saying why, without one."""
    browser = _browser()
    if browser is None:
        pytest.skip("no Chromium or Chrome on PATH (apt-get install chromium) to load report.html in")
    tools = DevTools(browser, tmp_path / "profile")
    try:
        yield tools
    finally:
        tools.close()


def test_report_in_headless_chromium(report, tmp_path, chromium):
    page, documents = report
    tools = chromium
    # The check can fail: a page with a script error is seen.
    broken = tmp_path / "broken.html"
    broken.write_text("<!doctype html><html><head><link rel='icon' href='data:,'></head><body>"
                      "<script>undefinedFunction()</script></body></html>")
    open_page(tools, broken.as_uri())
    assert any("undefinedFunction" in str(error) for error in console_errors(tools))
    tools.events.clear()

    session = open_page(tools, page.as_uri())
    column = evaluate_js(tools, session, PER_VIEW_COLUMN)
    assert column >= 2
    before = evaluate_js(tools, session, COLUMN_VALUES % column)
    assert len(before) == 6 and before != sorted(before)  # written in frame order, not PSNR order
    click = f"document.querySelectorAll('table.sortable')[1].tHead.rows[0].cells[{column}].click()"
    evaluate_js(tools, session, click)
    assert evaluate_js(tools, session, COLUMN_VALUES % column) == sorted(before)
    evaluate_js(tools, session, click)  # again: descending
    assert evaluate_js(tools, session, COLUMN_VALUES % column) == sorted(before, reverse=True)
    images = evaluate_js(tools, session, "Array.prototype.map.call(document.images, "
                                         "function (i) { return i.complete && i.naturalWidth > 0; })")
    assert images == [True, True, True]
    assert console_errors(tools) == []


PAGE_WIDTH = """(function () {
  return [document.documentElement.scrollWidth, window.innerWidth,
          Array.prototype.map.call(document.querySelectorAll("table.sortable"),
                                   function (t) { return t.getBoundingClientRect().right <= window.innerWidth
                                                         || t.parentElement.scrollWidth > t.parentElement.clientWidth; })];
})()"""


@pytest.mark.parametrize("width", [1280, 800, 400])
def test_report_fits_the_page_in_headless_chromium(report, chromium, width):
    """The page never scrolls sideways: a table wider than the window scrolls inside its own box."""
    page, _ = report
    session = open_page(chromium, page.as_uri())
    chromium.send("Emulation.setDeviceMetricsOverride", {"width": width, "height": 900, "deviceScaleFactor": 1,
                                                         "mobile": False}, session=session)
    page_width, window, tables = evaluate_js(chromium, session, PAGE_WIDTH)
    assert window == width and page_width <= window and tables and all(tables)
