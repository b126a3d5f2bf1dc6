"""Simulation: rendered camera views of a floor with objects on it."""
