"""Bytes: what each scheme sends in each stage (the per-scheme transfer
schedules) and the ledger that charges every transfer against the budget.

May import: core, sumo, links, vision, data, learning.
"""
