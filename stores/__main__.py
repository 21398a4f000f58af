"""``python -m stores validate|export|bench ...`` (the same functions back ``python -m pipeline validate|export``)."""
from __future__ import annotations

import sys

USAGE = "usage: python -m stores {validate,export,bench} [args]  (each with --help)"


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    if cmd == "validate":
        from stores.validate import main as run
    elif cmd == "export":
        from stores.export import main as run
    elif cmd == "bench":
        from stores.bench import main as run
    else:
        print(f"unknown command {cmd!r}\n{USAGE}", file=sys.stderr)
        return 2
    return run(rest)


if __name__ == "__main__":
    sys.exit(main())
