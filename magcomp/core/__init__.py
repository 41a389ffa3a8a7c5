"""Pure numerical core: numpy/scipy only, no I/O, no clocks, explicit ``dt``.

Conventions used everywhere in :mod:`magcomp.core`:

* frames: body is FRD (x forward, y right, z down); earth is local NED;
* quaternions are scalar-first ``(w, x, y, z)`` and ``q_nb`` rotates body vectors into NED,
  ``v_n = R(q_nb) @ v_b``; the paper's ``R = R_b^e`` (eq. 13) is ``R(q_nb)`` and its earth-to-body
  matrix ``R_e^b`` is the transpose;
* units: magnetic field in milligauss (mgauss), angular rate rad/s, specific force m/s^2,
  throttle 0..1, current A, voltage V, temperature degC, time s.
"""
