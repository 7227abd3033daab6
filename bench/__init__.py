"""Benchmarks: each measures bodynet side by side with a baseline in the same run."""
