"""Benchmarks of evtslowtv; run ``python -m benchmarks.speed --help``."""
