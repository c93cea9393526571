"""Quasi-Monte Carlo filters: the Yau–Niu method (solver/qmc/yau_niu.py) for models of any dimension."""
