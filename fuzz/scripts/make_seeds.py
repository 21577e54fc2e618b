#!/usr/bin/env python3
"""Writes the fuzz seed corpora (fuzz/seeds/<target>/) from the real data in ../shared/data
(or $VOXLIGHT_DATA): headers of the real files with small slices of their real voxels, plus a
few synthetic variants of each format. Every seed stays under 64 KiB. Run from anywhere:
    python3 fuzz/scripts/make_seeds.py
"""

import gzip
import json
import os
import re
import struct
import sys
import zlib
from pathlib import Path

FUZZ = Path(__file__).resolve().parent.parent
DATA = Path(os.environ.get("VOXLIGHT_DATA", FUZZ.parent.parent / "shared" / "data"))
SEEDS = FUZZ / "seeds"
LIMIT = 64 * 1024


def put(target: str, name: str, data: bytes) -> None:
    assert len(data) <= LIMIT, f"{target}/{name} is {len(data)} bytes"
    d = SEEDS / target
    d.mkdir(parents=True, exist_ok=True)
    (d / name).write_bytes(data)


def protocol() -> None:
    messages = [
        {"type": "hello", "protocol": 1, "viewport": {"width": 960, "height": 720},
         "dataset": "phantom:sphere", "technique": "raymarch"},
        {"type": "hello", "protocol": 1, "session": "6c1f0e1e9a4b47d2b3a1c0ffee5a7d21",
         "name": "Dr. Ada", "max_in_flight": 2,
         "technique_options": {"photon": {"passes": 4}}},
        {"type": "ack", "seq": 41},
        {"type": "name", "name": "Ada"},
        {"type": "dataset", "name": "nrrd/tooth.nrrd"},
        {"type": "camera", "eye": [0, -2.4, 0], "target": [0, 0, 0], "up": [0, 0, 1],
         "fov_deg": 30},
        {"type": "tf", "points": [
            {"value": 0.0, "color": [0.1, 0.2, 0.9], "opacity": 0.0},
            {"value": 0.5, "color": [1, 1, 1], "opacity": 0.25},
            {"value": 1.0, "color": [0.9, 0.8, 0.7], "opacity": 0.8}]},
        {"type": "tf", "points": []},
        {"type": "lights", "lights": [
            {"kind": "directional", "direction": [0.35, 0.75, -0.55], "irradiance": [3.2, 3.1, 2.9]},
            {"kind": "point", "position": [0, 0, 2], "intensity": [3, 3, 3]},
            {"kind": "environment", "radiance": [0.1, 0.11, 0.13]}]},
        {"type": "technique", "name": "manylight",
         "options": {"manylight": {"virtual_lights": 1000, "transmittance": "ray_marched"}}},
        {"type": "technique", "name": "irradiance",
         "options": {"irradiance": {"locking": "screen", "max_radius_voxels": 2, "gamma": 0.1}}},
        {"type": "viewport", "width": 64, "height": 48},
        {"type": "params", "density_scale": 60, "g": 0.3, "exposure": 1.5},
        {"type": "quality", "jpeg_quality": 70, "iterations": 256},
    ]
    for i, m in enumerate(messages):
        put("protocol_decode", f"{i:02}-{m['type']}.json", json.dumps(m).encode())


def frames() -> None:
    metas = [
        {"seq": 7, "format": "jpeg", "width": 96, "height": 64, "technique": "raymarch",
         "iteration": 4, "target_iterations": 128, "converged": False, "lossless": False,
         "quality": 85, "scene_version": 3, "render_ms": 1.5, "encode_ms": 0.25},
        {"seq": 8, "format": "png", "width": 2, "height": 3, "technique": "photon",
         "iteration": 128, "target_iterations": 128, "converged": True, "lossless": True,
         "scene_version": 3, "preview": True, "resolution_scale": 0.25,
         "preview_match": {"gain": [1.25, 1, 0.5], "multiple_weight": [0.5, 0, 0.25]},
         "render_ms": 2, "encode_ms": 1, "details": {"photons_traced": 100000, "virtual_lights": 3}},
    ]
    for i, m in enumerate(metas):
        j = json.dumps(m, separators=(",", ":")).encode()
        put("split_frame", f"{i}.bin", struct.pack("<I", len(j)) + j + bytes(range(40)))


def scenes() -> None:
    cornell = (FUZZ.parent / "docs" / "scenes" / "cornell.json").read_bytes()
    put("scene_file", "cornell.json", cornell)
    put("scene_file", "minimal.json", b'{"dataset":"phantom:sphere"}')
    put("scene_file", "full.json", json.dumps({
        "dataset": "nrrd/tooth.nrrd",
        "camera": {"eye": [2, -1, 0.5], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 35},
        "tf": {"points": [{"value": 0.2, "color": [1, 1, 1], "opacity": 0.0},
                          {"value": 1.0, "color": [1, 0.9, 0.8], "opacity": 0.7}]},
        "lights": [{"kind": "environment", "radiance": [0.25, 0.5, 0.75]}],
        "technique": "pathtrace", "technique_options": {"photon": {"bounces": 2}},
        "density_scale": 30, "g": -0.2, "exposure": 2, "width": 48, "height": 32,
        "iterations": 2, "seed": 9}).encode())


def nrrd() -> None:
    tooth = (DATA / "nrrd" / "tooth.nrrd").read_bytes()
    end = tooth.index(b"\n\n") + 2
    header, body = tooth[:end], tooth[end:]
    # The real header with the first 16 KiB of its data (truncated: an error path).
    put("load_nrrd", "tooth-cut.nrrd", header + body[:16384])
    # The real header resized to a 16×16×8 block of real voxels (loads).
    small = re.sub(rb"sizes: [0-9 ]+", b"sizes: 16 16 8", header)
    put("load_nrrd", "tooth-small.nrrd", small + body[:2048])
    # Gzip and ascii encodings of the same block, and a 2D slice.
    gz_header = small.replace(b"encoding: raw", b"encoding: gzip")
    put("load_nrrd", "tooth-gzip.nrrd", gz_header + gzip.compress(body[:2048]))
    ascii_header = re.sub(rb"sizes: [0-9 ]+", b"sizes: 8 8 2", header).replace(
        b"encoding: raw", b"encoding: ascii")
    put("load_nrrd", "tooth-ascii.nrrd",
        ascii_header + b"\n".join(b" ".join(b"%d" % v for v in body[r * 8:r * 8 + 8])
                                  for r in range(16)) + b"\n")
    put("load_nrrd", "slice-2d.nrrd",
        b"NRRD0004\ntype: float\ndimension: 2\nsizes: 4 4\nendian: little\nencoding: raw\n"
        b"spacings: 0.5 0.25\n\n" + struct.pack("<16f", *[i * 0.5 - 3 for i in range(16)]))
    # Detached headers: the real one (its tooth.raw is the harness's 8 KiB companion, so the
    # real sizes are a truncation) and one sized to the companion.
    nhdr = (DATA / "nrrd" / "tooth.nhdr").read_bytes()
    put("load_nrrd", "tooth.nhdr", nhdr)
    put("load_nrrd", "tooth-small.nhdr", re.sub(rb"sizes: [0-9 ]+", b"sizes: 32 16 8", nhdr))
    put("load_nrrd", "detached-gzip.nhdr",
        b"NRRD0005\ntype: int16\ndimension: 3\nsizes: 8 8 4\nendian: little\n"
        b"encoding: gzip\nbyte skip: 16\nline skip: 0\ndata file: data.raw.gz\n")
    raw = (DATA / "nrrd" / "tooth.raw").read_bytes()[:8192]
    companions = SEEDS / "companions"
    companions.mkdir(parents=True, exist_ok=True)
    (companions / "tooth.raw").write_bytes(raw)
    (companions / "data.raw.gz").write_bytes(gzip.compress(bytes(16) + raw[:512]))


def nifti() -> None:
    nii = gzip.decompress((DATA / "nifti" / "example_ct_sm.nii.gz").read_bytes())
    hdr = bytearray(nii[:348])
    vox_offset = int(struct.unpack_from("<f", hdr, 108)[0])
    ext = nii[348:vox_offset]
    data = nii[vox_offset:]
    # The real header and extensions with the first KiBs of data (truncated: an error path).
    put("load_nifti", "ct-sm-cut.nii", bytes(hdr) + ext + data[:8192])
    # Resized to a 16×16×4 block of the real int16 voxels (loads), plain and gzip.
    small = bytearray(hdr)
    struct.pack_into("<8h", small, 40, 3, 16, 16, 4, 1, 1, 1, 1)
    block = bytes(small) + ext + data[:16 * 16 * 4 * 2]
    put("load_nifti", "ct-sm-small.nii", block)
    put("load_nifti", "ct-sm-small.nii.gz", gzip.compress(block))
    # The big CT's header alone, gzip (truncated data).
    big = gzip.GzipFile(DATA / "nifti" / "example_ct.nii.gz").read(4096)
    put("load_nifti", "ct-head.nii.gz", gzip.compress(big))
    # A .hdr/.img pair header (the harness writes an 8 KiB pair.img): 16×16×16 uint8, scaled.
    pair = bytearray(small)
    struct.pack_into("<8h", pair, 40, 3, 16, 16, 16, 1, 1, 1, 1)
    struct.pack_into("<hh", pair, 70, 2, 8)
    struct.pack_into("<fff", pair, 108, 0.0, 2.0, -100.0)
    pair[344:348] = b"ni1\0"
    put("load_nifti", "pair.hdr", bytes(pair))
    # Big-endian float32 4×4×4 with odd pixdims.
    be = bytearray(348)
    struct.pack_into(">i", be, 0, 348)
    struct.pack_into(">8h", be, 40, 3, 4, 4, 4, 1, 1, 1, 1)
    struct.pack_into(">hh", be, 70, 16, 32)
    struct.pack_into(">8f", be, 76, 1, 0.5, -2, 0, 1, 1, 1, 1)
    struct.pack_into(">f", be, 108, 352.0)
    be[344:348] = b"n+1\0"
    put("load_nifti", "be-float.nii",
        bytes(be) + bytes(4) + struct.pack(">64f", *[i / 3 for i in range(64)]))


def vti_xml(ext: str, compressor: bool, header_type: str, fmt: str, offset: bool) -> bytes:
    comp = ' compressor="vtkZLibDataCompressor"' if compressor else ""
    off = ' offset="0"' if offset else ""
    return (f'<?xml version="1.0"?>\n<VTKFile type="ImageData" version="1.0" '
            f'byte_order="LittleEndian" header_type="{header_type}"{comp}>\n'
            f'  <ImageData WholeExtent="{ext}" Origin="0 0 0" Spacing="1 1 1">\n'
            f'    <Piece Extent="{ext}">\n      <PointData Scalars="ImageFile">\n'
            f'        <DataArray type="UInt8" Name="ImageFile" format="{fmt}"{off}>').encode()


def vti() -> None:
    b = (DATA / "vti" / "bonsai.vti").read_bytes()
    head_end = b.index(b"<AppendedData")
    start = b.index(b"_", head_end) + 1
    # The real file cut after its XML head and a part of its compression header.
    put("load_vti", "bonsai-cut.vti", b[:start + 4096])
    # The first zlib block's voxels, re-packed small.
    nblocks, blocksize, last = struct.unpack_from("<QQQ", b, start)
    first = struct.unpack_from("<Q", b, start + 24)[0]
    pos = start + 24 + 8 * nblocks
    voxels = zlib.decompress(b[pos:pos + first])[:16 * 16 * 8]
    ext = "0 15 0 15 0 7"
    tail = b"\n        </DataArray>\n      </PointData>\n    </Piece>\n  </ImageData>\n"
    appended = lambda payload: (b'  <AppendedData encoding="raw">\n   _' + payload
                                + b"\n  </AppendedData>\n</VTKFile>\n")
    blocks = [voxels[i:i + 1024] for i in range(0, len(voxels), 1024)]
    packed = [zlib.compress(x) for x in blocks]
    zhead = struct.pack("<QQQ", len(blocks), 1024, 0) + b"".join(
        struct.pack("<Q", len(p)) for p in packed)
    put("load_vti", "bonsai-zlib.vti",
        vti_xml(ext, True, "UInt64", "appended", True) + tail + appended(zhead + b"".join(packed)))
    put("load_vti", "bonsai-plain.vti",
        vti_xml(ext, False, "UInt32", "appended", True) + tail
        + appended(struct.pack("<I", len(voxels)) + voxels))
    import base64
    small = voxels[:4 * 4 * 4]
    put("load_vti", "inline-base64.vti",
        vti_xml("0 3 0 3 0 3", False, "UInt32", "binary", False) + b"\n"
        + base64.b64encode(struct.pack("<I", len(small)) + small) + tail + b"</VTKFile>\n")
    put("load_vti", "inline-ascii.vti",
        vti_xml("0 3 0 3 0 3", False, "UInt32", "ascii", False) + b"\n"
        + b" ".join(b"%d" % v for v in small) + tail + b"</VTKFile>\n")


def raw() -> None:
    tooth = (DATA / "nrrd" / "tooth.raw").read_bytes()
    # dims (u16 ×3), type|endian, spacing f32, header bytes u16, 2 spare, flags.
    params = struct.pack("<HHHBfH", 16, 16, 8, 2 | 8, 1.0, 0) + b"\0\0\0"
    put("load_raw", "tooth-u16be.bin", params + tooth[:4096])
    params = struct.pack("<HHHBfH", 8, 8, 8, 7, 0.5, 16) + b"\0\0\0"
    put("load_raw", "f64-le.bin", params + bytes(16) + struct.pack("<512d", *range(512)))


def dicom() -> None:
    # The first slice's header with its pixel data cut to a 16×16 image: Rows, Columns and the
    # Pixel Data length patched (Implicit VR Little Endian: tag, 4-byte length, value).
    src = sorted((DATA / "ct-chest-lidc").glob("*.dcm"))[0].read_bytes()
    pixel = src.index(b"\xe0\x7f\x10\x00")
    head = bytearray(src[:pixel])
    for tag in (b"\x28\x00\x10\x00\x02\x00\x00\x00", b"\x28\x00\x11\x00\x02\x00\x00\x00"):
        at = head.index(tag, 132) + len(tag)
        struct.pack_into("<H", head, at, 16)
    data = src[pixel + 8:pixel + 8 + 16 * 16 * 2]
    put("load_dicom", "ct-16x16.dcm", bytes(head) + b"\xe0\x7f\x10\x00"
        + struct.pack("<I", len(data)) + data)
    # The real header with a cut pixel data element (truncated: an error path).
    put("load_dicom", "ct-cut.dcm", src[:pixel + 8 + 8192])


if __name__ == "__main__":
    if not DATA.is_dir():
        sys.exit(f"no data folder at {DATA}; set VOXLIGHT_DATA")
    for make in (protocol, frames, scenes, nrrd, nifti, vti, raw, dicom):
        make()
    for d in sorted(SEEDS.iterdir()):
        files = list(d.iterdir())
        print(f"{d.name}: {len(files)} files, {sum(f.stat().st_size for f in files)} bytes")
