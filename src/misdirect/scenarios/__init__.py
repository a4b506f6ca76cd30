"""Problem generators: the paper's grid world and knapsack reduction, sensor networks on the
paper's grid, a drone among patrolling agents, and seeded random models."""

from misdirect.scenarios.drone import drone
from misdirect.scenarios.grid import paper_grid
from misdirect.scenarios.knapsack import knapsack
from misdirect.scenarios.random import random_problem
from misdirect.scenarios.sensor_grid import sensor_grid

__all__ = ["drone", "knapsack", "paper_grid", "random_problem", "sensor_grid"]
