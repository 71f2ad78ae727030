"""The i4cal service (FastAPI) and the ``i4cal`` command line."""

__version__ = "0.1.0"
