# shellcheck shell=bash
# Sourced by deploy/image/build-local.sh and scripts/test-image.sh: how podman is invoked here,
# stated on every call instead of relying on /etc/containers state of the machine, so a fresh
# Debian 12 machine (CI) behaves the same as a used one.
#
#   VOXLIGHT_STORAGE_DRIVER  unset (default): podman's own choice, i.e. the configured driver
#                            or, with none configured (Debian's default), the first that works:
#                            native overlay on ext4/xfs (here), vfs where overlay cannot work.
#                            overlay or vfs forces one; vfs works anywhere but copies every
#                            layer in full (slower, several times the disk). Podman 4.3 remembers
#                            the driver of its first use of a store and refuses a different one
#                            ("database storage graph driver \"\" does not match ..."), even ""
#                            vs "overlay", so set it only for a store always used with it (or
#                            together with VOXLIGHT_PODMAN_ROOT).
#   VOXLIGHT_PODMAN_ROOT     image store (default /var/lib/containers/storage, podman's own)
#
# Root podman on a cgroup v1 machine without systemd as PID 1: cgroupfs (not systemd) as cgroup
# manager, runc as OCI runtime (crun is not installed by `--no-install-recommends podman`),
# events to a file (there is no journald to log to).

vx_podman() {
  local args=(
    --cgroup-manager cgroupfs
    --runtime runc
    --events-backend file
  )
  if [ -n "${VOXLIGHT_STORAGE_DRIVER:-}" ]; then
    args+=(--storage-driver "$VOXLIGHT_STORAGE_DRIVER")
  fi
  if [ -n "${VOXLIGHT_PODMAN_ROOT:-}" ]; then
    args+=(--root "$VOXLIGHT_PODMAN_ROOT" --runroot "$VOXLIGHT_PODMAN_ROOT/run")
  fi
  podman "${args[@]}" "$@"
}

# Sets VX_RUN_LIMITS, the --ulimit flags `podman run` needs here. Podman's default
# RLIMIT_NOFILE for a container (1048576) is above this VM's hard limit (20000), and raising a
# hard limit needs CAP_SYS_RESOURCE, which this VM's root lacks: runc then fails with "error
# setting rlimits for ready process: error setting rlimit type 7: operation not permitted"
# (`--ulimit host` fails the same way). NPROC is given too: without it runc failed the same way
# on type 6 now and then.
# shellcheck disable=SC2034 # used by the scripts that source this file
vx_run_limits() {
  local nofile nproc
  nofile=$(ulimit -Hn)
  nproc=$(ulimit -Hu)
  if [ "$nofile" = unlimited ] || [ "$nofile" -gt 1048576 ]; then nofile=1048576; fi
  if [ "$nproc" = unlimited ] || [ "$nproc" -gt 32768 ]; then nproc=32768; fi
  VX_RUN_LIMITS=(--ulimit "nofile=$nofile:$nofile" --ulimit "nproc=$nproc:$nproc")
}

# Installs the Debian packages the image build needs when a command is missing.
vx_need_packages() {
  local missing=() cmd pkg
  for pair in podman:podman buildah:buildah runc:runc debootstrap:debootstrap conmon:conmon; do
    cmd=${pair%%:*}
    pkg=${pair#*:}
    command -v "$cmd" >/dev/null 2>&1 || missing+=("$pkg")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  if [ "$(id -u)" -ne 0 ]; then
    echo "error: missing ${missing[*]}; install them: apt-get install -y --no-install-recommends podman buildah runc debootstrap" >&2
    return 1
  fi
  echo "== installing ${missing[*]} (apt-get) =="
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends podman buildah runc debootstrap >/dev/null
}
