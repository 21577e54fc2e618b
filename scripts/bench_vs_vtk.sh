#!/usr/bin/env bash
# VTK's FixedPoint CPU ray caster and voxlight's interactive preview on the same volumes,
# viewport, transfer functions, camera and 5° orbit, in one run, with the ratios.
#   scripts/bench_vs_vtk.sh [size (default 512)] [frames (default 10)]
# Needs ../shared (data and baselines/vtk), PyPI vtk==9.7.2 and pydicom (installed if missing),
# and a release build of voxlight (built if missing).
set -euo pipefail
cd "$(dirname "$0")/.."
size=${1:-512}
frames=${2:-10}
shared=${VOXLIGHT_SHARED:-../shared}
out=$(mktemp -d)
python3 -c 'import vtk, pydicom' 2>/dev/null || python3 -m pip install -q vtk==9.7.2 pydicom==3.0.2
[ -x target/release/voxlight ] || cargo build --release -p voxlight-server
python3 "$shared/baselines/vtk/bench_vtk.py" --data "$shared/data" --datasets bonsai,ct \
    --mappers fixedpoint --sizes "$size" --shade 1 --sample-modes default --frames "$frames" \
    --msaa-side-sizes "" --no-screenshots --out "$out/vtk.json" >&2
target/release/voxlight bench preview-vtk --data "$shared/data" --sizes "$size" \
    --iterations "$frames" --json | tail -n 1 > "$out/voxlight.json"
python3 - "$out/vtk.json" "$out/voxlight.json" <<'PY'
import json, sys
vtk = json.load(open(sys.argv[1]))
ours = json.load(open(sys.argv[2]))
print(f"adapter: {ours['adapter']}")
print("| dataset | size | VTK FixedPoint shaded (ms) | preview 1/1 | 1/2 | 1/4 | 1/8 | ratio at 1/1 | best ratio <= 1 |")
print("|---|---|---|---|---|---|---|---|---|")
for r in ours["results"]:
    v = [c for c in vtk["configs"] if c["dataset"] == r["dataset"] and c["size"] == r["width"]]
    if not v:
        continue
    vtk_ms = v[0]["median_ms"]
    ms = {p["divisor"]: p["median_ms"] for p in r["previews"]}
    fits = [d for d in sorted(ms) if ms[d] <= vtk_ms]
    best = f"1/{fits[0]} ({ms[fits[0]] / vtk_ms:.2f})" if fits else "none"
    print(f"| {r['dataset']} | {r['width']}² | {vtk_ms:.1f} | " +
          " | ".join(f"{ms[d]:.1f}" for d in (1, 2, 4, 8)) +
          f" | {ms[1] / vtk_ms:.2f} | {best} |")
PY
