"""SUMO itself: a scenario (network, routes, edge sites, towns), the only
module that imports libsumo (simulation.py), route geometry and maps read
with sumolib, the per-step Frame of vehicle states, and edge-site placement.

May import: core.
"""
