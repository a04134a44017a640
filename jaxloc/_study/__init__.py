"""Monte Carlo studies: one trial, the chunked and sharded engine, statistics.
Imports everything below it (`_sim`, `_solvers`, `_refine`, ...), never `_cli`.
"""
