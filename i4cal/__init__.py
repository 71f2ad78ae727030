"""The top of the stack: the ``i4cal`` command line's assembly (:mod:`i4cal.cli`, run by the ``i4cal`` script and
``python -m i4cal``) and the benchmarks (:mod:`i4cal.benchmarks`, ``i4cal bench``). The rest of the code lives in
``calib``, ``drivers`` and ``service``, none of which imports this package."""
