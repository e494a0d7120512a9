"""Algorithm 1: the hierarchical federated loop (CRCHFL, HFL and SFL as
configurations of it) on SUMO's clock, and a run from its config to a
results folder with resume.

May import: core, sumo, links, vision, data, learning, accounting, planning.
"""
