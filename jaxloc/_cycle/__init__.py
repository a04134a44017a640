"""What one localization cycle is: its layout (steps, moves, placements), its
observations and poses. Imports `_core` and `_cameras`.
"""
