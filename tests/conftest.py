"""Shared fixtures: the Mitsuba variant, tiny scenes, temporary stores. Markers slow/gpu skip themselves."""
from __future__ import annotations

import os

import pytest


def pytest_collection_modifyitems(config, items):
    run_slow = os.environ.get("RUN_SLOW") == "1"
    try:
        import torch
        has_gpu = torch.cuda.is_available()
    except Exception:  # pragma: no cover
        has_gpu = False
    for item in items:
        if "slow" in item.keywords and not run_slow:
            item.add_marker(pytest.mark.skip(reason="slow: set RUN_SLOW=1"))
        if "gpu" in item.keywords and not has_gpu:
            item.add_marker(pytest.mark.skip(reason="needs a CUDA device"))


@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the project's variant (llvm_ad_rgb on CPU), 2 threads."""
    from pipeline.variant import mitsuba
    return mitsuba()
