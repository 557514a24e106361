"""Harnesses for the tests and benchmarks only: served drives, fault scenarios, synthetic logs."""
