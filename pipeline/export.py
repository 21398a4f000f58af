"""``python -m pipeline export``: the store's own formats (:mod:`stores.export`: ``exr``, ``oidn``,
``layerdenoise``) and ``noisebase`` (:mod:`pipeline.noisebase`), which re-traces the stored samples with
the renderer for their exact world-space positions and so lives here, above the store package."""
from __future__ import annotations

import sys

from stores import export as _export
from stores.validate import cli_main

from pipeline.noisebase import export_noisebase

_export.WRITERS.setdefault("noisebase", export_noisebase)
FORMATS = tuple(_export.WRITERS)
export = _export.export
add_arguments = _export.add_arguments
run = _export.run


def main(argv=None) -> int:
    """As :func:`stores.export.main`, with the ``noisebase`` format."""
    return cli_main("export", "Export store frames to OpenEXR, the OIDN training layout, layerdenoise HDF5 or "
                    "Noisebase sequences.", add_arguments, run, argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
