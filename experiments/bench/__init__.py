"""Benchmarks: each times one part of the library against an alternative, side by side, and prints a table."""
