"""Calibration: the twelve-position solution of the paper (``twelve_position``), the turntable
(``turntable``), a live capture session that identifies the poses and solves (``capture``), the
general fit of a probe model with its effects to stations (``fit``, ``labmodel``; ``wander`` for
the stochastic effects' paths, ``blas`` for one BLAS thread around the small fits), and the
simulator of stand and survey runs (``simulate``).

May import: ``core``, ``detect``, ``io``.
"""
