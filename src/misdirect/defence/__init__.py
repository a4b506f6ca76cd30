"""The defender's view: which sensors are weak, which to protect, and what an online attacker
could do (docs/defence.md).

* :func:`audit` — the attacker's optimum for every budget up to ``B``, per sensor its
  single-sensor value and its *criticality* (how much protecting it lowers the optimum at
  ``B``), and the online attacker's value;
* :func:`harden` — the protection set, within a protection budget ``D``, that minimises the
  attacker's optimum at ``B`` (an exact min–max by hitting-set branching);
* :func:`online_attack_value` — an attacker who sees the true state and the controller's
  memory and may alter every reading differently: maximal reachability of the decoy in the
  product MDP with the attacker's choices, as the least fixed point (policy iteration).

Every attacker value printed is the exact value of an alteration the solver returned
(``misdirect.solve`` re-evaluates it); whatever is not certified is labelled.

This package is the public face; its modules, one concept each:

* ``results`` — what the questions return (``to_dict``: the JSON output);
* ``attack`` — the attacker's solve under a protection set, shared by audit and harden;
* ``mdp`` — maximal reachability by policy iteration, and the budgeted MDP;
* ``online`` — the online attacker;
* ``audit`` — the audit;
* ``harden`` — hardening and its hitting-set lower bound;
* ``robust`` — robust controller synthesis by constraint generation (docs/robust.md).
"""

from misdirect.defence.attack import alterable_sensors, protect
from misdirect.defence.auditing import audit
from misdirect.defence.hardening import harden, hitting_lower_bound, protection_costs
from misdirect.defence.mdp import max_reach
from misdirect.defence.online import cost_unit, online_attack_value
from misdirect.defence.results import (
    AuditResult,
    HardenPoint,
    HardenResult,
    OnlineAttack,
    SensorAudit,
)
from misdirect.defence.robust import RobustResult, robust_controller

__all__ = [
    "AuditResult",
    "HardenPoint",
    "HardenResult",
    "OnlineAttack",
    "RobustResult",
    "SensorAudit",
    "alterable_sensors",
    "audit",
    "cost_unit",
    "harden",
    "hitting_lower_bound",
    "max_reach",
    "online_attack_value",
    "protect",
    "protection_costs",
    "robust_controller",
]
