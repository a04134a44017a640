"""Camera models and the paper's nominal cameras and mounts. Imports only `_core`.
"""
