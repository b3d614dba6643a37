"""Writes a scan's frames as camera files with tools other than subsurf (tests/outside.rs).

Usage: python camera_files.py JOB.json

JOB.json: {"width": W, "height": H, "black": B, "white": W16, "dn_per_unit": K,
           "frames": [{"raw": "in/000.f32", "tiff": "out/000.tif", "dng": "out/000.dng",
                       "brackets": [{"gain": 64, "tiff": "out/000_b.tif", "dng": ...}]}, ...]}

Each raw file holds H x W x 3 little-endian float32 (linear radiance, as the EXR frame). A camera
that maps radiance v to DN = B + K * v, rounded, clipped at W16 (16-bit), writes it:
- as an RGB 16-bit TIFF with tifffile;
- as a raw DNG with PiDNG: a 16-bit RGGB Bayer mosaic at twice the size (each pixel one 2x2 cell:
  its red, its green twice, its blue), BlackLevel B, WhiteLevel W16 in the file, uncompressed;
  checked by reading it back with rawpy (LibRaw).
"brackets" (optional): further exposures of the same frame, `gain` times longer (DN = B + gain *
K * v), written the same way (either file may be left out); the bright parts clip.
Prints one JSON line: how many values (pixel and colour) clipped in the frames' own files, and
per bracket position (0: the frames' own files).
"""
import json
import sys

import numpy as np
import rawpy
import tifffile
from pidng.core import RAW2DNG, DNGTags, Tag
from pidng.defs import CFAPattern, PhotometricInterpretation

job = json.load(open(sys.argv[1]))
w, h = job["width"], job["height"]
black, white, k = job["black"], job["white"], job["dn_per_unit"]


def write(v, gain, tiff_path, dng_path):
    """Writes radiance v exposed `gain` times longer; returns the clipped values (per pixel and
    colour, as in the TIFF)."""
    dn = np.clip(np.rint(black + gain * k * v), 0, white).astype(np.uint16)
    if tiff_path:
        tifffile.imwrite(tiff_path, dn, photometric="rgb")
    if not dng_path:
        return int((dn >= white).sum())
    mosaic = np.empty((2 * h, 2 * w), dtype=np.uint16)
    mosaic[0::2, 0::2] = dn[:, :, 0]
    mosaic[0::2, 1::2] = dn[:, :, 1]
    mosaic[1::2, 0::2] = dn[:, :, 1]
    mosaic[1::2, 1::2] = dn[:, :, 2]
    t = DNGTags()
    t.set(Tag.ImageWidth, 2 * w)
    t.set(Tag.ImageLength, 2 * h)
    t.set(Tag.TileWidth, 2 * w)
    t.set(Tag.TileLength, 2 * h)
    t.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    t.set(Tag.SamplesPerPixel, 1)
    t.set(Tag.BitsPerSample, 16)
    t.set(Tag.CFARepeatPatternDim, [2, 2])
    t.set(Tag.CFAPattern, CFAPattern.RGGB)
    t.set(Tag.BlackLevel, [int(black)])
    t.set(Tag.WhiteLevel, [int(white)])
    t.set(Tag.ColorMatrix1, [[1, 1], [0, 1], [0, 1], [0, 1], [1, 1], [0, 1], [0, 1], [0, 1], [1, 1]])
    t.set(Tag.AsShotNeutral, [[1, 1], [1, 1], [1, 1]])
    t.set(Tag.Make, "subsurf test")
    t.set(Tag.Model, "16-bit Bayer")
    # Uncompressed: PiDNG's lossless-JPEG encoder (its liblj92 extension) fails on Python >= 3.10.
    r = RAW2DNG()
    r.options(t, path="", compress=False)
    r.convert(mosaic, filename=dng_path[: -len(".dng")] if dng_path.endswith(".dng") else dng_path)
    # LibRaw reads the same photosites and levels back.
    with rawpy.imread(dng_path) as raw:
        assert np.array_equal(raw.raw_image_visible, mosaic), dng_path
        assert raw.white_level == white, (raw.white_level, white)
        assert list(raw.black_level_per_channel) == [black] * 4, raw.black_level_per_channel
        assert raw.raw_pattern.tolist() == [[0, 1], [3, 2]], raw.raw_pattern
    return int((dn >= white).sum())


by_bracket = []
for f in job["frames"]:
    v = np.fromfile(f["raw"], dtype="<f4").reshape(h, w, 3).astype(np.float64)
    files = [{"gain": 1, "tiff": f.get("tiff"), "dng": f.get("dng")}] + f.get("brackets", [])
    for i, b in enumerate(files):
        n = write(v, b["gain"], b.get("tiff"), b.get("dng"))
        by_bracket += [0] * (i + 1 - len(by_bracket))
        by_bracket[i] += n
print(json.dumps({"clipped_photosites": by_bracket[0], "clipped_by_bracket": by_bracket}))
