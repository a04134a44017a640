"""The `jaxloc` command line. May import every other subpackage; nothing imports it.
"""
