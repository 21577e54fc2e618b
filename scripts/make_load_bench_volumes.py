#!/usr/bin/env python3
"""Synthetic 256³ NRRD volumes of the sample types the shared data lacks (float32, int32, float64,
gzip u8), for `voxlight bench load`'s peak-memory measurement (docs/benchmarks.md).

  python3 scripts/make_load_bench_volumes.py /tmp/loadbench
  voxlight bench load --data /tmp/loadbench \
      --datasets float256.nrrd,int256.nrrd,double256.nrrd,uchar256-gz.nrrd
"""

import gzip
import pathlib
import sys

import numpy as np

N = 256


def write(path: pathlib.Path, values: np.ndarray, nrrd_type: str, encoding: str = "raw") -> None:
    header = (
        f"NRRD0004\ntype: {nrrd_type}\ndimension: 3\nsizes: {N} {N} {N}\n"
        f"spacings: 1 1 1\nendian: little\nencoding: {encoding}\n\n"
    ).encode()
    body = values.astype(values.dtype.newbyteorder("<")).tobytes()
    if encoding == "gzip":
        body = gzip.compress(body, 1)
    path.write_bytes(header + body)


def main() -> None:
    out = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/loadbench")
    out.mkdir(parents=True, exist_ok=True)
    axis = np.linspace(-1, 1, N, dtype=np.float32)
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij")
    blob = (np.exp(-(x * x + y * y + z * z) * 3) * 1000 - 200).astype(np.float32)
    write(out / "float256.nrrd", blob, "float")
    write(out / "int256.nrrd", blob.astype(np.int32), "int")
    write(out / "double256.nrrd", blob.astype(np.float64), "double")
    write(out / "uchar256-gz.nrrd", np.clip(blob / 4 + 50, 0, 255).astype(np.uint8), "uchar", "gzip")
    print(f"wrote 4 volumes to {out}")


if __name__ == "__main__":
    main()
