"""Monte Carlo studies: one trial, the chunked and sharded engine, statistics, and the
chunks as tasks of a Ray cluster (`cluster`, the only module that imports Ray, lazily).
Imports everything below it (`_sim`, `_solvers`, `_refine`, ...), never `_cli`.
"""
