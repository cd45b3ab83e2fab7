"""Headless Chromium for the web-page tests: Debian's ``chromium`` driven by Python Playwright
(never a browser downloaded by ``playwright install``), the service served by uvicorn on a free
local port, and a guarded page that records console errors and page errors, refuses every request
that leaves the machine, and takes screenshots.

The set-up installs the Debian packages ``chromium`` and ``chromium-driver`` when
``/usr/bin/chromium`` is missing (as root, with apt-get); when that is impossible the tests fail
with a message saying what to install, they are never skipped.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

CHROMIUM = Path("/usr/bin/chromium")
DEBIAN_PACKAGES = ("chromium", "chromium-driver")
#: Held while installing them, so that parallel test processes install once.
INSTALL_LOCK = Path("/tmp/compasscal-chromium-install.lock")
#: Flags for this machine: no sandbox (root in a container), no GPU, and none of Chromium's own
#: traffic (updates, sync, field trials...) towards a network that is closed anyway. The resolver
#: rule is a second fence behind the page's request filter: no host name but localhost resolves.
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--disable-default-apps", "--disable-extensions",
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE localhost, EXCLUDE 127.0.0.1",
]
LOCAL_HOSTS = {"127.0.0.1", "localhost", "::1", "[::1]"}
#: Default Playwright timeout (ms) of every action and navigation: nothing waits for ever.
ACTION_TIMEOUT_MS = 15_000


class BrowserSetupError(RuntimeError):
    """Chromium is missing and could not be installed."""


def ensure_chromium(binary: Path = CHROMIUM, timeout_s: float = 900.0) -> Path:
    """Debian's Chromium at ``binary``, installing ``chromium`` and ``chromium-driver`` with apt-get
    when it is missing. Raises :class:`BrowserSetupError` with what to do when it cannot."""
    if binary.exists():
        return binary
    how = f"install the Debian packages: apt-get install -y {' '.join(DEBIAN_PACKAGES)}"
    if os.geteuid() != 0:
        raise BrowserSetupError(f"{binary} is missing and the tests are not running as root; {how}")
    apt = shutil.which("apt-get")
    if apt is None:
        raise BrowserSetupError(f"{binary} is missing and there is no apt-get on this machine; {how}")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    log: list[str] = []

    def apt_get(*args: str) -> bool:
        try:
            r = subprocess.run([apt, *args], env=env, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            log.append(f"apt-get {' '.join(args)}: timed out after {timeout_s:.0f} s")
            return False
        if r.returncode != 0:
            log.append(f"apt-get {' '.join(args)}: exit {r.returncode}: {(r.stderr or r.stdout).strip()[-1500:]}")
        return r.returncode == 0

    # wait for dpkg's lock rather than fail on it (another apt-get, e.g. unattended upgrades)
    install = ("-o", "DPkg::Lock::Timeout=600", "install", "-y", *DEBIAN_PACKAGES)
    # one installer at a time: under pytest-xdist each worker process gets here at once
    with open(INSTALL_LOCK, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        # the package lists may be missing or stale: update once and retry
        if not binary.exists() and not apt_get(*install) and apt_get("update"):
            apt_get(*install)
    if not binary.exists():
        what = "\n".join(log) or f"apt-get reported success, yet {binary} is still missing"
        raise BrowserSetupError(f"{binary} is missing and apt-get could not install {' and '.join(DEBIAN_PACKAGES)}:\n"
                                f"{what}\n{how}")
    return binary


def launch(playwright: Any, headless: bool = True) -> Any:
    """Debian's Chromium under Playwright (sync API)."""
    binary = ensure_chromium()
    return playwright.chromium.launch(executable_path=str(binary), headless=headless, args=CHROMIUM_ARGS,
                                      timeout=30_000)


def is_local(url: str) -> bool:
    """Whether a request stays on this machine (data: and blob: URLs never leave the page)."""
    parts = urlsplit(url)
    if parts.scheme in ("data", "blob", "about"):
        return True
    return parts.scheme in ("http", "https", "ws", "wss") and (parts.hostname or "") in LOCAL_HOSTS


# ------------------------------------------------------------------------------------------ server

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def serve(app: Any, timeout_s: float = 30.0) -> Iterator[str]:
    """Serve an ASGI app with uvicorn in a thread of its own on a free local port; yields its base URL
    and stops it (lifespan shutdown included) on exit."""
    import uvicorn

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                                           timeout_graceful_shutdown=3, lifespan="on"))
    failure: list[BaseException] = []

    def run() -> None:
        try:
            server.run()
        except BaseException as e:  # noqa: BLE001 - reported to the test
            failure.append(e)

    thread = threading.Thread(target=run, name=f"uvicorn-{port}", daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout_s
    while not server.started:
        if failure or not thread.is_alive():
            raise RuntimeError(f"the service did not start on port {port}: {failure[0] if failure else 'thread ended'}")
        if time.monotonic() > deadline:
            server.should_exit = True
            raise RuntimeError(f"the service did not start on port {port} within {timeout_s:.0f} s")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(15)
        if thread.is_alive():  # a stuck connection: make uvicorn give up on it
            server.force_exit = True
            thread.join(5)


# ------------------------------------------------------------------------------------------- pages

@dataclass
class Guard:
    """What a browser context did wrong: console errors, uncaught page errors, requests that would
    have left the machine. ``check()`` asserts there were none (except ``allowed`` substrings)."""

    console_errors: list[str] = field(default_factory=list)
    page_errors: list[str] = field(default_factory=list)
    external: list[str] = field(default_factory=list)
    allowed: list[str] = field(default_factory=list)

    def watch(self, page: Any) -> None:
        page.on("console", lambda msg: self.console_errors.append(f"{page.url}: {msg.text}")
                if msg.type == "error" else None)
        page.on("pageerror", lambda err: self.page_errors.append(f"{page.url}: {err}"))

    def route(self, route: Any) -> None:
        url = route.request.url
        if is_local(url):
            route.continue_()
        else:
            self.external.append(url)
            route.abort("blockedbyclient")

    def problems(self) -> list[str]:
        bad = [e for e in self.console_errors if not any(a in e for a in self.allowed)]
        return ([f"console error: {e}" for e in bad] + [f"page error: {e}" for e in self.page_errors]
                + [f"request leaving the machine (blocked): {u}" for u in self.external])

    def check(self) -> None:
        problems = self.problems()
        assert not problems, "the pages misbehaved:\n" + "\n".join(problems)


class Shots:
    """Full-page screenshots numbered in order into one directory; each is checked to be non-empty."""

    def __init__(self, directory: Path) -> None:
        self.dir = directory
        self.dir.mkdir(parents=True, exist_ok=True)
        self.taken: list[Path] = []

    def __call__(self, page: Any, name: str) -> Path:
        path = self.dir / f"{len(self.taken) + 1:02d}-{name}.png"
        page.screenshot(path=str(path), full_page=True, timeout=ACTION_TIMEOUT_MS)
        assert path.exists() and path.stat().st_size > 0, f"screenshot {path} is missing or empty"
        self.taken.append(path)
        return path

    def check(self) -> None:
        for path in self.taken:
            assert path.exists() and path.stat().st_size > 0, f"screenshot {path} is missing or empty"
            assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"screenshot {path} is not a PNG"


@contextmanager
def guarded_context(browser: Any, base_url: str, **kw: Any) -> Iterator[tuple[Any, Guard]]:
    """A fresh browser context (its own cookies) whose pages are watched by a :class:`Guard` and may
    load nothing from outside the machine. The guard is *not* checked here: call ``guard.check()``."""
    guard = Guard()
    context = browser.new_context(base_url=base_url, viewport={"width": 1280, "height": 900},
                                  service_workers="block", **kw)
    context.set_default_timeout(ACTION_TIMEOUT_MS)
    context.set_default_navigation_timeout(ACTION_TIMEOUT_MS)
    context.route("**/*", guard.route)
    context.on("page", guard.watch)
    try:
        yield context, guard
    finally:
        try:
            context.close()
        except Exception:  # noqa: BLE001 - the browser may already be gone; nothing left to close
            pass
