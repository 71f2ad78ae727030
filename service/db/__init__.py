"""Persistence (SQLAlchemy 2 ORM): runs, events, results, datasets, calibrations, tokens."""

from .models import Base, Calibration, DatasetRecord, Event, Run, Token
from .session import Database

__all__ = ["Base", "Calibration", "Database", "DatasetRecord", "Event", "Run", "Token"]
