#!/usr/bin/env python3
"""Screenshot of rerun's web viewer showing a simulated body, taken with headless Chromium.

    .venv/bin/python launch_scripts/rerun_screenshot.py --out docs/img/rerun_web_viewer.png
    .venv/bin/python launch_scripts/rerun_screenshot.py --scene cantilever --steps 120 \\
        --set body.mesh.cell=0.05 --out /tmp/shot.png

Runs the scene headless with mdss_ros.record.rerun_logger in mode "serve" (an in-process
gRPC server plus rerun's web viewer on free local ports), opens the viewer in Debian's
`chromium` (--headless=new, software WebGL) through the DevTools protocol, and saves a
screenshot once two consecutive captures agree (the viewer has loaded and drawn).
Needs `apt-get install chromium`. Exit code 0 with the PNG written, 1 on failure.
"""
import argparse
import base64
import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class DevTools:
    """The smallest Chrome DevTools Protocol client: one page, JSON commands over a websocket."""

    def __init__(self, ws_url, timeout=60.0):
        host_port, path = ws_url[len("ws://"):].split("/", 1)
        host, port = host_port.rsplit(":", 1)
        self.sock = socket.create_connection((host, int(port)), timeout=timeout)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET /{path} HTTP/1.1\r\nHost: {host_port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
        buf = b""
        while b"\r\n\r\n" not in buf:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("DevTools closed the connection during the handshake")
            buf += chunk
        if b" 101 " not in buf.split(b"\r\n", 1)[0]:
            raise ConnectionError(f"DevTools handshake failed: {buf[:200]!r}")
        self.rest = buf.split(b"\r\n\r\n", 1)[1]
        self.next_id = 0

    def _send(self, text):
        data, mask = text.encode(), os.urandom(4)
        n = len(data)
        head = b"\x81" + (bytes([0x80 | n]) if n < 126 else
                          bytes([0x80 | 126]) + struct.pack(">H", n) if n < 65536 else
                          bytes([0x80 | 127]) + struct.pack(">Q", n))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def _read(self, n):
        while len(self.rest) < n:
            chunk = self.sock.recv(1 << 20)
            if not chunk:
                raise ConnectionError("DevTools connection closed")
            self.rest += chunk
        out, self.rest = self.rest[:n], self.rest[n:]
        return out

    def _recv(self):
        msg = b""
        while True:
            b0, b1 = self._read(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read(8))[0]
            msg += self._read(n)
            if b0 & 0x80:
                if b0 & 0x0F == 0x1:
                    return json.loads(msg.decode())
                msg = b""                       # ping/pong/binary: not for us

    def call(self, method, **params):
        self.next_id += 1
        self._send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            reply = self._recv()
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})


def screenshot(url, out, width=1400, height=860, wait_s=60.0, settle_s=4.0):
    """Open url in headless Chromium and write a PNG to out once the page stopped changing."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        raise RuntimeError("chromium is not installed (apt-get install chromium)")
    port = free_port()
    profile = tempfile.mkdtemp(prefix="mdss_chromium_")
    proc = subprocess.Popen([exe, "--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                             "--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--no-first-run",
                             f"--user-data-dir={profile}", f"--window-size={width},{height}",
                             f"--remote-debugging-port={port}", url],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        t_end = time.monotonic() + wait_s
        page = None
        while page is None and time.monotonic() < t_end:
            try:
                targets = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=2))
                page = next((t for t in targets if t.get("type") == "page"), None)
            except OSError:
                pass
            time.sleep(0.2)
        if page is None:
            raise RuntimeError("chromium did not open its DevTools endpoint")
        tools = DevTools(page["webSocketDebuggerUrl"])
        previous, png = None, None
        while time.monotonic() < t_end:
            time.sleep(settle_s)
            png = base64.b64decode(tools.call("Page.captureScreenshot", format="png")["data"])
            if previous is not None and png == previous and len(png) > 50_000:
                break
            previous = png
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_bytes(png)
        return out
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
        shutil.rmtree(profile, ignore_errors=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="cantilever")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", default=[])
    ap.add_argument("--steps", type=int, default=90)
    ap.add_argument("--out", default="docs/img/rerun_web_viewer.png")
    ap.add_argument("--wait", type=float, default=90.0, help="seconds to wait for the viewer to draw")
    args = ap.parse_args(argv)

    from mdss_ros.record.rerun_logger import RerunLogger
    from mdss_ros.scene import read_yaml
    from mdss_ros.simulator import Simulator
    from mdss_ros.timeline import TimelinePlayer
    overrides = {}
    for item in args.set:
        k, _, v = item.partition("=")
        overrides[k] = read_yaml(v)
    sim = Simulator(args.scene, overrides=overrides or None)
    web, grpc = free_port(), free_port()
    log = RerunLogger(sim, mode="serve", web_port=web, grpc_port=grpc)
    player = TimelinePlayer(sim.scene["timeline"])
    log.log_step()
    for _ in range(args.steps):
        player.apply_due(sim)
        sim.step()
        log.log_step(sim.stats().get("step_ms"))
    log.rec.flush()
    url = f"http://127.0.0.1:{web}/?url={urllib.parse.quote(log.url, safe='')}"
    print(f"rerun_screenshot: {args.steps} steps of {sim.scene.name} served at {log.url}; viewer {url}", flush=True)
    try:
        screenshot(url, args.out, wait_s=args.wait)
    except (RuntimeError, OSError) as err:
        print(f"rerun_screenshot: {err}", file=sys.stderr)
        return 1
    print(f"rerun_screenshot: wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
