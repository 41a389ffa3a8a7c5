"""magcomp: online compensation of throttle-driven magnetometer bias on UAVs.

Implements and extends M. Silic and K. Mohseni, "Correcting Current-Induced Magnetometer Errors on
UAVs: An Online Model-Based Approach", IEEE Sensors Journal 20(2), 2020 (DOI 10.1109/JSEN.2019.2945201).
Equation numbers in the code refer to that article.

Importing the package does no work: the numerical core lives in :mod:`magcomp.core`, the MAVLink,
file and Rerun shell in :mod:`magcomp.adapters` and :mod:`magcomp.service`.
"""

__version__ = "0.1.0"
__all__ = ["__version__"]


def init(mpstate: object) -> object:
    """MAVProxy's entry point: ``module load magcomp`` imports the package named ``magcomp`` (after
    ``MAVProxy.modules.mavproxy_magcomp``) and calls its ``init``; the module is :mod:`magcomp.mavproxy`."""
    from magcomp.mavproxy import init as module_init

    return module_init(mpstate)
