#!/usr/bin/env python3
"""Write a copy of a tiled, deflate-compressed GeoTIFF (the bundled sitl/maps/*.tif) whose pixels
are seeded random noise: the same georeferencing and size, texture that is nowhere on the ground.
As visnav's map (`run.py --map-ortho`) it is ground that cannot be matched (a map of other
ground, far older than the season): every fix attempt finds features and no consistent
correspondence, while the camera still sees the real ground. That is the real SITL test of
visual odometry across a map gap, in the map's own CRS (same zone: no grid convergence or scale
confound from a map of another place). A uniform image (`--value`) is refused by visnav's map
build (no features: a map without texture is a configuration error).

    python3 sitl/featureless_map.py sitl/maps/naip_nd_2009.tif /tmp/noise.tif [--seed 1]

Standard library only (struct, zlib): only tiled, deflate (8) or Adobe-deflate (32946),
8-bit TIFFs are handled; anything else is refused with the reason.
"""
import argparse
import random
import struct
import sys
import zlib

TILE_OFFSETS, TILE_BYTE_COUNTS = 324, 325
DEFLATE = (8, 32946)


def ifd_tags(data):
    """The first IFD's tags: {tag: (type, count, value_or_offset)}, and the byte order."""
    if data[:2] not in (b"II", b"MM"):
        raise ValueError("not a TIFF (no II/MM byte order mark)")
    bo = "<" if data[:2] == b"II" else ">"
    if struct.unpack(bo + "H", data[2:4])[0] != 42:
        raise ValueError("not a classic TIFF (BigTIFF is not handled)")
    off = struct.unpack(bo + "I", data[4:8])[0]
    n = struct.unpack(bo + "H", data[off:off + 2])[0]
    tags = {}
    for i in range(n):
        tag, typ, cnt, val = struct.unpack(bo + "HHII", data[off + 2 + 12 * i:off + 14 + 12 * i])
        if typ == 3 and cnt == 1:  # SHORT stored in the first two bytes of the value field
            val = struct.unpack(bo + "H", data[off + 10 + 12 * i:off + 12 + 12 * i])[0]
        tags[tag] = (typ, cnt, val)
    return bo, tags


def long_array(data, bo, tag):
    typ, cnt, val = tag
    if typ != 4:
        raise ValueError("tile offsets / byte counts are not LONG")
    if cnt == 1:
        return [val], None
    return list(struct.unpack(bo + "I" * cnt, data[val:val + 4 * cnt])), val


def featureless(data, value=None, seed=1):
    """The file with every tile replaced: all `value`, or (None) seeded noise in 2x2-pixel blocks
    (features at the map's finest SURF scales)."""
    rng = random.Random(seed)
    bo, tags = ifd_tags(data)
    for need in (TILE_OFFSETS, TILE_BYTE_COUNTS, 322, 323, 259):
        if need not in tags:
            raise ValueError(f"tag {need} missing: only tiled TIFFs are handled")
    if tags[259][2] not in DEFLATE:
        raise ValueError(f"compression {tags[259][2]}: only deflate is handled")
    offs, offs_at = long_array(data, bo, tags[TILE_OFFSETS])
    lens, lens_at = long_array(data, bo, tags[TILE_BYTE_COUNTS])
    if offs_at is None or lens_at is None:
        raise ValueError("a single tile: not handled")
    out = bytearray(data)
    new_offs, new_lens = [], []
    for o, n in zip(offs, lens):
        raw_len = len(zlib.decompress(bytes(data[o:o + n])))
        tile = zlib.compress(fill(raw_len, value, rng, tags), 6)
        if len(out) % 2:
            out += b"\0"  # word alignment, as TIFF asks
        new_offs.append(len(out))
        new_lens.append(len(tile))
        out += tile
    struct.pack_into(bo + "I" * len(offs), out, offs_at, *new_offs)
    struct.pack_into(bo + "I" * len(lens), out, lens_at, *new_lens)
    return bytes(out)


def fill(n, value, rng, tags):
    if value is not None:
        return bytes([value]) * n
    spp = tags.get(277, (3, 1, 1))[2]
    tw = tags[322][2]
    row_px = tw // 2
    out = bytearray()
    while len(out) < n:
        # One row of 2-px blocks, every band the same grey, written twice (2x2 blocks).
        row = bytearray()
        for v in rng.randbytes(row_px):
            row += bytes([v]) * (2 * spp)
        out += row * 2
    return bytes(out[:n])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src")
    ap.add_argument("dst")
    ap.add_argument("--seed", type=int, default=1, help="of the noise")
    ap.add_argument("--value", type=int, default=None,
                    help="instead of noise, every pixel this value, 0-255 (visnav refuses it)")
    args = ap.parse_args(argv)
    if args.value is not None and not 0 <= args.value <= 255:
        sys.exit(f"--value {args.value}: expected 0-255")
    try:
        with open(args.src, "rb") as f:
            data = f.read()
        out = featureless(data, args.value, args.seed)
    except (OSError, ValueError, zlib.error, struct.error) as e:
        sys.exit(f"{args.src}: {e}")
    with open(args.dst, "wb") as f:
        f.write(out)
    what = "noise" if args.value is None else f"every pixel {args.value}"
    print(f"{args.dst}: {args.src} with {what}")


if __name__ == "__main__":
    main()
