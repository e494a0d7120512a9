"""Driving data: the label schema and the expert's geometric labels, HDF5
shards and their manifest, data set generation from a scenario, online
collection during a run, and data set statistics.

May import: core, sumo, links, vision.
"""
