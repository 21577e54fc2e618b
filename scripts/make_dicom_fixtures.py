#!/usr/bin/env python3
"""Makes DICOM test fixtures from the chest CT series (../shared/data/ct-chest-lidc) with real
encoders, for voxlight's DICOM loader tests (server/volumes/tests/dicom_codecs.rs) and its
load-time benchmark.

Needs: dcmtk (dcmconv, dcmcrle, dcmcjpeg, dcmdjpeg, dcmcjpls, dcmdjpls), GDCM's command-line
tools (gdcmconv; Debian package libgdcm-tools), and Python 3 with pydicom 3 and numpy
(pip install 'pydicom>=3' numpy). pydicom only assembles files (the signed / 8-bit / bright /
MONOCHROME1 / enhanced multi-frame variants); it never decodes anything the tests compare
against. The lossy variants are also decoded back by the encoders' own decoders
(*-dcmtk-decoded, *-gdcm-decoded) as references for voxlight's decoding.

Usage: make_dicom_fixtures.py --source DIR --out DIR [--z-range FIRST:END] [--variants a,b,...]

The slices are sorted along the slice normal as voxlight sorts them; --z-range picks sorted
slices FIRST..END-1 (default: all). Each variant becomes one folder OUT/<variant>/. OUT must not
exist yet; the script writes into OUT.partial-<pid> and renames it when everything succeeded, so
a folder named OUT is always complete (when two runs race, the first rename wins).
"""

import argparse
import concurrent.futures
import os
import random
import shutil
import subprocess
import sys
from pathlib import Path

# JPEG-LS near-lossless: the largest allowed error of a stored value (JPEG-LS NEAR parameter).
JPEGLS_NEAR = 3
# Lossy JPEG 2000: compression ratio asked of gdcmconv (-r), about what lossy archives use.
J2K_LOSSY_RATE = 10
# Enhanced multi-frame variant: frame k's stored values are offset by ENHANCED_OFFSETS[k % 3],
# and its per-frame RescaleIntercept compensates, so HU equal the original's only when each
# frame's own PixelValueTransformationSequence is applied.
ENHANCED_OFFSETS = (0, 7, 300)
# "bright" variant: stored values + BRIGHT_SHIFT, clipped at 4095 (HU above 1000 clip).
BRIGHT_SHIFT = 2095
# *-fragmented variants: dcmcjpeg's fragment size limit in kB (+fs), so that each frame's JPEG
# stream (~120 kB at 12 bits) spans several fragments.
FRAGMENT_KB = 16

TOOLS = {
    "dcmcrle": "dcmtk (apt-get install dcmtk)",
    "dcmcjpeg": "dcmtk (apt-get install dcmtk)",
    "dcmcjpls": "dcmtk (apt-get install dcmtk)",
    "dcmconv": "dcmtk (apt-get install dcmtk)",
    "dcmdjpeg": "dcmtk (apt-get install dcmtk)",
    "dcmdjpls": "dcmtk (apt-get install dcmtk)",
    "gdcmconv": "GDCM tools (apt-get install libgdcm-tools)",
}


def fail(msg):
    print(f"make_dicom_fixtures: {msg}", file=sys.stderr)
    sys.exit(2)


def check_tools():
    missing = sorted({pkg for tool, pkg in TOOLS.items() if shutil.which(tool) is None})
    try:
        import numpy  # noqa: F401
        import pydicom

        if int(pydicom.__version__.split(".")[0]) < 3:
            missing.append(
                f"pydicom 3 or newer, found {pydicom.__version__} (pip install 'pydicom>=3')"
            )
    except ImportError as e:
        missing.append(
            f"pydicom and numpy for {sys.executable} (pip install 'pydicom>=3' numpy): {e}"
        )
    if missing:
        fail("missing fixture tools: " + "; ".join(missing))


def run(*cmd):
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    if r.returncode != 0:
        output = r.stderr.strip() or r.stdout.strip()
        fail(f"{' '.join(map(str, cmd))} failed ({r.returncode}): {output}")


def sorted_slices(source):
    import numpy as np
    import pydicom

    slices = []
    for p in sorted(source.glob("*.dcm")):
        ds = pydicom.dcmread(p, stop_before_pixels=True)
        iop = np.array([float(v) for v in ds.ImageOrientationPatient])
        normal = np.cross(iop[:3], iop[3:])
        pos = float(np.dot([float(v) for v in ds.ImagePositionPatient], normal))
        slices.append((pos, p))
    slices.sort()
    return [p for _, p in slices]


def pixels(ds):
    """Stored values of a native (uncompressed) single-frame file, without pydicom's decoding
    pipeline: the raw PixelData bytes viewed as little-endian integers."""
    import numpy as np

    dtype = {(16, 0): "<u2", (16, 1): "<i2", (8, 0): "u1", (8, 1): "i1"}[
        (ds.BitsAllocated, ds.PixelRepresentation)
    ]
    return np.frombuffer(ds.PixelData, dtype=dtype).reshape(ds.Rows, ds.Columns)


def rewrite(src, dst, edit):
    """Reads a native file, lets `edit` change it, writes it as Explicit VR Little Endian."""
    import pydicom
    from pydicom.uid import ExplicitVRLittleEndian

    ds = pydicom.dcmread(src)
    edit(ds)
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.save_as(dst, enforce_file_format=True)


def make_signed(ds):
    # Signed 12-bit stored values that are the Hounsfield units themselves (identity rescale).
    hu = pixels(ds).astype("int32") * int(ds.RescaleSlope) + int(ds.RescaleIntercept)
    ds.PixelRepresentation = 1
    ds.PixelData = hu.astype("<i2").tobytes()
    ds.RescaleSlope = 1
    ds.RescaleIntercept = 0


def make_8bit(ds):
    # 8 bits stored (stored >> 4); RescaleSlope 16 keeps the values in HU (4-HU steps lost).
    s = pixels(ds) >> 4
    ds.BitsAllocated = 8
    ds.BitsStored = 8
    ds.HighBit = 7
    ds.PixelData = s.astype("u1").tobytes()
    ds.RescaleSlope = 16
    ds.RescaleIntercept = int(ds.RescaleIntercept)


def make_bright(ds):
    # Shifted up by BRIGHT_SHIFT and clipped at 4095, the top of the 12-bit range, so that bone
    # forms plateaus at 4095 (HU above 1000 are clipped; the intercept keeps the others). Lossy
    # codecs ring at plateau edges and may reconstruct values above 4095 there.
    import numpy as np

    s = np.minimum(pixels(ds).astype("int32") + BRIGHT_SHIFT, 4095)
    ds.PixelData = s.astype("<u2").tobytes()
    ds.RescaleIntercept = int(ds.RescaleIntercept) - BRIGHT_SHIFT


def make_monochrome1(ds):
    # MONOCHROME1 (minimum = white) with no rescale: stored' = 4095 - stored.
    s = 4095 - pixels(ds).astype("int32")
    ds.PhotometricInterpretation = "MONOCHROME1"
    ds.PixelData = s.astype("<u2").tobytes()
    for kw in ("RescaleSlope", "RescaleIntercept", "RescaleType"):
        if kw in ds:
            delattr(ds, kw)


def make_monochrome1_rescaled(ds):
    # MONOCHROME1 whose rescale still yields the original HU: HU = -stored' + (4095 + intercept).
    s = 4095 - pixels(ds).astype("int32")
    ds.PhotometricInterpretation = "MONOCHROME1"
    ds.PixelData = s.astype("<u2").tobytes()
    ds.RescaleSlope = -1
    ds.RescaleIntercept = 4095 + int(ds.RescaleIntercept)


def make_enhanced(srcs, dst):
    """One Enhanced CT Image Storage file holding every slice as a frame, frames in a shuffled
    order, geometry and rescale in the shared and per-frame functional groups only."""
    import pydicom
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.sequence import Sequence
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    first = pydicom.dcmread(srcs[0], stop_before_pixels=True)
    order = list(range(len(srcs)))
    random.Random(22).shuffle(order)

    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.2.1"
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID
    ds.Modality = "CT"
    ds.StudyInstanceUID = first.StudyInstanceUID
    ds.SeriesInstanceUID = generate_uid()
    ds.SeriesNumber = 1
    ds.InstanceNumber = 1
    ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL", "NONE"]
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows = first.Rows
    ds.Columns = first.Columns
    ds.BitsAllocated = 16
    ds.BitsStored = 12
    ds.HighBit = 11
    ds.PixelRepresentation = 0
    ds.NumberOfFrames = len(srcs)

    measures = Dataset()
    measures.PixelSpacing = first.PixelSpacing
    measures.SliceThickness = first.SliceThickness
    orientation = Dataset()
    orientation.ImageOrientationPatient = first.ImageOrientationPatient
    shared = Dataset()
    shared.PixelMeasuresSequence = Sequence([measures])
    shared.PlaneOrientationSequence = Sequence([orientation])
    ds.SharedFunctionalGroupsSequence = Sequence([shared])

    per_frame = []
    frames = []
    for k, i in enumerate(order):
        src = pydicom.dcmread(srcs[i])
        offset = ENHANCED_OFFSETS[k % len(ENHANCED_OFFSETS)]
        frames.append((pixels(src).astype("int32") + offset).astype("<u2").tobytes())
        content = Dataset()
        content.InStackPositionNumber = i + 1
        position = Dataset()
        position.ImagePositionPatient = src.ImagePositionPatient
        transform = Dataset()
        transform.RescaleIntercept = int(src.RescaleIntercept) - offset
        transform.RescaleSlope = 1
        transform.RescaleType = "HU"
        item = Dataset()
        item.FrameContentSequence = Sequence([content])
        item.PlanePositionSequence = Sequence([position])
        item.PixelValueTransformationSequence = Sequence([transform])
        per_frame.append(item)
    ds.PerFrameFunctionalGroupsSequence = Sequence(per_frame)
    ds.PixelData = b"".join(frames)
    assert len(ds.PixelData) == len(srcs) * ds.Rows * ds.Columns * 2
    ds.save_as(dst, enforce_file_format=True)


# Each variant: (folder, source variant, how). "per-file" converters run once per slice file;
# "whole" ones get the source folder's file list and the output folder.
def per_file(fn):
    return ("per-file", fn)


def whole(fn):
    return ("whole", fn)


def dcmtk(tool, *opts):
    return per_file(lambda src, dst: run(tool, *opts, src, dst))


def gdcm(*opts):
    return per_file(lambda src, dst: run("gdcmconv", *opts, src, dst))


def pydicom_edit(edit):
    return per_file(lambda src, dst: rewrite(src, dst, edit))


VARIANTS = {
    # Sources, uncompressed.
    "explicit": ("native", dcmtk("dcmconv", "+te")),
    "signed": ("native", pydicom_edit(make_signed)),
    "native-8bit": ("native", pydicom_edit(make_8bit)),
    "bright": ("native", pydicom_edit(make_bright)),
    "monochrome1": ("native", pydicom_edit(make_monochrome1)),
    "monochrome1-rescaled": ("native", pydicom_edit(make_monochrome1_rescaled)),
    "enhanced": ("native", whole(lambda srcs, out: make_enhanced(srcs, out / "enhanced.dcm"))),
    # Lossless codecs.
    "rle": ("native", dcmtk("dcmcrle")),
    "jpeg-lossless-sv1": ("native", dcmtk("dcmcjpeg", "+e1")),
    "jpeg-lossless-p14": ("native", dcmtk("dcmcjpeg", "+el")),
    "jpegls-lossless": ("native", dcmtk("dcmcjpls", "+el")),
    "gdcm-jpegls-lossless": ("explicit", gdcm("--jpegls")),
    "j2k-lossless": ("explicit", gdcm("--j2k")),
    # GDCM 3.0 turns an Implicit VR file's standard elements into UN when it writes J2K.
    "j2k-lossless-un": ("native", gdcm("--j2k")),
    # Lossy codecs.
    "jpeg-baseline": ("native", dcmtk("dcmcjpeg", "+eb")),
    "jpeg-extended-8bit": ("native-8bit", dcmtk("dcmcjpeg", "+ee")),
    # 12-bit lossy JPEG (process 4, SOF1 with 12-bit precision): dcmcjpeg codes the 12 bits
    # stored at 12 bits (+bt says so explicitly; +ba would choose the same) at its default IJG
    # quality 90. For CT it writes the values shifted into 0..4095 with a new RescaleIntercept
    # (-2023 here, slope 1), so HU stay HU.
    "jpeg-extended-12bit": ("native", dcmtk("dcmcjpeg", "+ee", "+bt")),
    # The same streams cut into FRAGMENT_KB fragments (one frame over several fragments), and an
    # enhanced multi-frame file so cut (frames found through the basic offset table).
    "jpeg-extended-12bit-fragmented": (
        "native",
        dcmtk("dcmcjpeg", "+ee", "+bt", "+fs", FRAGMENT_KB),
    ),
    "enhanced-jpeg-extended-12bit": (
        "enhanced",
        dcmtk("dcmcjpeg", "+ee", "+bt", "+fs", FRAGMENT_KB),
    ),
    "jpegls-near": ("native", dcmtk("dcmcjpls", "+en", "+md", JPEGLS_NEAR)),
    "j2k-lossy": ("explicit", gdcm("--j2k", "--lossy", "-r", J2K_LOSSY_RATE)),
    # GDCM codes 12-bit data as 16-bit JPEG 2000: lossy values can exceed 4095.
    "bright-j2k-lossy": ("bright", gdcm("--j2k", "--lossy", "-r", J2K_LOSSY_RATE)),
    # The lossy files decoded back to native by the encoders' own decoders (the reference).
    "jpeg-baseline-dcmtk-decoded": ("jpeg-baseline", dcmtk("dcmdjpeg")),
    "jpeg-extended-8bit-dcmtk-decoded": ("jpeg-extended-8bit", dcmtk("dcmdjpeg")),
    "jpeg-extended-12bit-dcmtk-decoded": ("jpeg-extended-12bit", dcmtk("dcmdjpeg")),
    "jpegls-near-dcmtk-decoded": ("jpegls-near", dcmtk("dcmdjpls")),
    "j2k-lossy-gdcm-decoded": ("j2k-lossy", gdcm("--raw")),
    "bright-j2k-lossy-gdcm-decoded": ("bright-j2k-lossy", gdcm("--raw")),
    # Signed, MONOCHROME1 and multi-frame data through the codecs.
    "signed-rle": ("signed", dcmtk("dcmcrle")),
    "signed-jpeg-lossless-sv1": ("signed", dcmtk("dcmcjpeg", "+e1")),
    "signed-jpegls-lossless": ("signed", dcmtk("dcmcjpls", "+el")),
    "signed-j2k-lossless": ("signed", gdcm("--j2k")),
    "monochrome1-jpegls-lossless": ("monochrome1", dcmtk("dcmcjpls", "+el")),
    "enhanced-rle": ("enhanced", dcmtk("dcmcrle")),
    "enhanced-jpeg-lossless-sv1": ("enhanced", dcmtk("dcmcjpeg", "+e1")),
    "enhanced-jpegls-lossless": ("enhanced", dcmtk("dcmcjpls", "+el")),
    "enhanced-j2k-lossless": ("enhanced", gdcm("--j2k")),
}


def build(variant, root, done, pool):
    """Builds `variant` (and its sources first) under root; returns its folder."""
    if variant in done:
        return done[variant]
    source, (kind, fn) = VARIANTS[variant]
    src_dir = build(source, root, done, pool)
    out = root / variant
    out.mkdir()
    srcs = sorted(src_dir.glob("*.dcm"))
    if kind == "whole":
        fn(srcs, out)
    else:
        list(pool.map(lambda s: fn(s, out / s.name), srcs))
    done[variant] = out
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", type=Path, help="the ct-chest-lidc folder")
    ap.add_argument("--out", type=Path, help="the folder to create")
    ap.add_argument("--z-range", default=None, help="FIRST:END of the sorted slices (default: all)")
    ap.add_argument("--variants", default=None, help="comma-separated (default: all)")
    ap.add_argument("--list", action="store_true", help="print the variant names and exit")
    args = ap.parse_args()
    if args.list:
        print("\n".join(["native", *VARIANTS]))
        return
    if args.source is None or args.out is None:
        ap.error("--source and --out are required")
    check_tools()
    wanted = list(VARIANTS) if args.variants is None else args.variants.split(",")
    unknown = [v for v in wanted if v not in VARIANTS and v != "native"]
    if unknown:
        fail(f"unknown variants {unknown}; known: native, {', '.join(VARIANTS)}")
    if args.out.exists():
        fail(f"{args.out} exists already")
    slices = sorted_slices(args.source)
    if args.z_range:
        first, end = (int(v) for v in args.z_range.split(":"))
        slices = slices[first:end]
    if not slices:
        fail(f"no slices selected from {args.source}")

    partial = args.out.with_name(f"{args.out.name}.partial-{os.getpid()}")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    native = partial / "native"
    native.mkdir()
    for s in slices:
        shutil.copyfile(s, native / s.name)
    done = {"native": native}
    with concurrent.futures.ThreadPoolExecutor(max_workers=os.cpu_count() or 2) as pool:
        for v in wanted:
            build(v, partial, done, pool)
    try:
        os.rename(partial, args.out)
    except OSError:
        if not args.out.is_dir():
            raise
        shutil.rmtree(partial)  # another run finished first


if __name__ == "__main__":
    main()
