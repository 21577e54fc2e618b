#!/usr/bin/env bash
# Checks the Kubernetes manifests in deploy/k8s (CI runs this; no cluster needed):
#
#   1. every overlay builds: `kubectl kustomize deploy/k8s/overlays/<name>`;
#   2. `kubernetes-validate --strict` against the Kubernetes schemas of the oldest supported
#      version (1.28: the StatefulSet pod-index label) and a current one. It has no schema for
#      CRD kinds and only warns about them; any such warning for a kind that step 3 does not
#      validate is an error here;
#   3. scripts/check_k8s.py: the CRD kinds (HTTPRoute, ScaledObject, ServiceMonitor) against
#      their upstream schemas vendored in deploy/k8s/schemas, the structural checks (per-pod
#      routes for every ordinal, selectors, readiness, drain vs. grace period, probes, route
#      prefix...), that the generated per-pod routes match deploy/k8s/gen-pod-routes.py, and a
#      self-test that breaks each key property in memory and requires its check to fail.
#
# Needs kubectl (>= 1.28, it carries kustomize) and python3 with PyYAML; installs
# kubernetes-validate with pip when it is missing.
#   K8S_VERSIONS="1.28.0 1.32.0"   Kubernetes versions to validate against
set -euo pipefail

cd "$(dirname "$0")/.."

K8S_VERSIONS=${K8S_VERSIONS:-"1.28.0 1.32.0"}
KUBERNETES_VALIDATE_PIN=${KUBERNETES_VALIDATE_PIN:-1.37.0}

die() { echo "check-k8s: error: $*" >&2; exit 1; }

command -v kubectl >/dev/null 2>&1 ||
  die "kubectl not found on PATH. Install kubectl >= 1.28 (https://kubernetes.io/docs/tasks/tools/); it builds the kustomize overlays offline, no cluster needed."
command -v python3 >/dev/null 2>&1 || die "python3 not found"
python3 -c 'import yaml' 2>/dev/null ||
  die "PyYAML missing: python3 -m pip install pyyaml (or apt-get install python3-yaml)"
if ! command -v kubernetes-validate >/dev/null 2>&1; then
  echo "== installing kubernetes-validate==$KUBERNETES_VALIDATE_PIN (pip)"
  python3 -m pip install --quiet "kubernetes-validate==$KUBERNETES_VALIDATE_PIN" ||
    die "could not install kubernetes-validate (pip install kubernetes-validate)"
  command -v kubernetes-validate >/dev/null 2>&1 ||
    die "kubernetes-validate installed but not on PATH (add pip's script folder to PATH)"
fi

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

# "apiVersion kind" of every CRD kind check_k8s.py validates itself.
python3 scripts/check_k8s.py --list-crd-kinds >"$tmp/crd-kinds"

echo "kubectl $(kubectl version --client 2>/dev/null | head -n 1 | sed 's/^Client Version: //'), kubernetes-validate $(kubernetes-validate --version 2>/dev/null)"

status=0
built=()
for dir in deploy/k8s/overlays/*/; do
  overlay=$(basename "$dir")
  out="$tmp/$overlay.yaml"
  if ! kubectl kustomize "$dir" >"$out" 2>"$tmp/$overlay.err"; then
    echo "FAIL [kustomize] $overlay:"
    cat "$tmp/$overlay.err"
    status=1
    continue
  fi
  built+=(--built "$overlay=$out")
  objects=$(grep -c '^kind:' "$out" || true)
  for version in $K8S_VERSIONS; do
    log="$tmp/$overlay-$version.log"
    rc=0
    kubernetes-validate --strict --quiet -k "$version" "$out" >"$log" 2>&1 || rc=$?
    # Warnings: only "no schema" for the CRD kinds check_k8s.py validates.
    unexpected=$({ grep -v '^$' "$log" || true; } | while IFS= read -r line; do
      if [[ $line =~ ^WARN\ .*Couldn\'t\ find\ schema\ for\ kind\ ([A-Za-z]+)\ with\ api\ version\ ([^ ]+)\ for ]]; then
        grep -qx "${BASH_REMATCH[2]} ${BASH_REMATCH[1]}" "$tmp/crd-kinds" || echo "$line"
      else
        echo "$line"
      fi
    done)
    skipped=$(grep -c "^WARN .*Couldn't find schema" "$log" || true)
    if [ "$rc" -ne 0 ] || [ -n "$unexpected" ]; then
      echo "FAIL [kubernetes-validate] $overlay against $version (exit $rc):"
      echo "$unexpected"
      status=1
    else
      echo "ok   [kubernetes-validate --strict -k $version] $overlay: $((objects - skipped)) objects valid; $skipped CRD objects (no schema there) left to check_k8s.py"
    fi
  done
done

if [ ${#built[@]} -gt 0 ]; then
  python3 scripts/check_k8s.py "${built[@]}" --self-test || status=1
fi

if [ "$status" -eq 0 ]; then
  echo "check-k8s: OK"
else
  echo "check-k8s: FAILED"
fi
exit "$status"
