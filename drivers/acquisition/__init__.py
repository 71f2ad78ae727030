"""Executing a plan: the acquisition, the bench file, operators, metrics, suspenders, the stream worker."""
