"""Experiments built from the rest: reproduce (the paper's experiments), the
report, mobility sweeps, and simulate (association and link traces).

May import: every subpackage; only cli/ (the command line) sits above it.
"""
