"""Estimators: registered plug-ins that take a :class:`tofloc.problem.Problem` and return an Estimate."""
