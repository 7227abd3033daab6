"""The shared pure core of bodynet: key space, messages and wire-format codecs.

Nothing in this package performs I/O or reads a clock, and it imports no I/O
library (zenoh, can, serial, rerun, mcap): nodes, gateway and clients all build
on it, and ``tests/test_core_purity.py`` proves the rule holds.
"""
