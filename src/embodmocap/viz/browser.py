"""Headless Chromium for screenshots of the web viewer (README pictures, the viewer's browser test).

Uses Debian's ``/usr/bin/chromium`` (``.ci/install-chromium`` installs it) and talks to it over the
Chrome DevTools protocol with the ``websockets`` package viser already needs. Flags keep it off the
network (this machine has none) and make WebGL run in software.
"""

from __future__ import annotations

import base64
import json
import subprocess
import time
import urllib.request
from pathlib import Path

import numpy as np

CHROMIUM = Path("/usr/bin/chromium")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--remote-debugging-port=0")


class HeadlessChromium:
    """One headless Chromium page showing ``url``; use as a context manager.

    Args:
        url: the page to open.
        user_data_dir: a fresh folder for the browser profile (Chromium writes its DevTools port there).
        size: window width and height, pixels.
        timeout_s: how long to wait for the browser to come up.
    """

    def __init__(self, url: str, user_data_dir: Path, size: tuple[int, int] = (1280, 800), timeout_s: float = 30.0):
        from websockets.sync.client import connect

        if not CHROMIUM.exists():
            raise FileNotFoundError(f"{CHROMIUM} is missing: run .ci/install-chromium (Debian's chromium package)")
        user_data_dir = Path(user_data_dir)
        self._proc = subprocess.Popen(
            [str(CHROMIUM), *FLAGS, f"--user-data-dir={user_data_dir}", f"--window-size={size[0]},{size[1]}", url],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            port_file = user_data_dir / "DevToolsActivePort"
            deadline = time.monotonic() + timeout_s
            while not (port_file.exists() and port_file.read_text().strip()):
                if time.monotonic() > deadline:
                    raise TimeoutError("Chromium did not open its DevTools port")
                time.sleep(0.05)
            port = int(port_file.read_text().split()[0])
            while True:
                pages = [t for t in json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list"))
                         if t["type"] == "page"]
                if pages or time.monotonic() > deadline:
                    break
                time.sleep(0.1)
            self._ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=timeout_s)
        except BaseException:
            self._proc.terminate()
            raise
        self._id = 0

    def call(self, method: str, **params) -> dict:
        """Send one DevTools command and return its result."""
        self._id += 1
        self._ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self._ws.recv(timeout=60))
            if msg.get("id") == self._id:
                return msg["result"]

    def screenshot_png(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def screenshot(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB of the page as drawn now."""
        import cv2

        img = cv2.imdecode(np.frombuffer(self.screenshot_png(), np.uint8), cv2.IMREAD_COLOR)
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        try:
            self._ws.close()
        finally:
            self._proc.terminate()
            self._proc.wait(timeout=10)

    def __enter__(self) -> "HeadlessChromium":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
