"""The model and its exact semantics, with no solver in sight.

``model`` (POMDP, controller, costs, problem) and ``objective`` (what the attacker maximises)
define an instance; ``product`` builds the Markov chain of one alteration and ``reachability``
solves it exactly; ``evaluate`` reports it. ``alterations`` and ``choice_product`` describe
the attacker's real choices and the MDP they span, and ``attack`` prepares both once for the
solvers. ``simulate`` runs the robot for an independent, statistical check; ``grid`` finds
the cell of each state in a grid world; ``memory`` refuses, before allocating, work that
cannot fit in memory; ``tolerance`` is the one policy for comparing costs, values and bounds.
"""
