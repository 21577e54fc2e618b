#!/usr/bin/env python3
"""Sessions pinned to the process that holds them, through a real reverse proxy.

Several `voxlight serve` processes stand for StatefulSet pods, nginx (Debian) for the Gateway,
configured by deploy/nginx/voxlight_router.py the way deploy/k8s routes: `/p/<n>/` reaches
process n (prefix stripped), `/` reaches the processes whose /readyz says they take new
sessions. Checked, with scripted WebSocket clients and the web viewer in headless Chromium:

1. a session opened at the root is told its route; a second viewer joins through it and a
   dropped viewer reconnects through it, always on the same process;
2. full processes leave the root (`at_capacity` never reaches a client that retries; the root
   answers 503 when nobody takes sessions); a process started later takes new sessions and the
   old ones stay where they are;
3. SIGTERM on one process: readiness false, its viewers told (`draining`), new sessions on it
   refused with `draining`, its sessions still served, the others unaffected; at the drain
   deadline `bye`, exit 0, and the web viewer reopens its view on another process;
4. a process killed without a drain: the web viewer finds its route dead and the root alive
   and reopens its view on a process that takes it.

    python3 tests/deploy/routing_test.py --voxlight target/debug/voxlight

Needs nginx (apt-get install nginx), Python `websockets`, node with tests/web's playwright-core
and Chromium. Exits 1 when a check fails, 2 when it cannot run.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "deploy" / "nginx"))

from voxlight_router import Router  # noqa: E402

try:
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect
except ImportError:
    print("routing: cannot run: Python package `websockets` missing (pip install websockets)")
    sys.exit(2)

MAX_SESSIONS = 2
DRAIN_TIMEOUT_S = 15
STEP_S = 60.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Check:
    def __init__(self) -> None:
        self.failed = 0
        self.started = time.monotonic()

    def __call__(self, name: str, ok: bool, detail: str = "") -> bool:
        t = time.monotonic() - self.started
        print(f"{'ok  ' if ok else 'FAIL'} {name}{' — ' + detail if detail else ''} [{t:.1f} s]", flush=True)
        self.failed += not ok
        return ok


class Process:
    """One `voxlight serve` standing for pod `ordinal`."""

    def __init__(self, binary: str, ordinal: int, folder: Path) -> None:
        self.ordinal = ordinal
        self.port = free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.log_path = folder / f"voxlight-{ordinal}.log"
        self.log = open(self.log_path, "w")
        self.proc = subprocess.Popen(
            [binary, "serve", "--listen", self.address, "--route-prefix", f"/p/{ordinal}/",
             "--max-sessions", str(MAX_SESSIONS), "--no-preload", "--grace-period-s", "3",
             "--drain-timeout-s", str(DRAIN_TIMEOUT_S), "--default-dataset", "phantom:sphere"],
            stdout=self.log, stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + STEP_S
        while not self.health():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"process {ordinal} did not start:\n{self.log_path.read_text()[-2000:]}")
            time.sleep(0.2)

    def health(self) -> dict | None:
        try:
            with urllib.request.urlopen(f"http://{self.address}/healthz", timeout=2) as r:
                return json.load(r)
        except (urllib.error.URLError, OSError, ValueError):
            return None

    def sessions(self) -> int:
        health = self.health()
        return -1 if health is None else int(health["sessions"])


def http_get(url: str) -> tuple[int, str]:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.read().decode(errors="replace")
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode(errors="replace")
    except (urllib.error.URLError, OSError) as e:
        return 0, str(e)


def first_reply(ws) -> dict:
    """The first text message (frames skipped)."""
    while True:
        message = ws.recv(timeout=STEP_S)
        if isinstance(message, str):
            return json.loads(message)


def wait_for(ws, kind: str, timeout: float = STEP_S) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        message = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
        if isinstance(message, str):
            parsed = json.loads(message)
            if parsed.get("type") == kind:
                return parsed
            if parsed.get("type") == "error":
                raise RuntimeError(f"unexpected error while waiting for {kind}: {parsed}")


def wait_frame(ws, min_version: int = 0, timeout: float = STEP_S) -> dict:
    """The next frame whose header shows `scene_version` ≥ min_version."""
    deadline = time.monotonic() + timeout
    while True:
        message = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
        if isinstance(message, bytes):
            n = int.from_bytes(message[:4], "little")
            meta = json.loads(message[4:4 + n])
            if meta.get("scene_version", 0) >= min_version:
                return meta


def hello(ws, session: str | None = None, name: str = "script") -> dict:
    message = {"type": "hello", "protocol": 1, "viewport": {"width": 32, "height": 32}, "name": name}
    if session:
        message["session"] = session
    ws.send(json.dumps(message))
    return first_reply(ws)


def open_ws(url: str):
    # Unbounded queue: the test reads frames only now and then.
    options = dict(open_timeout=STEP_S, close_timeout=2, max_queue=None, max_size=None)
    try:
        # websockets ≥ 17.1 wants `legacy=True` for a connection outside a `with` block.
        return connect(url, legacy=True, **options)
    except TypeError:
        return connect(url, **options)


def open_session(url: str, name: str, tries: int = 40):
    """A new session through `url`, retrying as the web viewer does while processes fill up."""
    for _ in range(tries):
        try:
            ws = open_ws(url)
        except InvalidStatus as e:
            if e.response.status_code == 503:
                time.sleep(0.3)
                continue
            raise
        reply = hello(ws, name=name)
        if reply["type"] == "welcome":
            return ws, reply
        ws.close()
        if reply.get("code") not in ("at_capacity", "draining"):
            raise RuntimeError(f"hello refused: {reply}")
        time.sleep(0.3)
    raise RuntimeError(f"no session through {url} after {tries} tries")


def edit(ws) -> int:
    """An edit; returns the scene version it produced (from its echo)."""
    ws.send(json.dumps({"type": "params", "density_scale": 2.0 + time.monotonic() % 1, "g": 0.0}))
    return int(wait_for(ws, "edited")["version"])


def ordinal_of(route: str) -> int:
    return int(route.strip("/").split("/")[1])


def run(binary: str, folder: Path) -> int:
    check = Check()
    processes: dict[int, Process] = {}
    sockets = []
    page = None
    backends = folder / "backends.txt"
    router = Router(f"127.0.0.1:{free_port()}", backends, folder / "nginx")
    stop_sync = threading.Event()

    def write_backends() -> None:
        backends.write_text("".join(f"{n} {p.address}\n" for n, p in processes.items()))

    def sync_loop() -> None:
        while not stop_sync.wait(0.3):
            try:
                router.sync()
            except Exception as e:  # noqa: BLE001 - a failed poll is retried
                print(f"router sync failed: {e}", flush=True)

    def wait_ready(expected: set[int], among: bool = False) -> bool:
        """Until the router's ready set is `expected` (or, `among`, includes it)."""
        deadline = time.monotonic() + STEP_S
        while not (expected <= (router.ready or set()) if among else router.ready == expected):
            if time.monotonic() > deadline:
                return False
            time.sleep(0.1)
        return True

    try:
        for n in (0, 1):
            processes[n] = Process(binary, n, folder)
        write_backends()
        router.start()
        threading.Thread(target=sync_loop, daemon=True).start()
        base = f"http://{router.listen}"
        ws_root = f"ws://{router.listen}/ws"
        deadline = time.monotonic() + 20
        while http_get(f"{base}/p/1/healthz")[0] != 200 and time.monotonic() < deadline:
            time.sleep(0.2)

        # -- the routes ------------------------------------------------------------------
        status, body = http_get(f"{base}/")
        check("the root serves the viewer", status == 200 and "<html" in body.lower(), f"HTTP {status}")
        status, body = http_get(f"{base}/p/1/app.js")
        check("/p/1/ serves the viewer's files with the prefix stripped", status == 200, f"HTTP {status}")
        status, body = http_get(f"{base}/p/1/healthz")
        check("/p/1/ reaches process 1", status == 200 and json.loads(body).get("route") == "/p/1/", body[:120])

        # -- 1. a session stays on its process -------------------------------------------
        c1, welcome = open_session(ws_root, "Ada")
        sockets.append(c1)
        session, route = welcome["session"], welcome.get("route")
        check("welcome names the route of the process holding the session", bool(route) and route.startswith("/p/"), str(route))
        home = ordinal_of(route)
        other = 1 - home
        wait_frame(c1)
        check("the session lives on that process", processes[home].sessions() == 1 and processes[other].sessions() == 0,
              f"sessions {processes[home].sessions()} / {processes[other].sessions()}")
        c2 = open_ws(f"ws://{router.listen}{route}ws")
        reply = hello(c2, session=session, name="Bo")
        check("a second viewer joins through the route", reply["type"] == "welcome" and reply.get("joined") is True
              and reply["session"] == session, str(reply.get("type")))
        wait_frame(c2)
        c2.close()
        c1.socket.shutdown(socket.SHUT_RDWR)  # a dropped network, no close handshake
        c1.close()
        c1 = open_ws(f"ws://{router.listen}{route}ws")
        sockets.append(c1)
        reply = hello(c1, session=session, name="Ada")
        check("a dropped viewer reconnects into its session through the route",
              reply["type"] == "welcome" and reply.get("joined") is True and reply["session"] == session, str(reply)[:120])
        check("still one session, on the same process", processes[home].sessions() == 1 and processes[other].sessions() == 0)

        # -- the web viewer follows the route -------------------------------------------
        page = subprocess.Popen(["node", str(ROOT / "tests/deploy/page_route.mjs"), f"{base}/"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert page.stdout and page.stdin
        routed = json.loads(page.stdout.readline() or '{"event":"no output"}')
        ok = routed.get("event") == "routed"
        check("the web viewer opened at the root moves under its process's route", ok, json.dumps(routed)[:200])
        page_home = ordinal_of(routed["path"]) if ok else home
        share = urllib.parse.urlsplit(routed.get("share", ""))
        check("its share link names the route and the session",
              ok and share.path == f"/p/{page_home}/"
              and urllib.parse.parse_qs(share.query).get("session") == [routed["session"]], routed.get("share", ""))

        # -- 2. capacity: full processes leave the root ----------------------------------
        fillers = []
        while any(p.sessions() < MAX_SESSIONS for p in processes.values()):
            ws, w = open_session(ws_root, f"filler{len(fillers)}")
            fillers.append((ws, w))
            sockets.append(ws)
        check("both processes filled to capacity through the root, none over",
              all(p.sessions() == MAX_SESSIONS for p in processes.values()),
              f"{[p.sessions() for p in processes.values()]} after {len(fillers)} more sessions")
        check("the router dropped both from the root", wait_ready(set()), f"ready {router.ready}")
        # nginx's old workers may take a connection for a moment after a reload.
        refused, deadline = "", time.monotonic() + 10
        while refused != "503" and time.monotonic() < deadline:
            try:
                open_ws(ws_root).close()
                refused = "opened"
                time.sleep(0.2)
            except InvalidStatus as e:
                refused = str(e.response.status_code)
        check("the root answers 503 when no process takes sessions", refused == "503", refused)

        processes[2] = Process(binary, 2, folder)
        write_backends()
        check("a process started later joins the root", wait_ready({2}), f"ready {router.ready}")
        c3, w3 = open_session(ws_root, "Cy")
        sockets.append(c3)
        check("the new process takes the next new session", w3.get("route") == "/p/2/", str(w3.get("route")))
        c4 = open_ws(f"ws://{router.listen}{route}ws")
        sockets.append(c4)
        reply = hello(c4, session=session, name="Di")
        check("the old session did not move", reply["type"] == "welcome" and reply.get("joined") is True
              and processes[home].sessions() == MAX_SESSIONS)

        # -- 3. SIGTERM drains one process; the others go on -----------------------------
        drained = processes[page_home]
        viewers_there = [ws for ws, w in fillers if ordinal_of(w["route"]) == page_home]
        if home == page_home:
            viewers_there += [c1, c4]
        term_at = time.monotonic()
        drained.proc.send_signal(signal.SIGTERM)
        notice = wait_for(viewers_there[0], "draining")
        check("viewers of the draining process are told", 0 < notice["seconds_left"] <= DRAIN_TIMEOUT_S, str(notice)[:120])
        status, body = http_get(f"{base}/p/{page_home}/readyz")
        check("its readiness is false (draining)", status == 503 and "draining" in body, f"{status} {body}")
        check("the router dropped it from the root", wait_ready({2}), f"ready {router.ready}")
        probe = open_ws(f"ws://{router.listen}/p/{page_home}/ws")
        reply = hello(probe, name="late")
        probe.close()
        check("a new session on it is refused with `draining`", reply.get("code") == "draining", str(reply)[:120])
        version = edit(viewers_there[0])
        meta = wait_frame(viewers_there[0], version)
        check("its sessions are still served", meta["scene_version"] >= version)
        survivor = next(ws for ws, w in fillers if ordinal_of(w["route"]) != page_home)
        version = edit(survivor)
        check("another process keeps serving", wait_frame(survivor, version)["scene_version"] >= version)
        c5, w5 = open_session(ws_root, "Eve")
        sockets.append(c5)
        check("new sessions go to the others", w5.get("route") == "/p/2/", str(w5.get("route")))
        c5.close()  # a place for the web viewer when it moves (after the grace period)

        for ws in viewers_there[1:]:
            ws.close()
        # The web viewer stays connected, so the process serves it until the deadline.
        page.stdin.write("moved\n")
        page.stdin.flush()
        bye = wait_for(viewers_there[0], "bye", DRAIN_TIMEOUT_S + STEP_S)
        check("at the deadline the viewers get `bye`", "drained" in bye.get("reason", ""), bye.get("reason", ""))
        code = drained.proc.wait(STEP_S)
        waited = time.monotonic() - term_at
        check("then the process exits cleanly after the drain deadline",
              code == 0 and DRAIN_TIMEOUT_S - 1 <= waited <= DRAIN_TIMEOUT_S + 20, f"exit {code} after {waited:.1f} s")
        moved = json.loads(page.stdout.readline() or '{"event":"no output"}')
        moved_to = ordinal_of(moved["path"]) if moved.get("event") == "moved" and "/p/" in moved.get("path", "") else -1
        check("the web viewer reopened its view on another process", moved_to not in (-1, page_home),
              json.dumps(moved)[:200])

        # -- 4. a process dies without a drain: the web viewer finds its route dead and the root
        # alive, and reopens its view at the root --------------------------------------------
        survivor_home = next(n for n in processes if n not in (page_home, 2))
        freed = next(ws for ws, w in fillers if ordinal_of(w["route"]) == survivor_home)
        freed.close()  # room on the survivor once the session's grace period is over
        check("the survivor takes new sessions again", wait_ready({survivor_home}, among=True), f"ready {router.ready}")
        killed_at = time.monotonic()
        processes[2].proc.kill()
        processes[2].proc.wait(10)
        page.stdin.write("moved\n")
        page.stdin.flush()
        moved_again = json.loads(page.stdout.readline() or '{"event":"no output"}')
        check("after its process was killed the web viewer reopened its view on the survivor",
              moved_again.get("event") == "moved" and moved_again.get("path") == f"/p/{survivor_home}/",
              f"{json.dumps(moved_again)[:200]} after {time.monotonic() - killed_at:.1f} s")
        check("no script error in the page", not moved_again.get("errors"), str(moved_again.get("errors")))
    except Exception as e:  # noqa: BLE001 - reported as a failed check with the logs below
        check("routing test ran to the end", False, f"{type(e).__name__}: {e}")
    finally:
        stop_sync.set()
        if page and page.poll() is None:
            try:
                assert page.stdin
                page.stdin.write("quit\n")
                page.stdin.flush()
                page.wait(20)
            except Exception:  # noqa: BLE001
                page.kill()
        for ws in sockets:
            try:
                ws.close()
            except Exception:  # noqa: BLE001
                pass
        for p in processes.values():
            if p.proc.poll() is None:
                p.proc.send_signal(signal.SIGTERM)
        for p in processes.values():
            try:
                p.proc.wait(30)
            except subprocess.TimeoutExpired:
                p.proc.kill()
                check(f"process {p.ordinal} stopped on SIGTERM with no viewers", False)
        router.stop()
        if check.failed:
            for p in processes.values():
                print(f"---- voxlight-{p.ordinal} log (tail) ----")
                print(p.log_path.read_text()[-3000:])
            error_log = folder / "nginx" / "error.log"
            if error_log.exists():
                print("---- nginx error log (tail) ----")
                print(error_log.read_text()[-2000:])
    print(f"routing: {'FAILED' if check.failed else 'passed'} ({check.failed} failed) in {time.monotonic() - check.started:.0f} s")
    return 1 if check.failed else 0


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--voxlight", default=str(ROOT / "target/debug/voxlight"))
    args = parser.parse_args()
    if not shutil.which("nginx") and not Path("/usr/sbin/nginx").exists():
        print("routing: cannot run: nginx not found (apt-get install nginx)")
        return 2
    if not Path(args.voxlight).exists():
        print(f"routing: cannot run: no binary at {args.voxlight}")
        return 2
    os.environ["PATH"] += ":/usr/sbin"
    with tempfile.TemporaryDirectory(prefix="voxlight-routing-") as folder:
        return run(args.voxlight, Path(folder))


if __name__ == "__main__":
    sys.exit(main())
