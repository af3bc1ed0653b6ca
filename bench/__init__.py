"""Benchmarks that print figures (run through ``mfvs bench NAME`` or ``python -m bench.NAME``)."""
