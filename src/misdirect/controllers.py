"""Controllers from elsewhere: PAYNT's ``.fsc.json`` in and out, and Storm's enabled actions.

PAYNT (the synthesis tool built on Storm) writes a finite-state controller as JSON with
``action_function[node][obs]`` and ``update_function[node][obs]`` (indices), and the labels
``action_labels`` and ``observation_labels`` they refer to. We map both by name onto the
problem's actions and observations; node 0 is the initial node.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from misdirect.errors import ProblemError
from misdirect.model import Controller, CostModel, Pomdp

FIELD = "controller.paynt"


def _label(name: Any) -> str:
    """PAYNT writes observation labels as Storm valuations, e.g. ``[o=3]``; we name them ``o=3``."""
    return str(name).strip().strip("[]").strip().replace("\t", "").replace(" & ", ",")


def load_paynt_controller(path: Path, pomdp: Pomdp) -> Controller:
    try:
        document = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ProblemError(f"file not found: {path}", field=FIELD) from None
    except (OSError, json.JSONDecodeError) as error:
        raise ProblemError(f"cannot read {path}: {error}", field=FIELD) from None
    for key in ("action_function", "update_function", "action_labels", "observation_labels"):
        if key not in document:
            raise ProblemError(f"{path.name} has no {key!r}", field=FIELD)
    actions = {name: i for i, name in enumerate(pomdp.actions)}
    observations = {name: i for i, name in enumerate(pomdp.observations)}
    action_of = []
    for name in document["action_labels"]:
        label = str(name) if str(name) in actions else _label(name)
        if label not in actions:
            raise ProblemError(
                f"action label {name!r} of {path.name} is not an action of the model "
                f"({', '.join(pomdp.actions)})",
                field=FIELD,
            )
        action_of.append(actions[label])
    obs_columns = []
    for name in document["observation_labels"]:
        label = str(name) if str(name) in observations else _label(name)
        if label not in observations:
            raise ProblemError(
                f"observation label {name!r} of {path.name} is not an observation of the model",
                field=FIELD,
            )
        obs_columns.append(observations[label])
    if len(set(obs_columns)) != pomdp.n_observations:
        missing = sorted(set(range(pomdp.n_observations)) - set(obs_columns))
        raise ProblemError(
            f"{path.name} does not cover observation {pomdp.observations[missing[0]]!r}; an "
            "attacker can make the robot see any observation, so every one needs a rule",
            field=FIELD,
        )
    gamma, delta = document["action_function"], document["update_function"]
    n_nodes = len(gamma)
    action = np.full((n_nodes, pomdp.n_observations), -1, dtype=np.int64)
    update = np.full((n_nodes, pomdp.n_observations), -1, dtype=np.int64)
    for n in range(n_nodes):
        for k, o in enumerate(obs_columns):
            where = f"action_function[{n}][{k}]"
            chosen = gamma[n][k]
            if isinstance(chosen, dict):  # randomized: accept only a point distribution
                certain = [a for a, p in chosen.items() if math.isclose(float(p), 1.0)]
                if len(certain) != 1:
                    raise ProblemError(
                        f"{where} is randomized; misdirect needs a deterministic controller",
                        field=FIELD,
                    )
                chosen = int(certain[0])
            if chosen is None or delta[n][k] is None:
                raise ProblemError(
                    f"{where} or update_function[{n}][{k}] is empty; an attacker can make the "
                    "robot see any observation, so fill it in",
                    field=FIELD,
                )
            if not 0 <= int(chosen) < len(action_of) or not 0 <= int(delta[n][k]) < n_nodes:
                raise ProblemError(f"{where}: index out of range", field=FIELD)
            action[n, o] = action_of[int(chosen)]
            update[n, o] = int(delta[n][k])
    return Controller(
        nodes=tuple(f"n{n}" for n in range(n_nodes)), initial_node=0, action=action, update=update
    )


def controller_to_paynt(controller: Controller, pomdp: Pomdp) -> dict[str, Any]:
    """Our controller in PAYNT's format (initial node first)."""
    order = [controller.initial_node] + [
        n for n in range(controller.n_nodes) if n != controller.initial_node
    ]
    position = {n: i for i, n in enumerate(order)}
    return {
        "num_nodes": controller.n_nodes,
        "num_observations": pomdp.n_observations,
        "is_deterministic": True,
        "action_function": [controller.action[n].tolist() for n in order],
        "update_function": [[position[int(m)] for m in controller.update[n]] for n in order],
        "action_labels": list(pomdp.actions),
        "observation_labels": list(pomdp.observations),
        "node_labels": [controller.nodes[n] for n in order],
    }


def forbid_disabled_actions(
    cost: CostModel, pomdp: Pomdp, controller: Controller, enabled: np.ndarray
) -> CostModel:
    """``disabled_action: forbid``: o -> o' is not allowed if, in some state emitting o, some
    node's action for o' is not enabled there. The controller's own choices must be enabled."""
    pairs = dict(cost.pairs)
    for o in range(pomdp.n_observations):
        states = np.flatnonzero(pomdp.observation_of == o)
        if states.size == 0:
            continue
        # ok[t]: every node's action for received t is enabled in every state emitting o
        ok = enabled[states][:, controller.action].all(axis=(0, 1))
        if not ok[o]:
            n, s = _first_disabled(enabled, states, controller.action[:, o])
            raise ProblemError(
                f"the controller plays {pomdp.actions[controller.action[n, o]]!r} in state "
                f"{pomdp.states[s]!r} (observation {pomdp.observations[o]!r}, node "
                f"{controller.nodes[n]!r}), which the model does not enable there; fix the "
                "controller or use disabled_action: stay",
                field="pomdp.disabled_action",
            )
        for t in np.flatnonzero(~ok):
            pairs[o, int(t)] = math.inf
    return CostModel(cost.n_observations, cost.default, pairs, cost.protected)


def _first_disabled(
    enabled: np.ndarray, states: np.ndarray, actions: np.ndarray
) -> tuple[int, int]:
    for n, a in enumerate(actions):
        for s in states:
            if not enabled[s, a]:
                return n, int(s)
    raise AssertionError("no disabled action found")
