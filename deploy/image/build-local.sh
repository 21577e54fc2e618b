#!/usr/bin/env bash
# Builds the voxlight container image without any container registry: the base image is a
# minimal Debian 12 root filesystem made with debootstrap from a Debian package mirror and
# imported into podman as localhost/voxlight-base:bookworm (done once; later runs reuse it),
# then deploy/image/Containerfile is built on it with a context holding only the binary.
#
#   deploy/image/build-local.sh [--binary PATH] [--lavapipe] [--tag TAG] [--strip]
#                               [--rebuild-base] [--base-only]
#
#   --binary PATH    the voxlight binary (default target/release/voxlight)
#   --lavapipe       also install Mesa's lavapipe (CPU Vulkan): CPU nodes, CI, development
#   --tag TAG        image tag (default dev, or dev-lavapipe with --lavapipe);
#                    the image is localhost/voxlight:TAG
#   --strip          strip debug info from the copied binary (release: 73 MB -> 16 MB, but
#                    panics/backtraces lose file:line)
#   --rebuild-base   debootstrap the base again even if it exists
#   --base-only      make the base image and stop
#
# Environment: DEBIAN_MIRROR (default http://deb.debian.org/debian), DEBIAN_SECURITY_MIRROR
# (default http://deb.debian.org/debian-security), VOXLIGHT_BASE_IMAGE (default
# localhost/voxlight-base:bookworm), VOXLIGHT_STORAGE_DRIVER / VOXLIGHT_PODMAN_ROOT (see
# podman-env.sh). Needs root and the Debian packages podman buildah runc debootstrap (installed
# with apt-get when missing). Prints the image name on the last line of stdout.
#
# Measured on the 2-core CI-like VM: debootstrap + import 27-41 s (once; mirror speed), image
# build 9-11 s without lavapipe, 15-23 s with (apt-get runs inside the build); image sizes
# (podman's uncompressed Size) with the release binary: 168 MB, 111 MB with --strip, 424 MB
# with --lavapipe; gzipped `podman save`: 58 MB, 43 MB, 152 MB. The base alone is 81 MB.
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
repo=$(cd "$here/../.." && pwd)
# shellcheck source=deploy/image/podman-env.sh
. "$here/podman-env.sh"

binary=$repo/target/release/voxlight
lavapipe=0
tag=
strip=0
rebuild_base=0
base_only=0
while [ $# -gt 0 ]; do
  case $1 in
    --binary) binary=${2:?--binary needs a path}; shift 2 ;;
    --binary=*) binary=${1#*=}; shift ;;
    --lavapipe) lavapipe=1; shift ;;
    --tag) tag=${2:?--tag needs a value}; shift 2 ;;
    --tag=*) tag=${1#*=}; shift ;;
    --strip) strip=1; shift ;;
    --rebuild-base) rebuild_base=1; shift ;;
    --base-only) base_only=1; shift ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) echo "error: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done
if [ -z "$tag" ]; then
  tag=dev
  if [ "$lavapipe" = 1 ]; then tag=dev-lavapipe; fi
fi
base=${VOXLIGHT_BASE_IMAGE:-localhost/voxlight-base:bookworm}
image=localhost/voxlight:$tag
mirror=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
security_mirror=${DEBIAN_SECURITY_MIRROR:-http://deb.debian.org/debian-security}

if [ "$(id -u)" -ne 0 ]; then
  echo "error: run as root (debootstrap and root podman)" >&2
  exit 1
fi
if [ "$base_only" = 0 ]; then
  [ -f "$binary" ] || { echo "error: no voxlight binary at $binary (build it, or pass --binary)" >&2; exit 1; }
  [ -x "$binary" ] || { echo "error: $binary is not executable" >&2; exit 1; }
fi
vx_need_packages

work=
cleanup() {
  [ -n "$work" ] && [ -d "$work" ] || return 0
  # debootstrap mounts proc/sys inside the target; never let rm walk into a mount
  local m
  awk -v w="$work/" 'index($2, w) == 1 {print $2}' /proc/mounts | sort -r | while read -r m; do
    umount -l "$m" 2>/dev/null || true
  done
  rm -rf --one-file-system "$work"
}
trap cleanup EXIT
work=$(mktemp -d "${TMPDIR:-/var/tmp}/voxlight-image.XXXXXX")

make_base() {
  local rootfs=${work:?}/rootfs t0=$SECONDS
  echo "== debootstrap bookworm (minbase) from $mirror =="
  debootstrap --variant=minbase --arch=amd64 bookworm "$rootfs" "$mirror" >"$work/debootstrap.log" 2>&1 || {
    tail -30 "$work/debootstrap.log" >&2
    echo "error: debootstrap failed (log above); is $mirror reachable?" >&2
    return 1
  }
  # What the official debian:bookworm-slim does: updates and security in the sources, no
  # docs/man pages/translations, apt cleans its caches after every install.
  rm -f "$rootfs/etc/apt/sources.list"
  cat >"$rootfs/etc/apt/sources.list.d/debian.sources" <<EOF
Types: deb
URIs: $mirror
Suites: bookworm bookworm-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: $security_mirror
Suites: bookworm-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
  cat >"$rootfs/etc/dpkg/dpkg.cfg.d/docker-slim" <<'EOF'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/locale/*
path-include /usr/share/locale/locale.alias
path-exclude /usr/share/lintian/*
path-exclude /usr/share/linda/*
EOF
  cat >"$rootfs/etc/apt/apt.conf.d/docker-clean" <<'EOF'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache "";
Dir::Cache::srcpkgcache "";
EOF
  find "$rootfs/usr/share/doc" -mindepth 1 -not -name copyright -not -type d -delete
  find "$rootfs/usr/share/doc" -mindepth 1 -type d -empty -delete
  rm -rf "${rootfs:?}"/usr/share/man/* "${rootfs:?}"/usr/share/info/* "${rootfs:?}"/usr/share/lintian/*
  find "$rootfs/usr/share/locale" -mindepth 1 -maxdepth 1 -not -name locale.alias -exec rm -rf {} +
  find "$rootfs/var/log" "$rootfs/var/cache/apt" "$rootfs/var/lib/apt/lists" -type f -delete
  rm -rf "${rootfs:?}"/var/cache/debconf/*-old "${rootfs:?}"/var/lib/dpkg/*-old "${rootfs:?}"/tmp/* \
    "${rootfs:?}"/dev/* "${rootfs:?}"/proc/* "${rootfs:?}"/sys/*
  # host files debootstrap copied in; the container runtime provides its own
  : >"$rootfs/etc/resolv.conf"
  : >"$rootfs/etc/hostname"
  echo "== podman import as $base =="
  tar --numeric-owner --xattrs -C "$rootfs" -cf - . |
    vx_podman import \
      --change 'ENV=PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
      --change 'CMD=["bash"]' \
      --message "debootstrap --variant=minbase bookworm $mirror" \
      - "$base" >/dev/null
  rm -rf --one-file-system "$rootfs"
  echo "base image $base made in $((SECONDS - t0)) s"
}

if [ "$rebuild_base" = 1 ] || ! vx_podman image exists "$base"; then
  make_base
else
  echo "== base image $base exists (--rebuild-base to make it again) =="
fi
if [ "$base_only" = 1 ]; then exit 0; fi

context=$work/context
mkdir -p "$context"
cp "$binary" "$context/voxlight"
chmod 0755 "$context/voxlight"
if [ "$strip" = 1 ]; then strip --strip-debug "$context/voxlight"; fi
version=$(timeout 10 "$context/voxlight" --version 2>/dev/null | awk '{print $NF}') || version=unknown
revision=$(git -C "$repo" rev-parse --short HEAD 2>/dev/null) || revision=unknown

echo "== podman build $image (lavapipe=$lavapipe) =="
t0=$SECONDS
vx_podman build \
  --isolation=chroot \
  --pull=never \
  --build-arg "BASE=$base" \
  --build-arg "LAVAPIPE=$lavapipe" \
  --build-arg "VERSION=$version" \
  --build-arg "REVISION=$revision" \
  -t "$image" \
  -f "$here/Containerfile" \
  "$context"
echo "image $image built in $((SECONDS - t0)) s, $(vx_podman image inspect --format '{{.Size}}' "$image") bytes"
echo "$image"
