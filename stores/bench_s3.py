"""S3 against local disk: frame writes per second and crops per second (``python -m stores.bench_s3``).

The same synthetic frames (``tests/test_stores_synthetic.py``'s generator, 64x64 x 8 spp by default) are
written to a local store and to a store at an ``s3://`` URL, then the same random crops (radiance and
features, every sample) are read back from each. The S3 endpoint is ``AWS_ENDPOINT_URL`` when set (a
real server, MinIO, ...); otherwise a moto server is started on 127.0.0.1 for the measurement, which
measures the protocol and the code path, not a network: a real bucket adds its latency to every request
(a crop of a frame reads its shard's index and inner chunks: a few requests).
"""
from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time
from pathlib import Path


def _moto():
    """Start a moto S3 server and point the AWS environment at it; returns the server (stop it)."""
    import logging
    import socket

    from moto.server import ThreadedMotoServer
    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    srv = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    srv.start()
    os.environ.update(AWS_ENDPOINT_URL=f"http://127.0.0.1:{port}", AWS_ACCESS_KEY_ID="bench",
                      AWS_SECRET_ACCESS_KEY="bench", AWS_DEFAULT_REGION="us-east-1")
    return srv


def run(frames: int = 8, size: int = 64, spp: int = 8, crops: int = 64, crop: int = 32,
        bucket: str = "denoise-bench") -> dict:
    import numpy as np

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    from test_stores_synthetic import synthetic_frame

    from stores.reader import open_store
    from stores.schema import StoreLayout
    from stores.writer import open_or_create
    srv = None if os.environ.get("AWS_ENDPOINT_URL") else _moto()
    tmp = tempfile.mkdtemp(prefix="bench-s3-")
    try:
        import boto3
        try:
            boto3.client("s3").create_bucket(Bucket=bucket)
        except Exception:  # noqa: BLE001 - it exists
            pass
        url = f"s3://{bucket}/bench-{os.getpid()}-{int(time.time())}.zarr"
        data = [synthetic_frame(i, size, size, spp) for i in range(frames)]
        layout = StoreLayout(num_frames=frames, height=size, width=size, spp=spp)
        out = {"frames": frames, "size": size, "spp": spp, "endpoint": "moto (this machine)" if srv else "AWS_ENDPOINT_URL"}
        for name, target in (("disk", os.path.join(tmp, "s.zarr")), ("s3", url)):
            w = open_or_create(target, layout)
            t0 = time.perf_counter()
            recs = {i: w.write_frame_data(i, fr) for i, fr in enumerate(data)}
            w.commit(recs)
            out[f"{name}_frames_per_s"] = frames / (time.perf_counter() - t0)
            st = open_store(target)
            rng = np.random.default_rng(0)
            t0 = time.perf_counter()
            for _ in range(crops):
                i = int(rng.integers(frames))
                y, x = (int(v) for v in rng.integers(0, size - crop + 1, 2))
                st.read_array("inputs/radiance", i, (y, x, crop, crop))
                st.read_array("inputs/features", i, (y, x, crop, crop))
            out[f"{name}_crops_per_s"] = crops / (time.perf_counter() - t0)
        out["s3_over_disk_writes"] = out["s3_frames_per_s"] / out["disk_frames_per_s"]
        out["s3_over_disk_crops"] = out["s3_crops_per_s"] / out["disk_crops_per_s"]
        return out
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if srv is not None:
            srv.stop()


if __name__ == "__main__":  # pragma: no cover
    r = run()
    print(f"{r['frames']} frames of {r['size']}x{r['size']} x {r['spp']} spp, S3 at {r['endpoint']}:")
    print(f"  writes: disk {r['disk_frames_per_s']:.1f} frames/s, S3 {r['s3_frames_per_s']:.1f} frames/s "
          f"({r['s3_over_disk_writes']:.2f}x)")
    print(f"  crops (radiance + features, every sample): disk {r['disk_crops_per_s']:.0f}/s, "
          f"S3 {r['s3_crops_per_s']:.0f}/s ({r['s3_over_disk_crops']:.2f}x)")
