"""``python -m i4cal`` runs the ``i4cal`` command line; the code lives in ``calib``, ``drivers`` and ``service``."""
