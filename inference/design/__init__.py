"""Experiment design: which trials to run next.

:mod:`inference.design.active` chooses discrete actions and initial states to try
(active exploration of a table network); :mod:`inference.design.active_gaussian` chooses
parameter values for the clusters' linear-Gaussian regressions.
"""
