"""Verification problems (seed sections 3-5) and the seed's liquid-container examples.

The surgery problem is in :mod:`eyefem.eye`; :mod:`eyefem.catalog` lists them all by name.
"""
