"""Command line: ``python -m gpmhe demo [NAME] [options]``.

Each demo lives in ``gpmhe.demos.<name>`` and exposes ``main(argv) -> int``; this file only
dispatches. ``python -m gpmhe demo`` runs the batch-reactor GP-MHE demo (the paper's §V);
``python -m gpmhe demo rgp`` runs the RGP-dKF second-order-system demo.
"""

from __future__ import annotations

import importlib
import sys

DEMOS = {
    "batch-reactor": "gpmhe.demos.batch_reactor",
    "rgp": "gpmhe.demos.rgp",
}
DEFAULT_DEMO = "batch-reactor"


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help") or args[0] != "demo":
        print(__doc__.strip())
        print("demos:", ", ".join(DEMOS), f"(default: {DEFAULT_DEMO})")
        return 0 if args and args[0] in ("-h", "--help") else 2
    rest = args[1:]
    name = DEFAULT_DEMO
    if rest and not rest[0].startswith("-"):
        name = rest.pop(0)
    if name not in DEMOS:
        print(f"unknown demo {name!r}; choose one of: {', '.join(DEMOS)}", file=sys.stderr)
        return 2
    return int(importlib.import_module(DEMOS[name]).main(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
