"""``python -m i4cal``: the ``i4cal`` command line (:func:`i4cal.cli.run_program`: the service's commands and
``bench``)."""

from i4cal.cli import run_program

if __name__ == "__main__":
    run_program()
