"""Headless Chromium for the player's tests and benchmarks: Debian's `chromium` driven by Playwright (PyPI), with
software WebGL2 (SwiftShader) where there is no GPU, and a local static file server for a player folder.

    with static_server(folder) as url, chromium_page() as page:
        page.goto(url + "index.html?frame=0&paused=1&view=dataset")
        wait_drawn(page, 0)

Playwright's own browser download is never used (executable_path); the background-networking flags keep
Chromium from calling out (this machine has no network). The GPU flags give software GL; `hardware=True`
leaves GL to Chromium (a machine with a GPU). `args` adds launch flags: AUTOPLAY (sound may start without a click),
REFUSE_AUTOPLAY (it may not, whatever Chromium's default), fake_microphone(wav) (getUserMedia granted without asking
and fed from a WAV file, looped)."""

from __future__ import annotations

import contextlib
import functools
import http.server
import os
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Iterator

SOFTWARE_GL = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
AUTOPLAY = ["--autoplay-policy=no-user-gesture-required"]
REFUSE_AUTOPLAY = ["--autoplay-policy=user-gesture-required"]
QUIET = ["--no-sandbox", "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", "--disable-quic", "--disable-default-apps", "--metrics-recording-only"]


def chromium_path() -> str | None:
    """Debian's chromium (or a Chrome) on PATH, else None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def fake_microphone(wav: str | Path) -> list[str]:
    """Launch flags for a microphone that plays `wav` (looped) with permission granted without a prompt."""
    return ["--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
            f"--use-file-for-fake-audio-capture={Path(wav).resolve()}"]


def browser_missing() -> str | None:
    """Why the browser tests cannot run here (None when they can)."""
    try:
        import playwright  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install -r requirements/dev.txt)"
    if chromium_path() is None:
        return "no chromium on PATH (apt-get install chromium)"
    return None


@contextlib.contextmanager
def _niced(executable: str, nice: int) -> Iterator[str]:
    """`executable` itself, or (nice > 0) a wrapper script that starts it at that lower CPU priority.

    Two things defeated a plain `nice -n`: Playwright starts the browser in a session of its own, and with the
    kernel's autogroups (sched_autogroup_enabled, on by default) the scheduler shares the CPU between sessions'
    groups before it looks at a thread's nice, so the wrapper sets its session's group nice too
    (/proc/self/autogroup); and Chromium sets its threads' priorities itself (nice 0, -8 for the GPU process and
    display-critical threads), which it can when it has CAP_SYS_NICE, as under root, so there the wrapper drops
    that capability (util-linux's setpriv). Measured under root on a 2-core machine: every thread of the browser
    had nice 0 or -8 before, and its session's group took as much CPU as drive's."""
    if nice <= 0:
        yield executable
        return
    keep = ""
    if os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            raise RuntimeError("running as root, the browser's nice needs setpriv (util-linux) to hold: Chromium "
                               "raises its threads' priorities otherwise")
        keep = "setpriv --inh-caps=-sys_nice --bounding-set=-sys_nice "
    with tempfile.TemporaryDirectory(prefix="geoavatar-browser-") as folder:
        wrapper = Path(folder) / "chromium"
        wrapper.write_text(f'#!/bin/sh\n(echo {int(nice)} > /proc/self/autogroup) 2>/dev/null\n'
                           f'exec nice -n {int(nice)} {keep}"{executable}" "$@"\n')
        wrapper.chmod(0o755)
        yield str(wrapper)


@contextlib.contextmanager
def chromium_page(width: int = 640, height: int = 480, hardware: bool = False, console: list | None = None,
                  nice: int = 0, args: list[str] | None = None):
    """A Playwright page in headless Chromium (device scale 1); `console` collects the page's console lines;
    `nice` > 0 runs the browser at a lower CPU priority (a benchmark sharing 2 cores with the live pipeline);
    `args`: more launch flags (AUTOPLAY, REFUSE_AUTOPLAY, fake_microphone(wav))."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright, _niced(chromium_path(), nice) as executable:  # a fresh profile per launch
        flags = QUIET + ([] if hardware else SOFTWARE_GL) + list(args or [])
        browser = playwright.chromium.launch(executable_path=executable, headless=True, args=flags)
        try:
            page = browser.new_page(viewport={"width": width, "height": height}, device_scale_factor=1)
            if console is not None:
                page.on("console", lambda message: console.append(f"{message.type}: {message.text}"))
                page.on("pageerror", lambda error: console.append(f"pageerror: {error}"))
            yield page
        finally:
            browser.close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:  # no request lines on stderr
        pass


@contextlib.contextmanager
def static_server(folder: str | Path, host: str = "127.0.0.1", port: int = 0) -> Iterator[str]:
    """Serve `folder` over HTTP on loopback in a thread; yields its base URL ("http://127.0.0.1:PORT/")."""
    handler = functools.partial(_QuietHandler, directory=str(folder))
    server = http.server.ThreadingHTTPServer((host, port), handler)
    thread = threading.Thread(target=server.serve_forever, name="geoavatar-static", daemon=True)
    thread.start()
    try:
        yield f"http://{host}:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=5.0)


def wait_drawn(page, frame: int, timeout_s: float = 120.0) -> None:
    """Wait until the page announces `frame` drawn and sorted (document.body.dataset.drawnFrame)."""
    page.wait_for_function(
        "f => document.body.dataset.drawnFrame === String(f) || document.body.dataset.error !== undefined",
        arg=frame, timeout=timeout_s * 1000)
    error = page.evaluate("document.body.dataset.error")
    if error is not None:
        raise RuntimeError(f"the player failed: {error}")


def canvas_rgb(page):
    """[H, W, 3] uint8 numpy image of the player's canvas (a PNG screenshot of the element)."""
    import io

    import numpy as np
    from PIL import Image

    png = page.locator("#stage canvas").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


__all__ = ["AUTOPLAY", "REFUSE_AUTOPLAY", "browser_missing", "canvas_rgb", "chromium_page", "chromium_path",
           "fake_microphone", "static_server", "wait_drawn"]
