"""Problem generators: the paper's grid world and knapsack reduction, and seeded random models."""

from misdirect.scenarios.grid import paper_grid
from misdirect.scenarios.knapsack import knapsack
from misdirect.scenarios.random import random_problem

__all__ = ["knapsack", "paper_grid", "random_problem"]
