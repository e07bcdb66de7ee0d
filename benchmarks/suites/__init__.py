"""The suites of ``python -m benchmarks``: one module each, or one package (a module per mode or step, ``fit`` and
``real``), exposing ``DESCRIPTION`` (one line), ``add_arguments(parser)`` and ``run(args) -> dict`` (the figures,
JSON-serialisable; the suite prints its own table).

A suite imports heavy libraries (torch, open3d, sklearn) inside its functions, so that ``--help`` stays fast, and
imports only the library, the core modules of :mod:`benchmarks` and its own modules, never another suite.
"""
