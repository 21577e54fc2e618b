#!/usr/bin/env python3
"""Cross-check every voxlight technique (`pathtrace`, `photon`, `irradiance`, `manylight`, and
`raymarch` against single scattering) with Mitsuba 3, an independent path tracer.

The scene is built so that both renderers see exactly the same physics (DESIGN.md's model):
a heterogeneous volume of smooth Gaussian blobs with values in [0, 1], a *linear* transfer
function (opacity = v, constant albedo) so that post-classification equals Mitsuba's
interpolated extinction grid, a uniform environment and one directional light, isotropic
phase function, and the default pinhole camera.

  pip install mitsuba   (variant scalar_rgb, or llvm_ad_rgb with Debian's libllvm19)
  cargo build --release -p voxlight-server
  python3 scripts/compare_mitsuba.py [--technique photon] [--spp 1024] [--size 96] [--out target/mitsuba]

Scenes (--scene): `sun` (environment + directional light, the default), `point` (environment +
a point light), `dense` (the sun scene with albedo 0.99 and twice the density: multiple
scattering dominates), `ct` (a real CT, nifti/example_ct_sm.nii.gz from ../shared/data,
resampled to --grid, windowed to HU -200..1500). --spp is voxlight's iteration budget (spp
for pathtrace, passes for photon, iterations for the others); --ref-spp is Mitsuba's (its
image is cached in --out's parent folder by everything that defines it, so that sweeps and
several techniques pay for it once). --options passes
technique options (JSON, the protocol's `technique_options`). The report adds voxlight's wall
time and the ratio of the means.

Prints the mean radiance of both images and the relative RMSE over 8×8-pixel blocks (block
averages keep the Monte-Carlo noise of either image from dominating the comparison), over the
whole image and over the blocks that show the volume, and exits non-zero when either exceeds
--tolerance (default 2%), when |mean ratio - 1| exceeds --mean-tolerance (default: off), or when
the mirrored Mitsuba image matches better.
"""

import argparse
import gzip
import hashlib
import json
import os
import pathlib
import resource
import subprocess
import sys
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parent.parent


def blobs(n: int) -> np.ndarray:
    """A smooth heterogeneous field in [0, 1], shape (z, y, x), x fastest; asymmetric on purpose."""
    c = (np.arange(n) + 0.5) / n - 0.5
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    field = np.zeros_like(x)
    for (cx, cy, cz, r, a) in [(-0.15, 0.05, 0.1, 0.18, 1.0), (0.18, -0.1, -0.12, 0.14, 0.7), (0.05, 0.15, -0.2, 0.1, 0.5)]:
        field += a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) / (2 * r * r))
    field = np.clip(field, 0.0, 1.0)
    field[0, 0, 0] = 0.0
    field[n // 2, n // 2, n // 2] = max(field[n // 2, n // 2, n // 2], 1.0)
    return (field / field.max()).astype(np.float32)


def real_ct(n: int) -> np.ndarray:
    """nifti/example_ct_sm.nii.gz (122×101×30 voxels of 3 mm, HU), cropped to its central
    x/y square, resampled (box filter) to n×n×30·n/101 voxels and normalized to [0, 1]; shape
    (z, y, x). The voxels stay cubic, so the box is 1 × 1 × nz/n world units."""
    data_dir = pathlib.Path(os.environ.get("VOXLIGHT_DATA", REPO.parent / "shared" / "data"))
    path = data_dir / "nifti" / "example_ct_sm.nii.gz"
    if not path.exists():
        sys.exit(f"real CT {path} is missing (set VOXLIGHT_DATA to ../shared/data)")
    raw = gzip.decompress(path.read_bytes())
    dims = np.frombuffer(raw[40:56], dtype="<i2")
    nx, ny, nz = (int(d) for d in dims[1:4])
    datatype = int(np.frombuffer(raw[70:72], dtype="<i2")[0])
    offset = int(np.frombuffer(raw[108:112], dtype="<f4")[0])
    slope, inter = (float(v) for v in np.frombuffer(raw[112:120], dtype="<f4"))
    dtype = {4: "<i2", 8: "<i4", 16: "<f4"}[datatype]
    hu = np.frombuffer(raw[offset:], dtype=dtype, count=nx * ny * nz).reshape(nz, ny, nx).astype(np.float64)
    hu = hu * (slope if slope != 0 else 1.0) + inter
    side = min(nx, ny)
    x0, y0 = (nx - side) // 2, (ny - side) // 2
    hu = hu[:, y0:y0 + side, x0:x0 + side]
    # Box-filter resample to n along x and y, and keep the slices' proportion along z.
    mz = max(2, round(nz * n / side))
    def resample(a: np.ndarray, axis: int, m: int) -> np.ndarray:
        edges = np.linspace(0, a.shape[axis], m + 1).round().astype(int)
        return np.stack([np.take(a, range(edges[i], max(edges[i + 1], edges[i] + 1)), axis=axis).mean(axis=axis)
                         for i in range(m)], axis=axis)
    hu = resample(resample(resample(hu, 2, n), 1, n), 0, mz)
    # Window: air and fat clear, soft tissue faint, bone dense. The window is applied to the
    # data (not as a TF knee) so that the linear TF's post-classification still equals
    # Mitsuba's interpolated extinction grid.
    v = np.clip((hu + 200.0) / 1700.0, 0.0, 1.0)
    v[0, 0, 0] = 0.0
    return (v / v.max()).astype(np.float32)


def write_nrrd(path: pathlib.Path, volume: np.ndarray) -> None:
    nz, ny, nx = volume.shape
    header = (
        "NRRD0004\n"
        "type: float\n"
        "dimension: 3\n"
        f"sizes: {nx} {ny} {nz}\n"
        "spacings: 1 1 1\n"
        "endian: little\n"
        "encoding: raw\n\n"
    )
    path.write_bytes(header.encode() + volume.astype("<f4").tobytes())


def read_pfm(path: pathlib.Path) -> np.ndarray:
    data = path.read_bytes()
    parts = data.split(b"\n", 3)
    w, h = map(int, parts[1].split())
    scale = float(parts[2])
    img = np.frombuffer(parts[3], dtype="<f4" if scale < 0 else ">f4").reshape(h, w, 3)
    return img[::-1].copy()  # PFM stores the bottom row first


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--technique", choices=["pathtrace", "raymarch", "photon", "irradiance", "manylight"],
                    default="pathtrace",
                    help="raymarch is compared with Mitsuba limited to single scattering (max_depth 2)")
    ap.add_argument("--scene", choices=["sun", "point", "dense", "ct"], default="sun")
    ap.add_argument("--spp", type=int, default=1024, help="voxlight's iterations (spp, passes)")
    ap.add_argument("--ref-spp", type=int, default=None, help="Mitsuba's spp (default: --spp)")
    ap.add_argument("--max-depth", type=int, default=None,
                    help="Mitsuba's max_depth (default 1024; 2 for raymarch)")
    ap.add_argument("--seed", type=int, default=1,
                    help="voxlight's scene seed (independent renders for telling variance from bias)")
    ap.add_argument("--options", default=None, help="technique_options, JSON")
    ap.add_argument("--mean-tolerance", type=float, default=None,
                    help="also fail when |mean ratio - 1| exceeds this")
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--grid", type=int, default=48)
    ap.add_argument("--density", type=float, default=None, help="default 40 (80 for dense, 60 for ct)")
    ap.add_argument("--albedo", type=float, nargs=3, default=None,
                    help="default 0.9 0.7 0.5 (0.99 0.97 0.95 for dense)")
    ap.add_argument("--tolerance", type=float, default=0.02)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--voxlight", default=str(REPO / "target/release/voxlight"))
    ap.add_argument("--out", default=str(REPO / "target/mitsuba"))
    args = ap.parse_args()
    out = pathlib.Path(args.out).resolve()  # the scene file names the volume by absolute path
    out.mkdir(parents=True, exist_ok=True)

    if args.density is None:
        args.density = {"dense": 80.0, "ct": 60.0}.get(args.scene, 40.0)
    if args.albedo is None:
        args.albedo = [0.99, 0.97, 0.95] if args.scene == "dense" else [0.9, 0.7, 0.5]
    volume = real_ct(args.grid) if args.scene == "ct" else blobs(args.grid)
    nrrd = out / ("ct.nrrd" if args.scene == "ct" else "blobs.nrrd")
    write_nrrd(nrrd, volume)
    # The box: longest side 1 world unit, cubic voxels (DESIGN.md).
    extent = np.array(volume.shape[::-1], dtype=np.float64) / max(volume.shape)
    env = [0.3, 0.3, 0.3]
    sun_dir = [0.3, 0.4, -0.866]
    sun = [2.0, 2.0, 2.0]
    point_pos = [0.6, -0.7, 0.8]
    point = [1.5, 1.5, 1.5]
    camera = {"eye": [0.0, -2.4, 0.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0], "fov_deg": 30.0}
    lights = [{"kind": "environment", "radiance": env}]
    if args.scene == "point":
        lights.append({"kind": "point", "position": point_pos, "intensity": point})
    else:
        lights.append({"kind": "directional", "direction": sun_dir, "irradiance": sun})
    tf_points = [
        {"value": 0.0, "color": args.albedo, "opacity": 0.0},
        {"value": 1.0, "color": args.albedo, "opacity": 1.0},
    ]

    # voxlight
    scene = {
        "dataset": str(nrrd),
        "camera": camera,
        "tf": {"points": tf_points},
        "lights": lights,
        "technique": args.technique,
        "density_scale": args.density,
        "g": 0.0,
        "width": args.size,
        "height": args.size,
        "iterations": args.spp,
        "seed": args.seed,
    }
    if args.options:
        scene["technique_options"] = json.loads(args.options)
    scene_path = out / "scene.json"
    scene_path.write_text(json.dumps(scene, indent=2))
    ours_pfm = out / "voxlight.pfm"
    started = time.monotonic()
    cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([args.voxlight, "render", "--scene", str(scene_path), "--out", str(out / "voxlight.png"),
                    "--pfm", str(ours_pfm)], check=True, env={**os.environ, "RUST_LOG": "warn"})
    seconds = time.monotonic() - started
    # CPU time too: on a shared VM (lavapipe) it varies less with other jobs than wall time.
    cpu_after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_seconds = (cpu_after.ru_utime - cpu_before.ru_utime) + (cpu_after.ru_stime - cpu_before.ru_stime)
    ours = read_pfm(ours_pfm)
    theirs = mitsuba_reference(args, out, volume, extent, camera, env, sun_dir, sun, point_pos, point)
    # Beside voxlight's image, for per-block looks and for averaging independent renders.
    np.save(out / "mitsuba.npy", theirs)
    return compare(args, ours, theirs, env, seconds, cpu_seconds)


def mitsuba_reference(args, out, volume, extent, camera, env, sun_dir, sun, point_pos, point) -> np.ndarray:
    """Mitsuba's image of the scene, cached under `out` by everything that defines it."""
    ref_spp = args.ref_spp or args.spp
    max_depth = args.max_depth or (2 if args.technique == "raymarch" else 1024)
    key = hashlib.sha256(json.dumps([args.scene, args.size, args.grid, args.density, args.albedo, ref_spp,
                                     max_depth, args.variant, camera, env, sun_dir, sun, point_pos, point,
                                     extent.tolist()]).encode() + volume.tobytes()).hexdigest()[:16]
    cache = out.parent / f"mitsuba-ref-{key}.npy"
    if cache.exists():
        return np.load(cache)

    # Mitsuba 3
    import mitsuba as mi
    mi.set_variant(args.variant)
    from mitsuba import ScalarTransform4f as T

    # voxlight normalizes the NRRD to 16 bits; give Mitsuba the same quantized values.
    quantized = np.round(volume * 65535.0) / 65535.0
    sigma_t = mi.VolumeGrid((quantized * args.density)[..., None].astype(np.float32))
    medium = {
        "type": "heterogeneous",
        "albedo": {"type": "rgb", "value": args.albedo},
        "sigma_t": {"type": "gridvolume", "grid": sigma_t, "filter_type": "trilinear",
                    "to_world": T().translate((-0.5 * extent).tolist()).scale(extent.tolist())},
        "scale": 1.0,
        "phase": {"type": "isotropic"},
    }
    mscene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": max_depth, "rr_depth": 1000},
        "sensor": {
            "type": "perspective",
            "fov": camera["fov_deg"],
            "fov_axis": "y",
            "to_world": T().look_at(origin=camera["eye"], target=camera["target"], up=camera["up"]),
            "film": {"type": "hdrfilm", "width": args.size, "height": args.size,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": ref_spp},
        },
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": env}},
        **({"light": {"type": "point", "position": point_pos, "intensity": {"type": "rgb", "value": point}}}
           if args.scene == "point" else
           {"light": {"type": "directional", "direction": sun_dir, "irradiance": {"type": "rgb", "value": sun}}}),
        "box": {
            "type": "cube",
            "to_world": T().scale((0.5 * extent).tolist()),
            "bsdf": {"type": "null"},
            "interior": medium,
        },
    })
    theirs = np.array(mi.render(mscene), dtype=np.float32)[..., :3]
    mi.util.write_bitmap(str(out / "mitsuba.exr"), theirs)
    np.save(cache, theirs)
    return theirs


def compare(args, ours: np.ndarray, theirs: np.ndarray, env, seconds: float, cpu_seconds: float) -> int:
    def blocks(img: np.ndarray, b: int = 8) -> np.ndarray:
        h, w, _ = img.shape
        return img[: h - h % b, : w - w % b].reshape(h // b, b, w // b, b, 3).mean(axis=(1, 3))

    results = {}
    for name, candidate in [("as is", theirs), ("mirrored x", theirs[:, ::-1])]:
        a, b = blocks(ours), blocks(candidate)
        results[name] = float(np.sqrt(np.mean((a - b) ** 2)) / np.mean(b))
    best = min(results, key=results.get)
    rel_rmse = results["as is"]
    # The same over the blocks that show the volume (not just the environment behind it).
    a, b = blocks(ours), blocks(theirs)
    on_object = np.abs(b.mean(axis=2) / np.mean(env) - 1.0) > 0.05
    object_rmse = float(np.sqrt(np.mean((a[on_object] - b[on_object]) ** 2)) / np.mean(b[on_object]))
    mean_ours, mean_theirs = float(ours.mean()), float(theirs.mean())
    report = {
        "technique": args.technique, "scene": args.scene, "spp": args.spp, "ref_spp": args.ref_spp or args.spp,
        "seed": args.seed, "size": args.size, "grid": args.grid, "density_scale": args.density, "options": args.options,
        "seconds": round(seconds, 2), "cpu_seconds": round(cpu_seconds, 2),
        "mean_voxlight": mean_ours, "mean_mitsuba": mean_theirs,
        "mean_ratio": mean_ours / mean_theirs, "mean_rel_diff": mean_ours / mean_theirs - 1.0,
        "block8_rel_rmse": rel_rmse, "block8_rel_rmse_mirrored": results["mirrored x"],
        "object_blocks": int(on_object.sum()), "object_block8_rel_rmse": object_rmse,
        "best_orientation": best, "mitsuba_variant": args.variant,
    }
    print(json.dumps(report))
    if best != "as is":
        print("orientation mismatch: the mirrored Mitsuba image matches better", file=sys.stderr)
        return 1
    if args.mean_tolerance is not None and abs(mean_ours / mean_theirs - 1.0) > args.mean_tolerance:
        print(f"mean ratio {mean_ours / mean_theirs:.4f} off by more than {args.mean_tolerance}", file=sys.stderr)
        return 1
    return 0 if max(rel_rmse, object_rmse) <= args.tolerance else 1


if __name__ == "__main__":
    sys.exit(main())
