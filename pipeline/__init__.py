"""Photogrammetry-to-material pipeline: the library.

Domain packages (camera, geometry, imaging, render, fit, synthetic, capture), the
framework that runs stages (core), the command line (cli) and the formats of the
files stages exchange (formats). The library never imports ``stages``.
"""

import logging

logger = logging.getLogger("pipeline")
"""The one logger every stage and runner module writes to."""
# Pass everything to handlers: each stage's log file wants debug detail, and the
# console handler (or Python's last-resort handler) filters by its own level.
logger.setLevel(logging.DEBUG)

__version__ = "0.1.0"
