"""``python -m simfleet.screenshots RRD --out DIR``: a recording in Rerun's web viewer, headless, saved as PNGs.

The recording is served by the ``rerun`` CLI of the installed wheel (``--serve-web``: the web
viewer over HTTP and the recording over gRPC, on free ports) and opened in headless Chromium
with a software GL (SwiftShader), driven through the DevTools protocol over a pipe
(``--remote-debugging-pipe``: NUL-separated JSON on file descriptors 3 and 4, so no websocket
client is needed). A picture is taken once the viewer has drawn the same frame twice in a row:
the wasm is loaded, the recording streamed in and the layout settled. ``--shot NAME@X,Y`` clicks
at X,Y (CSS pixels) before that picture, e.g. to open a tab of the layout.

Every process started here is stopped on the way out; a failure is one line on stderr and exit 1.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import json
import os
import select
import shutil
import signal
import socket
import subprocess
import struct
import sys
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
SETTLE_INTERVAL_S = 4.0  # between two frames compared
SETTLE_FRAMES = 3  # consecutive nearly unchanged frames that make a settled view
# Share of pixel bytes two frames of a settled view may differ by: the viewer's top bar redraws
# its own counters from frame to frame, while a panel still filling in changes several per cent.
SETTLE_CHANGE = 0.002
DEFAULT_TIMEOUT_S = 600.0  # SwiftShader renders on the CPU: on a busy machine a frame can take a minute


class ScreenshotError(RuntimeError):
    """Why the pictures could not be taken (one line for the user)."""


@dataclass(frozen=True)
class Shot:
    """One picture: its file name and the clicks (CSS px) made in the viewer before it."""

    name: str
    clicks: tuple[tuple[int, int], ...] = ()


def free_port() -> int:
    """A TCP port nobody listens on now (the OS's choice)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def find_executable(names: Sequence[str], beside: Path | None = None) -> str:
    """The first of ``names`` found beside ``beside`` (e.g. the venv's bin) or on the PATH."""
    for name in names:
        if beside is not None and (beside / name).is_file():
            return str(beside / name)
        found = shutil.which(name)
        if found:
            return found
    raise ScreenshotError(f"none of {', '.join(names)} found on the PATH")


def viewer_url(web_port: int, grpc_port: int) -> str:
    """The web viewer's page, told to open the gRPC proxy that serves the recording."""
    proxy = f"rerun+http://127.0.0.1:{grpc_port}/proxy"
    return f"http://127.0.0.1:{web_port}/?url={urllib.parse.quote(proxy, safe='')}&renderer=webgl&hide_welcome_screen"


def wait_http(url: str, timeout_s: float, proc: subprocess.Popen, what: str) -> None:
    """Until ``url`` answers (``proc`` must stay alive meanwhile)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise ScreenshotError(f"{what} exited with code {proc.returncode} before serving {url}")
        try:
            with urllib.request.urlopen(url, timeout=2.0):
                return
        except (urllib.error.URLError, OSError):
            time.sleep(0.2)
    raise ScreenshotError(f"{what} did not serve {url} within {timeout_s:.0f} s")


@contextlib.contextmanager
def started(args: Sequence[str], log_path: Path, **kw) -> Iterator[subprocess.Popen]:
    """A child process, its output to ``log_path``; terminated (then killed) on the way out."""
    with open(log_path, "wb") as log:
        # Its own process group: the venv's `rerun` is a wrapper that starts the real binary as a
        # child, and Chromium starts helpers; stopping the group stops them all.
        proc = subprocess.Popen(list(args), stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True, **kw)
    try:
        yield proc
    finally:
        for sig, wait_s in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, sig)
            try:
                proc.wait(timeout=wait_s)
                break
            except subprocess.TimeoutExpired:
                continue


class DevTools:
    """The Chrome DevTools protocol over ``--remote-debugging-pipe``: one page target, flat sessions."""

    def __init__(self, to_browser: int, from_browser: int, proc: subprocess.Popen, deadline: float):
        self._out, self._in, self._proc, self._deadline = to_browser, from_browser, proc, deadline
        self._buf = b""
        self._next_id = 0
        self.session: str | None = None

    def call(self, method: str, params: dict | None = None, timeout_s: float | None = None,
             session: bool = True) -> dict:
        """Send one command and wait for its answer, at most ``timeout_s`` (default: until the
        deadline of the whole capture); events meanwhile are dropped."""
        self._next_id += 1
        msg = {"id": self._next_id, "method": method, "params": params or {}}
        if session and self.session is not None:
            msg["sessionId"] = self.session
        os.write(self._out, json.dumps(msg).encode() + b"\0")
        deadline = self._deadline if timeout_s is None else time.monotonic() + timeout_s
        while True:
            reply = self._read(deadline, method)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise ScreenshotError(f"chromium: {method}: {reply['error'].get('message', reply['error'])}")
                return reply.get("result", {})

    def _read(self, deadline: float, method: str) -> dict:
        while b"\0" not in self._buf:
            if time.monotonic() > deadline:
                raise ScreenshotError(f"chromium did not answer {method} in time")
            ready, _, _ = select.select([self._in], [], [], 0.5)
            if ready:
                chunk = os.read(self._in, 1 << 20)
                if not chunk:
                    raise ScreenshotError(f"chromium closed the DevTools pipe (exit code {self._proc.poll()})")
                self._buf += chunk
        line, self._buf = self._buf.split(b"\0", 1)
        return json.loads(line)

    def attach_page(self, width: int, height: int) -> None:
        targets = self.call("Target.getTargets", session=False)["targetInfos"]
        page = next((t for t in targets if t["type"] == "page"), None)
        if page is None:
            page = {"targetId": self.call("Target.createTarget", {"url": "about:blank"}, session=False)["targetId"]}
        self.session = self.call("Target.attachToTarget", {"targetId": page["targetId"], "flatten": True},
                                 session=False)["sessionId"]
        self.call("Emulation.setDeviceMetricsOverride",
                  {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False})

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"})["data"])

    def click(self, x: int, y: int) -> None:
        for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", {"type": kind, "x": x, "y": y, "button": "left", "clickCount": 1})

    def evaluate(self, expression: str):
        return self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True})["result"].get("value")


def _chromium_args(exe: str, profile: Path, width: int, height: int) -> list[str]:
    args = [exe, "--headless=new", "--remote-debugging-pipe", f"--user-data-dir={profile}",
            f"--window-size={width},{height}", "--hide-scrollbars", "--no-first-run", "--no-default-browser-check",
            "--disable-extensions", "--mute-audio",
            # WebGL on the CPU: there is no GPU on the machines this runs on.
            "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        args.append("--no-sandbox")  # Chromium refuses to start as root with its sandbox
    return args + ["about:blank"]


def png_bytes(png: bytes) -> bytes:
    """A PNG's (filtered) pixel rows: its IDAT chunks inflated (stdlib only; enough to compare two frames)."""
    pos, data = 8, []
    while pos + 8 <= len(png):
        (length,) = struct.unpack(">I", png[pos:pos + 4])
        kind = png[pos + 4:pos + 8]
        if kind == b"IDAT":
            data.append(png[pos + 8:pos + 8 + length])
        pos += 12 + length
    return zlib.decompress(b"".join(data))


def frame_change(a: bytes, b: bytes) -> float:
    """The share of pixel-row bytes that differ between two PNGs of one size (1.0: sizes differ)."""
    pa, pb = png_bytes(a), png_bytes(b)
    if len(pa) != len(pb):
        return 1.0
    diff = sum(x != y for x, y in zip(pa[::7], pb[::7]))  # a sample of the bytes is enough for a share
    return diff / max(len(pa[::7]), 1)


def settled_screenshot(dev: DevTools, deadline: float, proc: subprocess.Popen, say) -> bytes:
    """A frame nearly equal to the `SETTLE_FRAMES` taken before it, ``SETTLE_INTERVAL_S`` apart,
    once the viewer has started (a slow machine ingests a recording for a while: one quiet
    interval is not enough to say it is done)."""
    last, quiet = None, 0
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise ScreenshotError(f"the rerun server exited with code {proc.returncode}")
        state = dev.evaluate("typeof window._handle === 'undefined' ? 'loading' : "
                             "window._handle.has_panicked() ? window._handle.panic_message() : 'started'")
        if state not in ("loading", "started"):
            raise ScreenshotError(f"the web viewer crashed: {state}")
        if state == "started":
            png = dev.screenshot()
            change = 1.0 if last is None else frame_change(last, png)
            say(f"frame: {100 * change:.2f} % changed")
            quiet = quiet + 1 if change <= SETTLE_CHANGE else 0
            if quiet >= SETTLE_FRAMES:
                return png
            last = png
        else:
            say("loading the web viewer")
        time.sleep(SETTLE_INTERVAL_S)
    raise ScreenshotError("the web viewer did not settle on a picture in time")


def capture(rrd: Path, out_dir: Path, shots: Sequence[Shot], width: int = 1920, height: int = 1200,
            timeout_s: float = DEFAULT_TIMEOUT_S, say=lambda text: None) -> list[Path]:
    """Serve ``rrd``, open it in headless Chromium and save each of ``shots`` as ``out_dir/<name>.png``
    (``say`` gets a line of progress now and then)."""
    rrd = Path(rrd).resolve()
    if not rrd.is_file():
        raise ScreenshotError(f"{rrd}: no such recording")
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ScreenshotError(f"cannot create {out_dir}: {e.strerror or e}") from None
    rerun = find_executable(["rerun"], Path(sys.executable).parent)
    chromium = find_executable(CHROMIUM_NAMES)
    web_port, grpc_port = free_port(), free_port()
    deadline = time.monotonic() + timeout_s
    written = []
    with tempfile.TemporaryDirectory(prefix="driveby-shots-") as tmp:
        tmp = Path(tmp)
        serve = [rerun, "--serve-web", "--web-viewer-port", str(web_port), "--port", str(grpc_port), str(rrd)]
        with started(serve, tmp / "rerun.log") as server:
            wait_http(f"http://127.0.0.1:{web_port}/", 60.0, server, "rerun --serve-web")
            to_r, to_w = os.pipe()  # us → chromium (its fd 3)
            from_r, from_w = os.pipe()  # chromium (its fd 4) → us

            def pipes_as_3_and_4():  # (3 and 4 are in pass_fds too: kept open when the rest are closed)
                os.dup2(to_r, 3)
                os.dup2(from_w, 4)

            try:
                with started(_chromium_args(chromium, tmp / "profile", width, height), tmp / "chromium.log",
                             pass_fds=(to_r, from_w, 3, 4), preexec_fn=pipes_as_3_and_4) as browser:
                    os.close(to_r)
                    os.close(from_w)
                    to_r = from_w = -1
                    dev = DevTools(to_w, from_r, browser, deadline)
                    dev.attach_page(width, height)
                    dev.call("Page.enable")
                    dev.call("Page.navigate", {"url": viewer_url(web_port, grpc_port)})
                    for shot in shots:
                        for x, y in shot.clicks:
                            dev.click(x, y)
                        png = settled_screenshot(dev, deadline, server, say)
                        path = out_dir / f"{shot.name}.png"
                        path.write_bytes(png)
                        written.append(path)
                    with contextlib.suppress(ScreenshotError):
                        dev.call("Browser.close", session=False, timeout_s=5.0)
            finally:
                for fd in (to_r, to_w, from_r, from_w):
                    if fd >= 0:
                        with contextlib.suppress(OSError):
                            os.close(fd)
    return written


def parse_shot(spec: str) -> Shot:
    """``NAME`` or ``NAME@X,Y[;X,Y...]``: a picture and the clicks (CSS px) made before it."""
    name, _, clicks = spec.partition("@")
    pts = []
    for c in filter(None, clicks.split(";")):
        try:
            x, y = (int(v) for v in c.split(","))
        except ValueError:
            raise ScreenshotError(f"--shot {spec!r}: expected NAME or NAME@X,Y[;X,Y...] in pixels") from None
        pts.append((x, y))
    if not name or "/" in name:
        raise ScreenshotError(f"--shot {spec!r}: a file name (without .png) is needed")
    return Shot(name, tuple(pts))


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m simfleet.screenshots", description=__doc__.splitlines()[0])
    p.add_argument("rrd", help="the Rerun recording (.rrd) to render")
    p.add_argument("--out", default="docs/img", help="directory for the PNGs (default docs/img)")
    p.add_argument("--shot", action="append", default=None, metavar="NAME[@X,Y;...]",
                   help="a picture to save as NAME.png, after clicking at X,Y (CSS px, e.g. on a tab); "
                        "repeatable, taken in order (default: demo-view)")
    p.add_argument("--size", default="1920x1200", help="viewport WIDTHxHEIGHT in CSS pixels (default 1920x1200)")
    p.add_argument("--verbose", action="store_true", help="say what is happening on stderr")
    p.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, help="seconds for everything (default 600)")
    args = p.parse_args(argv)
    try:
        try:
            width, height = (int(v) for v in args.size.lower().split("x"))
        except ValueError:
            raise ScreenshotError(f"--size {args.size!r}: expected WIDTHxHEIGHT") from None
        shots = [parse_shot(spec) for spec in args.shot or ["demo-view"]]
        say = (lambda text: print(f"screenshots: {text}", file=sys.stderr, flush=True)) if args.verbose else \
            (lambda text: None)
        for path in capture(Path(args.rrd), Path(args.out), shots, width, height, args.timeout, say):
            print(path)
    except ScreenshotError as e:
        print(f"screenshots: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
