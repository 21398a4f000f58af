"""``python -m pipeline export``: every export format, as ``python -m stores export`` offers them
(:func:`stores.export.writers`): the store's own (``exr``, ``oidn``, ``layerdenoise``) and the installed
plug-ins (``noisebase``, :mod:`pipeline.noisebase`, which re-traces the stored samples with the renderer
for their exact world-space positions and so lives here, above the store package; registered as an
entry point in pyproject.toml)."""
from __future__ import annotations

from stores import export as _export

FORMATS = tuple(_export.writers())
export = _export.export
add_arguments = _export.add_arguments
run = _export.run
