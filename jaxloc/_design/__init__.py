"""Formation design: formation parameters, constraints, objectives and search.
Imports everything below it, never `_cli`.
"""
