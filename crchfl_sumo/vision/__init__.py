"""Pictures from SUMO state: the four vehicle cameras, the static raster world
(ground texture of roads and markings), per-frame rendering of vehicles and
signals, and mosaics and videos.

May import: core, sumo.
"""
