"""Sensory processing: log sources, egosphere images, pyramids and the five SP functions per level.

Kept free of heavy imports so that ``logs`` can be used on its own (the simulator writes
logs through it).
"""
