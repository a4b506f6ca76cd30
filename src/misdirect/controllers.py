"""Controllers from elsewhere: PAYNT's ``.fsc.json`` in and out, and Storm's enabled actions.

PAYNT (the synthesis tool built on Storm) writes a finite-state controller as JSON with
``action_function[node][obs]`` and ``update_function[node][obs]`` (indices), and the labels
``action_labels`` and ``observation_labels`` they refer to. We map both by name onto the
problem's actions and observations; node 0 is the initial node.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from misdirect.errors import ProblemError
from misdirect.io_utils import parse_json, read_text_file
from misdirect.model import Controller, CostModel, Pomdp
from misdirect.storm_models import NO_LABEL, valuation_name

FIELD = "controller.paynt"


def _label(name: Any) -> str:
    """PAYNT writes observation labels as Storm valuations (``[o=3]``, ``[x=2\\t& y=0]``); we
    name them as the Storm model's observations are named (``o=3``, ``x=2,y=0``)."""
    return valuation_name(name)


def _is_index(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


PAYNT_NO_LABEL = "__no_label__"  # PAYNT's name for an unlabelled choice (ours: __NOLABEL__)


@dataclass(frozen=True)
class PayntController:
    controller: Controller
    # observations with a null entry (some node never meets them): not alteration targets
    never_read: np.ndarray


def load_paynt_controller(path: Path, pomdp: Pomdp, *, aliases: Sequence[str] = ()) -> Controller:
    """The controller of a PAYNT ``.fsc.json`` (see :func:`read_paynt_controller`)."""
    return read_paynt_controller(path, pomdp, aliases=aliases).controller


def read_paynt_controller(
    path: Path, pomdp: Pomdp, *, aliases: Sequence[str] = ()
) -> PayntController:
    """Read a PAYNT ``.fsc.json``; every malformed part is a ProblemError naming the file (as
    source), the field inside it (``update_function[1][2]``) and the reason.

    ``aliases[o]`` is Storm's own text for observation ``o`` (PAYNT writes that), matched when
    the label is not one of our names. A ``null`` entry means PAYNT's controller never meets
    that (node, observation): the observation is returned in ``never_read``, and the entry is
    filled with a placeholder (action 0, stay in the node) that no run can reach once no
    alteration may target it."""
    if not Path(path).exists():
        raise ProblemError(f"file not found: {path}", field=FIELD)
    document = parse_json(read_text_file(Path(path)), source=str(path))

    def fail(field: str, reason: str) -> ProblemError:
        return ProblemError(reason, source=str(path), field=field)

    if not isinstance(document, dict):
        raise fail(
            "(top level)", "expected a JSON object with action_function, update_function, ..."
        )
    for key in ("action_function", "update_function", "action_labels", "observation_labels"):
        if key not in document:
            raise fail(
                key,
                "missing (a PAYNT controller needs action_function, "
                "update_function, action_labels and observation_labels)",
            )
        if not isinstance(document[key], list):
            raise fail(key, f"expected a list, got {type(document[key]).__name__}")

    actions = {name: i for i, name in enumerate(pomdp.actions)}
    if PAYNT_NO_LABEL not in actions and NO_LABEL in actions:
        actions[PAYNT_NO_LABEL] = actions[NO_LABEL]
    observations = {name: i for i, name in enumerate(pomdp.observations)}
    # Storm's texts, where they name one observation only (a true boolean prints as nothing)
    texts, counts = np.unique(np.array(aliases, dtype=str), return_counts=True)
    unique_texts = set(texts[counts == 1].tolist())
    for o, text in enumerate(aliases):
        if text in unique_texts and text not in observations:
            observations[text] = o
    action_of = []
    for k, name in enumerate(document["action_labels"]):
        label = str(name) if str(name) in actions else _label(name)
        if label not in actions:
            raise fail(
                f"action_labels[{k}]",
                f"{name!r} is not an action of the model ({', '.join(pomdp.actions)})",
            )
        action_of.append(actions[label])
    obs_columns: list[int] = []
    for k, name in enumerate(document["observation_labels"]):
        label = str(name) if str(name) in observations else _label(name)
        if label not in observations:
            raise fail(f"observation_labels[{k}]", f"{name!r} is not an observation of the model")
        if observations[label] in obs_columns:
            first = obs_columns.index(observations[label])
            raise fail(
                f"observation_labels[{k}]",
                f"{name!r} names the same observation as observation_labels[{first}]",
            )
        obs_columns.append(observations[label])
    if len(obs_columns) != pomdp.n_observations:
        missing = sorted(set(range(pomdp.n_observations)) - set(obs_columns))
        raise fail(
            "observation_labels",
            f"observation {pomdp.observations[missing[0]]!r} is not covered; an attacker can "
            "make the robot see any observation, so every one needs a rule",
        )

    gamma, delta = document["action_function"], document["update_function"]
    n_nodes, n_cols = len(gamma), len(obs_columns)
    if n_nodes == 0:
        raise fail("action_function", "empty: the controller needs at least one node")
    if len(delta) != n_nodes:
        raise fail(
            "update_function",
            f"has {len(delta)} rows (nodes), action_function has {n_nodes}",
        )
    declared = document.get("num_nodes")
    if declared is not None and declared != n_nodes:
        raise fail("num_nodes", f"says {declared!r}, but action_function has {n_nodes} rows")
    declared = document.get("num_observations")
    if declared is not None and declared != n_cols:
        raise fail(
            "num_observations",
            f"says {declared!r}, but observation_labels has {n_cols} entries",
        )
    for key, table in (("action_function", gamma), ("update_function", delta)):
        for n, row in enumerate(table):
            if not isinstance(row, list):
                raise fail(f"{key}[{n}]", f"expected a list, got {type(row).__name__}")
            if len(row) != n_cols:
                raise fail(
                    f"{key}[{n}]",
                    f"has {len(row)} entries, observation_labels has {n_cols} (one per "
                    "observation)",
                )

    action = np.full((n_nodes, pomdp.n_observations), -1, dtype=np.int64)
    update = np.full((n_nodes, pomdp.n_observations), -1, dtype=np.int64)
    never: set[int] = set()
    for n in range(n_nodes):
        for k, o in enumerate(obs_columns):
            if gamma[n][k] is None and delta[n][k] is None:
                if o == pomdp.initial_observation and n == 0:
                    raise fail(
                        f"action_function[{n}][{k}]",
                        "empty, but the robot starts in node 0 reading this observation",
                    )
                never.add(o)
                action[n, o], update[n, o] = action_of[0] if action_of else 0, n
                continue
            chosen = _action_entry(gamma[n][k], f"action_function[{n}][{k}]", fail)
            if not 0 <= chosen < len(action_of):
                raise fail(
                    f"action_function[{n}][{k}]",
                    f"action index {chosen} is out of range (action_labels has "
                    f"{len(action_of)} entries)",
                )
            target = delta[n][k]
            where = f"update_function[{n}][{k}]"
            if target is None:
                raise fail(where, "empty, but action_function has an action here; fill it in")
            if not _is_index(target):
                raise fail(where, f"expected a node index (integer), got {target!r}")
            if not 0 <= target < n_nodes:
                raise fail(
                    where,
                    f"node {target} is out of range (the controller has "
                    f"{n_nodes} nodes, 0..{n_nodes - 1})",
                )
            action[n, o] = action_of[chosen]
            update[n, o] = target
    controller = Controller(
        nodes=tuple(f"n{n}" for n in range(n_nodes)), initial_node=0, action=action, update=update
    )
    return PayntController(controller, np.array(sorted(never), dtype=np.int64))


def _action_entry(chosen: Any, where: str, fail) -> int:
    """One ``action_function`` entry as an action index; randomized only if it is certain."""
    if chosen is None:
        raise fail(where, "empty, but update_function has a node here; fill it in")
    if isinstance(chosen, dict):  # randomized: accept only a point distribution
        try:
            weights = {int(a): float(p) for a, p in chosen.items()}
        except (TypeError, ValueError):
            raise fail(
                where, "a randomized choice must map action indices to probabilities"
            ) from None
        certain = [a for a, p in weights.items() if math.isclose(p, 1.0)]
        if len(certain) != 1:
            raise fail(where, "randomized; misdirect needs a deterministic controller")
        return certain[0]
    if not _is_index(chosen):
        raise fail(where, f"expected an action index (integer), got {chosen!r}")
    return chosen


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


def forbid_targets(cost: CostModel, targets: np.ndarray) -> CostModel:
    """No observation may be altered into one of ``targets`` (cost inf)."""
    pairs = dict(cost.pairs)
    for t in targets.tolist():
        for o in range(cost.n_observations):
            if o != t:
                pairs[o, t] = math.inf
    return CostModel(cost.n_observations, cost.default, pairs, cost.protected)


def forbid_disabled_actions(
    cost: CostModel,
    pomdp: Pomdp,
    controller: Controller,
    enabled: np.ndarray,
    decoy: np.ndarray | None = None,
) -> CostModel:
    """``disabled_action: forbid``: o -> o' is not allowed if, in some state emitting o, some
    node's action for o' is not enabled there. The controller's own choices must be enabled.

    Decoy and absorbing states are skipped: the run has ended there, so whatever the controller
    would play in them is never played.
    """
    ended = pomdp.absorbing.copy()
    if decoy is not None:
        ended |= decoy
    pairs = dict(cost.pairs)
    for o in range(pomdp.n_observations):
        states = np.flatnonzero((pomdp.observation_of == o) & ~ended)
        if states.size == 0:
            continue
        # ok[t]: every node's action for received t is enabled in every state emitting o
        ok = enabled[states][:, controller.action].all(axis=(0, 1))
        if not ok[o]:
            bad_s, bad_n = np.nonzero(~enabled[states][:, controller.action[:, o]])
            n, s = int(bad_n[0]), int(states[bad_s[0]])
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
