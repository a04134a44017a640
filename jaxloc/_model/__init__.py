"""A cycle's measurement model, its information (covariance and Cramér–Rao bound) and the
gates every estimate passes (goodness of fit, observability). Imports `_core`, `_cameras`,
`_cycle`.
"""
