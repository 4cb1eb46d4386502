"""Benchmarks: each module writes JSON (and a PNG where a person would look)."""
