"""Benchmark scripts: each prints ratios measured in one run.

Run one with ``python -m couch.tools.bench.NAME``."""
