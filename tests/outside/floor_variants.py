"""Writes a scan's frames as the camera-file variants that hide a camera's noise floor
(tests/outside.rs, the noise floor refusals), with tools other than subsurf.

Usage: python floor_variants.py JOB.json

JOB.json: {"width": W, "height": H, "black": B, "white": W16, "dn_per_unit": K,
           "pedestal": P, "frames": [{"raw": "in/000.f32", "out": "dir/000"}, ...]}

Each raw file holds H x W x 3 little-endian float32 (linear radiance). A 16-bit camera maps
radiance v to DN = B + K * v, rounded, clipped at W16. Per frame it writes:
- OUT.clean.tif: that camera's RGB TIFF (tifffile), black level B;
- OUT.pedestal.tif: the same with P DN of ambient light or an offset on every pixel;
- OUT.demosaiced.tif: the frame as an RGGB Bayer mosaic of the same size (each photosite its
  colour's DN), written as a raw DNG by PiDNG and developed by rawpy (LibRaw: AHD demosaicing,
  linear, no white balance or brightening, black level subtracted, 16 bits): what a camera's
  TIFF export or `rawpy.postprocess` gives;
- OUT.jpg: the frame as an 8-bit JPEG (imagecodecs), as a camera's JPEG output.
"""
import json
import sys

import imagecodecs
import numpy as np
import rawpy
import tifffile
from pidng.core import RAW2DNG, DNGTags, Tag
from pidng.defs import CFAPattern, PhotometricInterpretation

job = json.load(open(sys.argv[1]))
w, h = job["width"], job["height"]
black, white, k, pedestal = job["black"], job["white"], job["dn_per_unit"], job["pedestal"]


def dng(mosaic, path):
    t = DNGTags()
    t.set(Tag.ImageWidth, w)
    t.set(Tag.ImageLength, h)
    t.set(Tag.TileWidth, w)
    t.set(Tag.TileLength, h)
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
    r = RAW2DNG()
    r.options(t, path="", compress=False)
    r.convert(mosaic, filename=path[: -len(".dng")])


for f in job["frames"]:
    v = np.fromfile(f["raw"], dtype="<f4").reshape(h, w, 3).astype(np.float64)
    out = f["out"]
    dn = np.clip(np.rint(black + k * v), 0, white).astype(np.uint16)
    tifffile.imwrite(out + ".clean.tif", dn, photometric="rgb")
    lifted = np.clip(np.rint(black + pedestal + k * v), 0, white).astype(np.uint16)
    tifffile.imwrite(out + ".pedestal.tif", lifted, photometric="rgb")
    mosaic = np.empty((h, w), dtype=np.uint16)
    mosaic[0::2, 0::2] = dn[0::2, 0::2, 0]
    mosaic[0::2, 1::2] = dn[0::2, 1::2, 1]
    mosaic[1::2, 0::2] = dn[1::2, 0::2, 1]
    mosaic[1::2, 1::2] = dn[1::2, 1::2, 2]
    dng(mosaic, out + ".dng")
    with rawpy.imread(out + ".dng") as raw:
        rgb = raw.postprocess(
            demosaic_algorithm=rawpy.DemosaicAlgorithm.AHD,
            gamma=(1, 1),
            no_auto_bright=True,
            output_bps=16,
            use_camera_wb=False,
            use_auto_wb=False,
            user_wb=[1.0, 1.0, 1.0, 1.0],
            output_color=rawpy.ColorSpace.raw,
            user_flip=0,
        )
    tifffile.imwrite(out + ".demosaiced.tif", rgb, photometric="rgb")
    eight = np.clip(np.rint(255.0 * (dn.astype(np.float64) - black) / (white - black)), 0, 255)
    with open(out + ".jpg", "wb") as j:
        j.write(imagecodecs.jpeg8_encode(eight.astype(np.uint8), level=90))
print(json.dumps({"frames": len(job["frames"])}))
