"""``module load magcomp`` in MAVProxy: MAVProxy imports ``mavproxy_<name>`` when it is not one of its own
modules. Everything lives in :mod:`magcomp.mavproxy`."""

from magcomp.mavproxy import MagcompModule, init

__all__ = ["MagcompModule", "init"]
