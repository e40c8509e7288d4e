"""Evaluation: metrics (e_x, e_gamma, NEES), the paper's trial protocol, tables and plots."""
