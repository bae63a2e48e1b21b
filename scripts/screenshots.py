"""Screenshots of the dashboard (native Rerun viewer under Xvfb, web viewer in headless
Chromium) for docs/dashboard.md.

For each run (default: ``diffpos emulate`` and ``diffpos emulate large``, recorded) it
converts the recording twice with ``diffpos to-rerun``: the whole run (the viewer opens at
its end: the default cursor) and the run up to its middle (``--end``: the cursor at a
mid-run moment), and takes one screenshot of each with each viewer:
``docs/img/dashboard_<run>_<moment>_<viewer>.png`` (halved, metadata stripped).

Needs (Debian 12): ``apt-get install -y xvfb chromium mesa-vulkan-drivers libgl1-mesa-dri
imagemagick``; the ``rerun`` executable of rerun-sdk next to this Python; Pillow (comes
with matplotlib). No GPU: both viewers render in software (Vulkan llvmpipe, SwiftShader),
which takes one to two minutes per native screenshot on a 2-core machine.

usage:
  python scripts/screenshots.py                          run both emulations, then shoot
  python scripts/screenshots.py --mcap default=a.mcap --mcap large=b.mcap   existing runs
  python scripts/screenshots.py --viewers web --out /tmp/shots
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
RERUN = Path(sys.executable).with_name("rerun")
try:  # the viewer binary itself (the script above is a Python wrapper that would orphan it)
    import rerun_cli

    if Path(rerun_cli.__file__).with_name("rerun").exists():
        RERUN = Path(rerun_cli.__file__).with_name("rerun")
except ImportError:  # pragma: no cover
    pass
DIFFPOS = [str(Path(sys.executable).with_name("diffpos"))]
WINDOW = (1600, 900)
#: an emulation per run name (20 s of emulated time; large in lockstep: as fast as the fusion)
RUNS = {
    "default": ["emulate", "--duration", "20", "--speed", "0"],
    "large": ["emulate", "large", "--duration", "20", "--speed", "0"],
}


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def emulate(name: str, out_dir: Path) -> Path:
    mcap = out_dir / f"{name}.mcap"
    cmd = [*DIFFPOS, *RUNS[name], "--record", str(mcap), "--dashboard", "off", "--no-progress"]
    print("run: diffpos", " ".join(cmd[1:]), flush=True)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return mcap


def convert(mcap: Path, out: Path, *, end_s: float | None = None, scenario: str | None = None
            ) -> Path:
    cmd = [*DIFFPOS, "to-rerun", str(mcap), "-o", str(out), "--json"]
    if scenario is not None:  # walls and stairs (a default-scenario recording has only the box)
        cmd += ["--scenario", scenario]
    if end_s is not None:
        cmd += ["--end", f"{end_s:g}"]
    res = subprocess.run(cmd, check=True, capture_output=True, text=True)
    info = json.loads(res.stdout)
    if not info.get("building"):
        raise SystemExit(f"{mcap}: no building in the recording")
    return out


# ------------------------------------------------------------------------------ native
class Xvfb:
    """A virtual X display for the native viewer (only when there is no display)."""

    def __init__(self) -> None:
        self.proc = None
        self.env = dict(os.environ)
        if os.environ.get("DISPLAY"):
            return
        display = f":{90 + os.getpid() % 9}"
        self.proc = subprocess.Popen(["Xvfb", display, "-screen", "0", "1920x1080x24",
                                      "-nolisten", "tcp"], stderr=subprocess.DEVNULL)
        runtime = Path(tempfile.mkdtemp(prefix="xdg-"))
        runtime.chmod(0o700)
        self.env |= {"DISPLAY": display, "XDG_RUNTIME_DIR": str(runtime)}
        sock = Path(f"/tmp/.X11-unix/X{display[1:]}")
        deadline = time.monotonic() + 20
        while not sock.exists():  # readiness: the server's socket
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise SystemExit("Xvfb did not start")
            time.sleep(0.05)

    def close(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(10)


def shoot_native(rrd: Path, png: Path, xvfb: Xvfb) -> None:
    """The native viewer's own screenshot option (an X screen grab of its Vulkan swapchain
    is black under Xvfb; see docs/dashboard.md)."""
    subprocess.run([str(RERUN), "--port", str(free_port()), "--window-size",
                    f"{WINDOW[0]}x{WINDOW[1]}", "--screenshot-to", str(png), str(rrd)],
                   env=xvfb.env, check=True, timeout=600, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)


# ------------------------------------------------------------------------------ web
class Chromium:
    """Headless Chromium driven over the DevTools protocol on a pipe (fds 3/4: no
    websocket library needed)."""

    def __init__(self) -> None:
        exe = shutil.which("chromium") or shutil.which("chromium-browser")
        if exe is None:
            raise SystemExit("chromium not found (apt-get install -y chromium)")
        to_chrome_r, self._w = os.pipe()
        self._r, from_chrome_w = os.pipe()

        def fds() -> None:  # the child's fds 3 (commands in) and 4 (replies out)
            x, y = os.dup(to_chrome_r), os.dup(from_chrome_w)  # above 4: no clash
            os.dup2(x, 3)
            os.dup2(y, 4)
            os.set_inheritable(3, True)
            os.set_inheritable(4, True)

        self.profile = tempfile.mkdtemp(prefix="chromium-")
        self.proc = subprocess.Popen(
            [exe, "--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
             "--remote-debugging-pipe", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             "--ignore-gpu-blocklist", f"--window-size={WINDOW[0]},{WINDOW[1]}",
             f"--user-data-dir={self.profile}", "about:blank"],
            preexec_fn=fds, close_fds=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._id = 0
        self._buf = b""

    def call(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self._w, json.dumps(msg).encode() + b"\0")
        while True:
            while b"\0" not in self._buf:
                chunk = os.read(self._r, 1 << 20)
                if not chunk:
                    raise SystemExit("chromium exited")
                self._buf += chunk
            raw, self._buf = self._buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)
        shutil.rmtree(self.profile, ignore_errors=True)


def _loaded(png: bytes) -> bool:
    """The viewer has drawn its panels: thousands of colours (plots, 3D view, text); its
    loading screen (dark, one line of text) has a few hundred at most (threshold 1500)."""
    import io

    img = Image.open(io.BytesIO(png)).convert("RGB")
    return len(img.getcolors(maxcolors=1 << 20) or ()) > 1500


def shoot_web(rrd: Path, png: Path, chrome: Chromium) -> None:
    """``rerun --serve-web FILE`` and a screenshot of its page once the viewer has drawn the
    data: the page streams the file from the gRPC server for minutes in software rendering,
    so it is captured once it has drawn its panels and four captures 10 s apart agree
    within 2 % in PNG size (at most 10 minutes; then the last capture, with a warning)."""
    web, grpc = free_port(), free_port()
    server = subprocess.Popen([str(RERUN), "--serve-web", "--web-viewer-port", str(web),
                               "--port", str(grpc), str(rrd)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        url = (f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}"
               "%2Fproxy")
        target = chrome.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = chrome.call("Target.attachToTarget",
                              {"targetId": target, "flatten": True})["sessionId"]
        chrome.call("Emulation.setDeviceMetricsOverride", {
            "width": WINDOW[0], "height": WINDOW[1], "deviceScaleFactor": 1, "mobile": False},
            session)
        chrome.call("Page.navigate", {"url": url}, session)
        deadline, sizes, shot = time.monotonic() + 600, [], b""
        while time.monotonic() < deadline:
            time.sleep(10)  # poll period of a screen that settles (not a synchronisation)
            shot = base64.b64decode(chrome.call("Page.captureScreenshot", {"format": "png"},
                                                session)["data"])
            sizes = [*sizes, len(shot)][-4:] if _loaded(shot) else []
            if len(sizes) == 4 and max(sizes) - min(sizes) < 0.02 * max(sizes):
                break
        else:
            print(f"warning: {rrd}: the web viewer did not settle in 10 minutes", flush=True)
        png.write_bytes(shot)
        chrome.call("Target.closeTarget", {"targetId": target})
    finally:
        server.terminate()
        server.wait(10)


def shrink(png: Path, dest: Path) -> None:
    """At most 1600 wide (the native viewer's 3200x1800 halved), no metadata, palette PNG:
    docs stay small."""
    img = Image.open(png).convert("RGB")
    if img.width > WINDOW[0]:
        img = img.resize((img.width // 2, img.height // 2), Image.LANCZOS)
    img.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(dest, optimize=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mcap", action="append", default=[], metavar="NAME=FILE",
                    help="use this recording instead of running the emulation NAME")
    ap.add_argument("--runs", nargs="+", default=list(RUNS), help="default: default large")
    ap.add_argument("--viewers", nargs="+", default=["native", "web"])
    ap.add_argument("--moments", nargs="+", default=["end", "midrun"])
    ap.add_argument("--mid-s", type=float, default=10.0, metavar="S",
                    help="the mid-run moment [s after the first anchor state] (default 10: "
                         "the middle of the 20 s runs)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "img"),
                    help="folder (default docs/img/)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    given = dict(x.split("=", 1) for x in args.mcap)
    work = Path(tempfile.mkdtemp(prefix="diffpos-shots-"))
    xvfb = Xvfb() if "native" in args.viewers else None
    chrome = Chromium() if "web" in args.viewers else None
    try:
        for name in args.runs:
            mcap = Path(given[name]) if name in given else emulate(name, work)
            mid = args.mid_s
            rrds = {m: convert(mcap, work / f"{name}_{m}.rrd", scenario=name,
                               end_s=mid if m == "midrun" else None) for m in args.moments}
            for moment, rrd in rrds.items():
                for viewer in args.viewers:
                    raw = work / f"{name}_{moment}_{viewer}.png"
                    t0 = time.monotonic()
                    if viewer == "native":
                        shoot_native(rrd, raw, xvfb)
                    else:
                        shoot_web(rrd, raw, chrome)
                    dest = out / f"dashboard_{name}_{moment}_{viewer}.png"
                    shrink(raw, dest)
                    print(f"{dest}  ({time.monotonic() - t0:.0f} s, mid-run = {mid} s)",
                          flush=True)
    finally:
        if chrome is not None:
            chrome.close()
        if xvfb is not None:
            xvfb.close()
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
