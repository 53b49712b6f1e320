"""Benchmarks that print figures (speed and memory targets are met here, never in tests)."""
