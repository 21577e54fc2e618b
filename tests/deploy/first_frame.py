#!/usr/bin/env python3
"""Scripted first-frame check against a running voxlight server (used by scripts/test-image.sh).

Polls GET /healthz until it answers (checking that it names the adapter and, with
--software-renderer, whether it is a software one), opens the WebSocket /ws (retrying until the
deadline), sends `hello`, waits for `welcome` and then for the first binary message, and checks
that it is a frame (u32 LE metadata length, FrameMeta JSON, a complete JPEG or PNG). Prints one
JSON object with the seconds from --start (a Unix time, e.g. `date +%s.%N` taken just before
`podman run`) to each step. Exit status 0 on success; 1 with a message on stderr otherwise.

    python3 tests/deploy/first_frame.py --url http://127.0.0.1:8080 --start "$(date +%s.%N)" \
        --deadline 120 --software-renderer true

Needs Python 3.11 and the PyPI package `websockets` (>= 12, sync client).
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import time
import urllib.error
import urllib.request

PROTOCOL_VERSION = 1  # protocol/src/lib.rs PROTOCOL_VERSION


class Failure(Exception):
    pass


def since(start: float) -> float:
    return round(time.time() - start, 3)


def wait_healthz(base: str, start: float, deadline: float, token: str | None) -> tuple[dict, float]:
    last = "no answer yet"
    while time.time() < deadline:
        req = urllib.request.Request(base + "/healthz")
        if token:
            req.add_header("Authorization", f"Bearer {token}")
        try:
            with urllib.request.urlopen(req, timeout=5) as resp:
                body = resp.read()
            health = json.loads(body)
            return health, since(start)
        except (urllib.error.URLError, ConnectionError, TimeoutError, OSError) as e:
            last = str(e)
        except json.JSONDecodeError as e:
            raise Failure(f"/healthz did not answer JSON: {e}: {body[:200]!r}") from e
        time.sleep(0.2)
    raise Failure(f"/healthz did not answer before the deadline (last: {last})")


def check_health(health: dict, software: str) -> None:
    if health.get("status") != "ok":
        raise Failure(f"/healthz status is not ok: {health}")
    adapter = health.get("adapter")
    if not isinstance(adapter, str) or not adapter.strip():
        raise Failure(f"/healthz names no adapter: {health}")
    if "software_renderer" not in health:
        raise Failure(f"/healthz has no software_renderer field: {health}")
    if software != "any" and health["software_renderer"] is not (software == "true"):
        raise Failure(f"/healthz software_renderer is {health['software_renderer']}, expected {software}: {health}")


def parse_frame(data: bytes) -> dict:
    if len(data) < 4:
        raise Failure(f"binary message of {len(data)} bytes is too short for a frame")
    (n,) = struct.unpack_from("<I", data, 0)
    if 4 + n > len(data):
        raise Failure(f"frame metadata length {n} exceeds the message ({len(data)} bytes)")
    try:
        meta = json.loads(data[4 : 4 + n].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise Failure(f"frame metadata is not JSON: {e}") from e
    image = data[4 + n :]
    fmt = meta.get("format")
    if fmt == "jpeg":
        ok = image[:2] == b"\xff\xd8" and image[-2:] == b"\xff\xd9"
    elif fmt == "png":
        ok = image[:8] == b"\x89PNG\r\n\x1a\n"
    else:
        raise Failure(f"frame format {fmt!r} is neither jpeg nor png: {meta}")
    if not ok:
        raise Failure(f"frame image bytes are not a complete {fmt} file ({len(image)} bytes)")
    for key in ("seq", "width", "height", "technique"):
        if key not in meta:
            raise Failure(f"frame metadata lacks {key}: {meta}")
    return {
        "format": fmt,
        "width": meta["width"],
        "height": meta["height"],
        "seq": meta["seq"],
        "technique": meta["technique"],
        "iteration": meta.get("iteration"),
        "bytes": len(data),
    }


def first_frame(args: argparse.Namespace) -> dict:
    try:
        from websockets.exceptions import ConnectionClosed, InvalidHandshake
        from websockets.sync.client import connect
    except ImportError as e:
        raise Failure("the Python package `websockets` (>= 12) is missing: pip install websockets") from e

    start, deadline = args.start, args.start + args.deadline
    base = args.url.rstrip("/")
    ws_url = "ws" + base[len("http") :] + "/ws" if base.startswith("http") else base + "/ws"
    result: dict = {}

    health, t = wait_healthz(base, start, deadline, args.token)
    check_health(health, args.software_renderer)
    result.update(healthz_s=t, adapter=health["adapter"], software_renderer=health["software_renderer"])

    headers = {"Authorization": f"Bearer {args.token}"} if args.token else None
    last = "no attempt"
    while True:
        left = deadline - time.time()
        if left <= 0:
            raise Failure(f"could not open {ws_url} before the deadline (last: {last})")
        try:
            ws = connect(ws_url, additional_headers=headers, open_timeout=min(10.0, left), max_size=64 * 2**20)
            break
        except (OSError, TimeoutError, InvalidHandshake) as e:
            last = f"{type(e).__name__}: {e}"
            time.sleep(0.2)
    result["connected_s"] = since(start)
    with ws:
        hello = {"type": "hello", "protocol": PROTOCOL_VERSION, "viewport": {"width": args.size, "height": args.size}}
        ws.send(json.dumps(hello))
        welcome = None
        try:
            while True:
                left = deadline - time.time()
                if left <= 0:
                    step = "welcome" if welcome is None else "the first frame"
                    raise Failure(f"no {step} before the deadline ({args.deadline} s after start)")
                try:
                    msg = ws.recv(timeout=left)
                except TimeoutError:
                    continue
                if isinstance(msg, str):
                    obj = json.loads(msg)
                    kind = obj.get("type")
                    if kind == "error":
                        raise Failure(f"server answered an error: {obj}")
                    if kind == "welcome" and welcome is None:
                        welcome = obj
                        if welcome.get("protocol") != PROTOCOL_VERSION:
                            raise Failure(f"welcome has protocol {welcome.get('protocol')}, expected {PROTOCOL_VERSION}")
                        result["welcome_s"] = since(start)
                        result["welcome"] = {
                            "server_version": welcome.get("server_version"),
                            "adapter": welcome.get("adapter"),
                            "dataset": (welcome.get("dataset") or {}).get("name"),
                        }
                    elif welcome is None:
                        raise Failure(f"expected welcome first, got {kind!r}: {msg[:300]}")
                    continue
                if welcome is None:
                    raise Failure("a binary message arrived before welcome")
                result["first_frame_s"] = since(start)
                result["frame"] = parse_frame(msg)
                break
        except ConnectionClosed as e:
            raise Failure(f"the server closed the WebSocket: {e}") from e
    return result


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--url", required=True, help="server base URL, e.g. http://127.0.0.1:8080")
    p.add_argument("--start", type=float, default=None, help="Unix time the measurement starts at (default: now)")
    p.add_argument("--deadline", type=float, default=120.0, help="seconds after --start to give up (default 120)")
    p.add_argument("--size", type=int, default=64, help="viewport width and height (default 64)")
    p.add_argument("--token", default=None, help="access token, when the server requires one")
    p.add_argument(
        "--software-renderer",
        choices=("true", "false", "any"),
        default="any",
        help="what /healthz software_renderer must be (true: lavapipe)",
    )
    args = p.parse_args()
    if args.start is None:
        args.start = time.time()
    try:
        result = first_frame(args)
    except Failure as e:
        print(f"first_frame: FAIL: {e}", file=sys.stderr)
        return 1
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
