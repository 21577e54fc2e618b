#!/usr/bin/env bash
# Container image test (CI): builds the voxlight image with lavapipe and no registry
# (deploy/image/build-local.sh: debootstrapped base + deploy/image/Containerfile), starts it with
# podman, and has a scripted WebSocket client (tests/deploy/first_frame.py) check /healthz
# (adapter named, software_renderer true) and receive `welcome` and a first frame; then checks
# the image's user, entrypoint, `sleep` (the Kubernetes preStop hook) and that the server
# stops on SIGTERM. Prints the image size, the build time and the time from `podman run` to
# the first frame.
#
#   scripts/test-image.sh [BINARY]        # BINARY, else $VOXLIGHT_BINARY, else target/release/voxlight
#
# Environment: VOXLIGHT_IMAGE_TEST_BUDGET_S (whole-run time limit, default 900),
# VOXLIGHT_IMAGE_TEST_FRAME_DEADLINE_S (podman run -> first frame limit, default 120),
# VOXLIGHT_IMAGE_TEST_NETWORK (publish: -p 127.0.0.1:PORT:8080 with the image's own CMD,
# the default; host: --network host and `serve --listen 127.0.0.1:PORT`), and those of
# build-local.sh (DEBIAN_MIRROR, VOXLIGHT_STORAGE_DRIVER, ...). Needs root; installs podman,
# buildah, runc, debootstrap (apt-get) and the PyPI package websockets (pip) when missing.
#
# Measured wall time on the 2-core CI-like VM (Debian 12, release binary; the debug binary
# gives the same times within a second):
#   cold (podman & co. not installed, no base image, no build cache): 52-60 s
#     apt-get install podman buildah runc debootstrap ~10 s, debootstrap + import 27-41 s
#     (mirror speed), image build 15-16 s, podman run -> first frame 1.2 s, stop 0.7 s
#   warm (base image cached, image layers not): 18-26 s; everything cached: 4 s
# Image sizes: 424 MB with lavapipe, 168 MB without (73 MB of it the release binary).
set -euo pipefail
self=$(realpath "$0")
binary=${1:-${VOXLIGHT_BINARY:-}}
[ -z "$binary" ] || binary=$(realpath -m "$binary") # relative to the caller's directory
cd "$(dirname "$self")/.."
binary=${binary:-$PWD/target/release/voxlight}

budget=${VOXLIGHT_IMAGE_TEST_BUDGET_S:-900}
if [ -z "${VOXLIGHT_IMAGE_TEST_INNER:-}" ]; then
  # the whole test under one time limit; timeout signals the whole process group, the traps
  # below remove the container
  export VOXLIGHT_IMAGE_TEST_INNER=1
  status=0
  timeout --kill-after=20 "$budget" "$self" "$binary" || status=$?
  if [ "$status" -eq 124 ] || [ "$status" -eq 137 ]; then
    echo "test-image: FAIL: did not finish within ${budget} s (VOXLIGHT_IMAGE_TEST_BUDGET_S)" >&2
  fi
  exit "$status"
fi

# shellcheck source=deploy/image/podman-env.sh
. deploy/image/podman-env.sh

t_script=$SECONDS
network=${VOXLIGHT_IMAGE_TEST_NETWORK:-publish}
tag=test-lavapipe
image=localhost/voxlight:$tag
name=voxlight-image-test-$$

fail() {
  echo "test-image: FAIL: $*" >&2
  exit 1
}

[ -x "$binary" ] || fail "no executable voxlight binary at $binary (build it, or pass its path / VOXLIGHT_BINARY)"
[ "$(id -u)" -eq 0 ] || fail "needs root (debootstrap and root podman)"
case $network in publish|host) ;; *) fail "VOXLIGHT_IMAGE_TEST_NETWORK must be publish or host" ;; esac

container_started=0
cleanup() {
  local rc=$?
  if [ "$container_started" = 1 ]; then
    vx_podman rm -f -t 2 "$name" >/dev/null 2>&1 || true
  fi
  exit "$rc"
}
trap cleanup EXIT
trap 'exit 143' TERM
trap 'exit 130' INT

echo "== tools =="
vx_need_packages
if ! python3 -c 'import websockets.sync.client' 2>/dev/null; then
  echo "installing the PyPI package websockets"
  python3 -m pip install --quiet 'websockets>=12' ||
    python3 -m pip install --quiet --break-system-packages 'websockets>=12' ||
    fail "could not pip install websockets"
fi

echo "== build (binary $binary) =="
build_log=$(mktemp "${TMPDIR:-/tmp}/voxlight-image-build.XXXXXX")
t0=$SECONDS
deploy/image/build-local.sh --base-only
base_s=$((SECONDS - t0))
t0=$SECONDS
deploy/image/build-local.sh --binary "$binary" --lavapipe --tag "$tag" >"$build_log" 2>&1 || {
  tail -40 "$build_log" >&2
  fail "image build failed (log above; whole log in $build_log)"
}
build_s=$((SECONDS - t0))
rm -f "$build_log"
size=$(vx_podman image inspect --format '{{.Size}}' "$image")

echo "== image configuration =="
user=$(vx_podman image inspect --format '{{.Config.User}}' "$image")
entrypoint=$(vx_podman image inspect --format '{{json .Config.Entrypoint}}' "$image")
env=$(vx_podman image inspect --format '{{json .Config.Env}}' "$image")
ports=$(vx_podman image inspect --format '{{json .Config.ExposedPorts}}' "$image")
[ "$user" = "10001:10001" ] || fail "image user is '$user', expected 10001:10001 (non-root)"
[ "$entrypoint" = '["/usr/local/bin/voxlight"]' ] || fail "image entrypoint is $entrypoint"
case $env in *NVIDIA_DRIVER_CAPABILITIES=*graphics*) ;; *) fail "NVIDIA_DRIVER_CAPABILITIES lacks graphics (no Vulkan on NVIDIA nodes): $env" ;; esac
case $ports in *8080/tcp*) ;; *) fail "image does not expose 8080: $ports" ;; esac

vx_run_limits
run_flags=("${VX_RUN_LIMITS[@]}")

vx_podman run --rm "${run_flags[@]}" --network none --entrypoint sleep "$image" 0 ||
  fail "\`sleep\` does not run in the image (the Kubernetes preStop hook needs it)"

echo "== podman run -> first frame =="
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
if [ "$network" = host ]; then
  net_flags=(--network host)
  cmd=(serve --listen "127.0.0.1:$port")
else
  net_flags=(-p "127.0.0.1:$port:8080")
  cmd=()
fi
start=$(date +%s.%N)
container_started=1
vx_podman run -d --name "$name" "${run_flags[@]}" "${net_flags[@]}" "$image" "${cmd[@]}" >/dev/null ||
  fail "podman run failed"
result=$(python3 tests/deploy/first_frame.py --url "http://127.0.0.1:$port" --start "$start" \
  --deadline "${VOXLIGHT_IMAGE_TEST_FRAME_DEADLINE_S:-120}" --size 64 --software-renderer true) || {
  echo "---- container log ----" >&2
  vx_podman logs "$name" 2>&1 | tail -40 >&2 || true
  fail "no first frame from the container (see the log above)"
}
echo "$result"
first_frame_s=$(python3 -c 'import json,sys; print(json.loads(sys.argv[1])["first_frame_s"])' "$result")

echo "== podman stop (SIGTERM) =="
t_stop=$(date +%s.%N)
vx_podman stop -t 10 "$name" >/dev/null
stop_s=$(python3 -c 'import sys,time; print(round(time.time()-float(sys.argv[1]),2))' "$t_stop")
exit_code=$(vx_podman inspect --format '{{.State.ExitCode}}' "$name")
if [ "$exit_code" != 0 ]; then
  vx_podman logs "$name" 2>&1 | tail -20 >&2 || true
  fail "the server exited with $exit_code on SIGTERM (137: it ignored SIGTERM and was killed)"
fi

echo "== test-image: OK =="
echo "image $image: $size bytes ($((size / 1000000)) MB)"
echo "base image (debootstrap + import, 0 when cached): ${base_s} s"
echo "image build: ${build_s} s"
echo "podman run -> first frame: ${first_frame_s} s"
echo "podman stop (SIGTERM) -> exited: ${stop_s} s"
echo "total: $((SECONDS - t_script)) s"
