"""Persistence (SQLAlchemy 2 ORM): runs, events, results, datasets, calibrations, checks, tokens."""

from .models import Base, Calibration, Check, DatasetRecord, Event, Run, Token
from .session import Database

__all__ = ["Base", "Calibration", "Check", "Database", "DatasetRecord", "Event", "Run", "Token"]
