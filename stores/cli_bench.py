"""``python -m stores bench``: the store crop-read benchmark (:mod:`stores.bench`), figures printed."""
from __future__ import annotations

import argparse

from stores.codecs import DEFAULT_ENCODING, ENCODINGS


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--store", default=None, help="benchmark this store instead of synthetic frames")
    ap.add_argument("--crops", type=int, default=40)
    ap.add_argument("--size", type=int, default=256, help="synthetic frame size")
    ap.add_argument("--reencode", nargs="+", default=None, metavar="STORE",
                    help="re-encode a few frames of these real stores in compact3, compact and lz4 and compare")
    ap.add_argument("--frames", type=int, default=4, help="frames per store for --reencode")
    ap.add_argument("--encoding", default=None, choices=list(ENCODINGS),
                    help=f"encoding of the synthetic store (default: that of new stores, {DEFAULT_ENCODING})")
    ap.add_argument("--quick", action="store_true", help="crop reads and sizes only (no codec table, no checksum timing)")


def run(args) -> int:
    from stores.bench import reencode, run as bench
    if args.reencode:
        reencode(args.reencode, frames=args.frames, crops=args.crops)
        return 0
    bench(args.store, crops=args.crops, size=args.size, encoding=args.encoding, compare=not args.quick,
          checksums=not args.quick)
    return 0
