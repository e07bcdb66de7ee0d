"""The suites of ``python -m benchmarks``: one module each, exposing ``DESCRIPTION`` (one line),
``add_arguments(parser)`` and ``run(args) -> dict`` (the figures, JSON-serialisable; the suite prints its own table).

A suite imports heavy libraries (torch, open3d, sklearn) inside its functions, so that ``--help`` stays fast, and
imports only the library and the core modules of :mod:`benchmarks`, never another suite.
"""
