"""Closed loop: vehicle dynamics, policies (a trained model, the scripted
reference driver), the drive loop in SUMO, its metrics and plots, named
routes and the drive command.

May import: core, sumo, links, vision, data, learning, accounting, planning,
federation.
"""
