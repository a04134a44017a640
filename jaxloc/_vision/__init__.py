"""The image front end: marker detection, rendering, calibration, localization from a
team's images. Imports everything below it, never `_cli`.
"""
