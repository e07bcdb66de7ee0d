"""The benchmark harness: ``python -m benchmarks SUITE [options]`` (benchmarks/README.md).

Core modules, which suites may import: :mod:`benchmarks.record` (the JSON record of a run), :mod:`benchmarks.cache`
(collections and models cached by their parameters), :mod:`benchmarks.metrics`, :mod:`benchmarks.baselines` and
:mod:`benchmarks.inspect_api` (the one door into the inspection package). Suites live in :mod:`benchmarks.suites`
and never import each other.
"""
