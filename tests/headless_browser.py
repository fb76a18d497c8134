"""Open a page in Debian's headless chromium and look at it through the DevTools protocol: wait for a condition,
collect console errors and uncaught exceptions, take a screenshot. For page tests (skip when `CHROMIUM` is None).
Needs the `websockets` package (a dependency of viser)."""

from __future__ import annotations

import base64
import itertools
import json
import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--hide-scrollbars", "--no-first-run", "--remote-debugging-port=0"]


@dataclass
class PageLoad:
    """What the browser saw: `ready` (the condition held in time), `png` screenshot bytes, `errors` (console errors
    and uncaught exceptions, one line each), `text` (the page's visible text)."""

    ready: bool
    png: bytes
    text: str
    errors: list[str] = field(default_factory=list)


def _devtools_port(proc: subprocess.Popen, timeout: float) -> int:
    end = time.time() + timeout
    assert proc.stderr is not None
    while time.time() < end:
        line = proc.stderr.readline()
        m = re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line)
        if m:
            return int(m.group(1))
        if not line and proc.poll() is not None:
            break
    raise RuntimeError("chromium did not open its DevTools port")


def load_page(url: str, ready_js: str, size: tuple[int, int] = (1000, 700), timeout: float = 60.0,
              then_js: str = "") -> PageLoad:
    """Load `url` in a `size` (width, height) viewport, wait until the JavaScript expression `ready_js` is true (at
    most `timeout` s), run `then_js` (e.g. close a notice), screenshot it."""
    from websockets.sync.client import connect

    if CHROMIUM is None:
        raise RuntimeError("chromium is not installed (apt-get install -y chromium)")
    # chromium's helper processes (renderer, GPU, zygote) may still write into the profile after the main one is
    # gone: it runs in its own process group, the whole group is killed, and a file written in that last instant
    # does not fail the test when the profile is removed
    with tempfile.TemporaryDirectory(prefix="inrslam-chromium-", ignore_cleanup_errors=True) as profile:
        proc = subprocess.Popen([CHROMIUM, *FLAGS, f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
                                 "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                start_new_session=True)
        try:
            port = _devtools_port(proc, timeout)
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
                page = next(t for t in json.load(r) if t["type"] == "page")
            with connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=10) as ws:
                return _drive(ws, url, ready_js, size, timeout, then_js)
        finally:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait(timeout=10)


def _drive(ws, url: str, ready_js: str, size: tuple[int, int], timeout: float, then_js: str) -> PageLoad:
    ids = itertools.count(1)
    errors: list[str] = []

    def note(event: dict) -> None:
        method, p = event.get("method"), event.get("params", {})
        if method == "Runtime.exceptionThrown":
            d = p["exceptionDetails"]
            errors.append("uncaught: " + str(d.get("exception", {}).get("description") or d.get("text")))
        elif method == "Runtime.consoleAPICalled" and p.get("type") == "error":
            errors.append("console.error: " + " ".join(str(a.get("value", a.get("description"))) for a in p["args"]))
        elif method == "Log.entryAdded" and p["entry"].get("level") == "error":
            errors.append(f"log: {p['entry'].get('text')} ({p['entry'].get('url', '')})")

    def call(method: str, **params) -> dict:
        i = next(ids)
        ws.send(json.dumps({"id": i, "method": method, "params": params}))
        while True:
            msg = json.loads(ws.recv(timeout=timeout))
            if msg.get("id") == i:
                return msg.get("result", {})
            note(msg)

    for domain in ("Page", "Runtime", "Log"):
        call(f"{domain}.enable")
    call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1, mobile=False)
    call("Page.navigate", url=url)
    end, ready = time.time() + timeout, False
    while not ready and time.time() < end:
        ready = bool(call("Runtime.evaluate", expression=f"Boolean({ready_js})", returnByValue=True)
                     .get("result", {}).get("value"))
        if not ready:
            time.sleep(0.25)
    if then_js:
        call("Runtime.evaluate", expression=then_js)
    time.sleep(1.0)  # a few more frames of the render loop
    text = call("Runtime.evaluate", expression="document.body.innerText", returnByValue=True)["result"]["value"]
    png = base64.b64decode(call("Page.captureScreenshot", format="png")["data"])
    return PageLoad(ready=ready, png=png, text=text, errors=errors)


def main(argv: list[str] | None = None) -> int:
    """`python tests/headless_browser.py URL_OR_FILE OUT.png [--size 1100x1400] [--ready JS] [--then JS]
    [--palette]`: a screenshot of a page (how docs/images/report*.png are made; docs/benchmark.md)."""
    import argparse
    from pathlib import Path

    p = argparse.ArgumentParser(prog="headless_browser", description=main.__doc__)
    p.add_argument("url", help="http(s) URL, or a local file (e.g. a report's index.html)")
    p.add_argument("out", help="PNG to write")
    p.add_argument("--size", default="1100x1400", help="viewport WIDTHxHEIGHT in pixels")
    p.add_argument("--ready", default="document.readyState === 'complete'", help="JavaScript condition to wait for")
    p.add_argument("--then", default="", help="JavaScript run before the screenshot (e.g. scroll to a section)")
    p.add_argument("--palette", action="store_true", help="save with 256 colours (a smaller file)")
    args = p.parse_args(argv)
    url = args.url if "://" in args.url else Path(args.url).resolve().as_uri()
    width, height = (int(x) for x in args.size.lower().split("x"))
    eager = "document.querySelectorAll('img').forEach(i => i.loading = 'eager')"  # lazy pictures load too
    page = load_page(url, f"({eager}, {args.ready})", size=(width, height), then_js=args.then)
    png = page.png
    if args.palette:
        import io

        from PIL import Image

        buf = io.BytesIO()
        Image.open(io.BytesIO(png)).convert("RGB").quantize(256).save(buf, format="PNG", optimize=True)
        png = buf.getvalue()
    Path(args.out).write_bytes(png)
    print(f"{args.out}: {len(png) // 1024} KB{'' if page.ready else ' (the ready condition never held)'}"
          + "".join(f"\n  page error: {e}" for e in page.errors))
    return 0 if page.ready and not page.errors else 1


if __name__ == "__main__":
    raise SystemExit(main())
