"""Scripted procedures (what to do) and, later, the engine that runs them."""
