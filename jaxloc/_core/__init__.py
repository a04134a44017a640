"""Shared numerics and plumbing with no robotics in them: small closed-form linear
algebra, safe elementwise functions, rotations, result codes, the least-squares kernel.
Imports nothing from jaxloc outside `_core`.
"""
