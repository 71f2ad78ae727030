"""Shared numerics: transforms, robust losses, numerical differentiation, threads, JSON I/O."""
