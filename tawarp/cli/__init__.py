"""The ``tawarp`` command line: argument parsing and printing only; the package never imports it."""

from .app import build_parser, main

__all__ = ["build_parser", "main"]
