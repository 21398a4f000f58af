"""Tiny test-only models, one of each input kind, registered by the tests that import this module (never
shipped). Each is the least a model of its kind must be: it reads only what its kind's items hold and
declares nothing else, so the whole CLI (train, evaluate, report, bench, denoise, hard-cases, torchrun)
working on it shows that the training stack takes everything else from the kind.

Also a torchrun script: ``torchrun ... tests/kind_models.py ARGS`` registers the probes and runs
``python -m training ARGS``; ``--each FILE`` runs every argument list of a JSON list in turn."""
from __future__ import annotations

import sys

import torch
import torch.nn as nn

from training.inputs import InputSpec
from training.models.common import Denoiser, conv_fmas
from training.models.registry import MODELS, register

PROBES = {"samples": "probe-samples", "pixels": "probe-pixels", "clips": "probe-clips",
          "sampled-layers": "probe-layers"}


class _Probe(Denoiser):
    """A 1x1 convolution of the noisy per-pixel radiance (and, where the kind has them, the guides)."""

    tiny: dict = {}
    train_defaults = dict(warmup=0)

    def __init__(self, width: int = 4):
        super().__init__(width=width)
        self.net = nn.Sequential(nn.Conv2d(self.cin, width, 1), nn.ReLU(), nn.Conv2d(width, 3, 1))

    def fmas_per_pixel(self, spp: int) -> float:
        return float(conv_fmas(self.net))

    def run(self, radiance: torch.Tensor, guide: torch.Tensor | None = None) -> torch.Tensor:
        x = torch.nan_to_num(radiance, nan=0.0, posinf=0.0).clamp(min=0.0)
        if guide is not None:
            x = torch.cat((x, guide), dim=1)
        return x[:, :3] + self.net(torch.log1p(x))


class ProbeSamples(_Probe):
    """Kind ``samples``: ``denoise(radiance (B S 3 H W), features)``."""

    inputs = InputSpec("samples", frames=1, default_spp=2)
    cin = 3

    def denoise(self, radiance, features):
        return self.run(radiance.mean(dim=1))


class ProbePixels(_Probe):
    """Kind ``pixels``: per-pixel radiance with the albedo guide; its own ``forward``."""

    inputs = InputSpec("pixels", frames=1, default_spp=1)
    cin = 6

    def forward(self, batch):
        return self.run(batch["radiance"], batch["albedo"])


class ProbeClips(_Probe):
    """Kind ``clips``: a recurrent ``step`` over per-sample frames, blending its previous output in; the
    kind unrolls it over the window (training) or over each clip (evaluation)."""

    inputs = InputSpec("clips", frames=2, default_spp=2)
    cin = 3

    def __init__(self, width: int = 4):
        super().__init__(width)
        self.mix = nn.Parameter(torch.zeros(1))

    def step(self, frame, state):
        out = self.run(frame["radiance"].mean(dim=1))
        if state is not None:
            a = torch.sigmoid(self.mix)
            out = (1 - a) * out + a * state["previous"]
        return out, {"previous": out}, {}


class ProbeLayers(_Probe):
    """Kind ``sampled-layers``: ``spp`` samples in every pixel composed from the layers (no sampler)."""

    inputs = InputSpec("sampled-layers", frames=1, default_spp=3)
    cin = 3

    def forward(self, batch):
        from training import adaptive
        layers = adaptive.clean_layers(batch["layers"])
        counts = adaptive.uniform_counts(layers[:, 0], batch["spp"])
        return self.run(adaptive.compose(layers, counts))


CLASSES = {"probe-samples": ProbeSamples, "probe-pixels": ProbePixels, "probe-clips": ProbeClips,
           "probe-layers": ProbeLayers}


def register_probes() -> None:
    for name, cls in CLASSES.items():
        if MODELS.get(name) is not cls:
            register(name)(cls)


def unregister_probes() -> None:
    for name in CLASSES:
        MODELS.pop(name, None)


if __name__ == "__main__":          # torchrun's script: the probes, then the CLI
    import json
    register_probes()
    from training import distributed
    from training.__main__ import main
    if sys.argv[1:2] == ["--each"]:
        with open(sys.argv[2]) as f:
            distributed.end_process(max(main(argv) for argv in json.load(f)))
    distributed.end_process(main(sys.argv[1:]))
