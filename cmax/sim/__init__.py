"""Simulation of event cameras: the ESIM event model, adaptive sampling and video sources."""
