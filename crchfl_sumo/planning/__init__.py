"""Problem P: the CVXPY allocator that splits the byte budget (maths only, in
problem.py), the timing it takes from a run, the calibration of its
weights from pilot runs, and the plan command.

May import: core, sumo, links, vision, data, learning, accounting.
"""
