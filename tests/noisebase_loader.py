"""Run under Noisebase's own environment (zarr 2; tests/test_noisebase.py builds it): read an exported
folder with Noisebase's ``TrainingSampleLoader_v1`` and save what it gives, frame by frame, to an .npz.

    python tests/noisebase_loader.py DIR OUT.npz
"""
import sys

import numpy as np
import yaml
import zarr
from noisebase.loaders.torch.training_sample_v1 import TrainingSampleLoader_v1

BUFFERS = ["normal", "motion", "depth", "w_normal", "w_motion", "w_position", "diffuse", "color", "reference"]


def main(folder: str, out: str) -> int:
    assert zarr.__version__.startswith("2."), zarr.__version__
    with open(f"{folder}/noisebase.yaml") as f:
        src = yaml.safe_load(f)["src"]
    saved = {}
    # Noisebase splits sequences into val (at least one batch) and train: read both stages
    for stage in ("val", "train"):
        loader = TrainingSampleLoader_v1(src=src, stage=stage, seed=0, val_split=0.0, shuffle=False, batch_size=1,
                                         drop_last=False, num_workers=0, flip_rotate=False, buffers=BUFFERS,
                                         samples=src["samples"], data_path=folder)
        for batch in loader:
            name = batch["file"][0].rsplit("/", 1)[-1].removesuffix(".zip")
            f = int(batch["frame_index"])
            for k in BUFFERS + ["view_proj_mat"]:
                saved[f"{name}/{f}/{k}"] = batch[k][0].numpy()
    np.savez(out, **saved)
    print(f"read {len({k.rsplit('/', 1)[0] for k in saved})} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
