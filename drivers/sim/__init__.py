"""Simulated hardware: the geometric and image-level twins of the bench, the simulated controller.

Production code never imports this package except through configuration (``sim://`` URIs).
"""
