#!/usr/bin/env python3
"""Cross-check voxlight's `pathtrace` (and `raymarch`, against single scattering) with Mitsuba 3,
an independent path tracer.

The scene is built so that both renderers see exactly the same physics (DESIGN.md's model):
a heterogeneous volume of smooth Gaussian blobs with values in [0, 1], a *linear* transfer
function (opacity = v, constant albedo) so that post-classification equals Mitsuba's
interpolated extinction grid, a uniform environment and one directional light, isotropic
phase function, and the default pinhole camera.

  pip install mitsuba   (variant scalar_rgb, or llvm_ad_rgb with Debian's libllvm19)
  cargo build --release -p voxlight-server
  python3 scripts/compare_mitsuba.py [--spp 1024] [--size 96] [--out target/mitsuba]

Prints the mean radiance of both images and the relative RMSE over 8×8-pixel blocks (block
averages keep the Monte-Carlo noise of either image from dominating the comparison), over the
whole image and over the blocks that show the volume, and exits non-zero when either exceeds
--tolerance (default 2%) or when the mirrored Mitsuba image matches better.
"""

import argparse
import json
import os
import pathlib
import subprocess
import sys

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
    ap.add_argument("--technique", choices=["pathtrace", "raymarch"], default="pathtrace",
                    help="raymarch is compared with Mitsuba limited to single scattering (max_depth 2)")
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--grid", type=int, default=48)
    ap.add_argument("--density", type=float, default=40.0)
    ap.add_argument("--albedo", type=float, nargs=3, default=[0.9, 0.7, 0.5])
    ap.add_argument("--tolerance", type=float, default=0.02)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--voxlight", default=str(REPO / "target/release/voxlight"))
    ap.add_argument("--out", default=str(REPO / "target/mitsuba"))
    args = ap.parse_args()
    out = pathlib.Path(args.out).resolve()  # the scene file names the volume by absolute path
    out.mkdir(parents=True, exist_ok=True)

    volume = blobs(args.grid)
    nrrd = out / "blobs.nrrd"
    write_nrrd(nrrd, volume)
    env = [0.3, 0.3, 0.3]
    sun_dir = [0.3, 0.4, -0.866]
    sun = [2.0, 2.0, 2.0]
    camera = {"eye": [0.0, -2.4, 0.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0], "fov_deg": 30.0}

    # voxlight
    scene = {
        "dataset": str(nrrd),
        "camera": camera,
        "tf": {"points": [
            {"value": 0.0, "color": args.albedo, "opacity": 0.0},
            {"value": 1.0, "color": args.albedo, "opacity": 1.0},
        ]},
        "lights": [
            {"kind": "environment", "radiance": env},
            {"kind": "directional", "direction": sun_dir, "irradiance": sun},
        ],
        "technique": args.technique,
        "density_scale": args.density,
        "g": 0.0,
        "width": args.size,
        "height": args.size,
        "iterations": args.spp,
        "seed": 1,
    }
    scene_path = out / "scene.json"
    scene_path.write_text(json.dumps(scene, indent=2))
    ours_pfm = out / "voxlight.pfm"
    subprocess.run([args.voxlight, "render", "--scene", str(scene_path), "--out", str(out / "voxlight.png"),
                    "--pfm", str(ours_pfm)], check=True, env={**os.environ, "RUST_LOG": "warn"})
    ours = read_pfm(ours_pfm)

    # Mitsuba 3
    import mitsuba as mi
    mi.set_variant(args.variant)
    from mitsuba import ScalarTransform4f as T

    n = args.grid
    # voxlight normalizes the NRRD to 16 bits; give Mitsuba the same quantized values.
    quantized = np.round(volume * 65535.0) / 65535.0
    sigma_t = mi.VolumeGrid((quantized * args.density)[..., None].astype(np.float32))
    medium = {
        "type": "heterogeneous",
        "albedo": {"type": "rgb", "value": args.albedo},
        "sigma_t": {"type": "gridvolume", "grid": sigma_t, "filter_type": "trilinear",
                    "to_world": T().translate([-0.5, -0.5, -0.5])},
        "scale": 1.0,
        "phase": {"type": "isotropic"},
    }
    mscene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": 1024 if args.technique == "pathtrace" else 2,
                       "rr_depth": 1000},
        "sensor": {
            "type": "perspective",
            "fov": camera["fov_deg"],
            "fov_axis": "y",
            "to_world": T().look_at(origin=camera["eye"], target=camera["target"], up=camera["up"]),
            "film": {"type": "hdrfilm", "width": args.size, "height": args.size,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": args.spp},
        },
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": env}},
        "sun": {"type": "directional", "direction": sun_dir, "irradiance": {"type": "rgb", "value": sun}},
        "box": {
            "type": "cube",
            "to_world": T().scale(0.5),
            "bsdf": {"type": "null"},
            "interior": medium,
        },
    })
    theirs = np.array(mi.render(mscene), dtype=np.float32)[..., :3]
    mi.util.write_bitmap(str(out / "mitsuba.exr"), theirs)

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
        "technique": args.technique, "spp": args.spp, "size": args.size, "grid": n, "density_scale": args.density,
        "mean_voxlight": mean_ours, "mean_mitsuba": mean_theirs,
        "mean_rel_diff": mean_ours / mean_theirs - 1.0,
        "block8_rel_rmse": rel_rmse, "block8_rel_rmse_mirrored": results["mirrored x"],
        "object_blocks": int(on_object.sum()), "object_block8_rel_rmse": object_rmse,
        "best_orientation": best, "mitsuba_variant": args.variant,
    }
    print(json.dumps(report))
    if best != "as is":
        print("orientation mismatch: the mirrored Mitsuba image matches better", file=sys.stderr)
        return 1
    return 0 if max(rel_rmse, object_rmse) <= args.tolerance else 1


if __name__ == "__main__":
    sys.exit(main())
