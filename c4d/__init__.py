"""c4d: the roof over the three packages (command line, inspection reports, demo); nothing imports it.

Shared config, errors, files, geometry and drawing live in the floor package `c4d_core`.
"""

__version__ = "0.1.0"
