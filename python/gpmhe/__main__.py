"""Command line: ``python -m gpmhe demo [NAME] [options]``; each demo lives in
``gpmhe.demos.<name>`` and exposes ``main(argv) -> int``; this file only dispatches."""

from __future__ import annotations

import importlib
import sys

DEMOS = {
    "batch-reactor": ("gpmhe.demos.batch_reactor",
                      "GP-MHE on the paper's batch reactor, gpmhe's defaults next to the "
                      "paper's setup"),
    "rgp": ("gpmhe.demos.rgp", "the RGP-dKF learning a hidden disturbance (second-order system)"),
}
DEFAULT_DEMO = "batch-reactor"
HELP = """usage: python -m gpmhe demo [NAME] [options]

Runs one of gpmhe's demos (default: {default}). Options per demo: python -m gpmhe demo NAME --help

demos:
{demos}
"""


def _help() -> str:
    demos = "\n".join(f"  {name:14s} {text}" for name, (_, text) in DEMOS.items())
    return HELP.format(default=DEFAULT_DEMO, demos=demos)


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help") or args[0] != "demo":
        print(_help(), end="", file=sys.stdout if args and args[0] in ("-h", "--help") else sys.stderr)
        return 0 if args and args[0] in ("-h", "--help") else 2
    rest = args[1:]
    name = DEFAULT_DEMO
    if rest and not rest[0].startswith("-"):
        name = rest.pop(0)
    if name not in DEMOS:
        print(f"unknown demo {name!r}; choose one of: {', '.join(DEMOS)}", file=sys.stderr)
        return 2
    return int(importlib.import_module(DEMOS[name][0]).main(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
