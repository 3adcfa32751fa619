"""Runnable demos behind ``python -m gpmhe demo NAME``; each module exposes ``main(argv) -> int``."""
