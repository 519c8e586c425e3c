"""Learned depth and ego-motion from events, trained with the contrast loss of :mod:`cmax`."""
