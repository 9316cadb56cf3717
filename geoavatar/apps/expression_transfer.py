"""Moved to geoavatar/animation/expression_transfer.py (the animation layer). Its names stay importable from here for
benchmarks/cross_reenactment.py, which imports TRANSFER_MODES from this module; new code imports the animation one."""

from geoavatar.animation.expression_transfer import *  # noqa: F401,F403
from geoavatar.animation.expression_transfer import __all__  # noqa: F401
