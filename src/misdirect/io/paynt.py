"""Controllers from elsewhere: PAYNT's ``.fsc.json`` in and out, and Storm's enabled actions.

PAYNT (the synthesis tool built on Storm) writes a finite-state controller as JSON with
``action_function[node][obs]`` and ``update_function[node][obs]`` (indices, or distributions
``{index: probability}``), or jointly as ``transitions[node][obs]`` (a distribution over
(action, next node)), and the labels ``action_labels`` and ``observation_labels`` they refer
to. Node 0 is the initial node.

Which observation a column means: for a model misdirect loads through Storm, PAYNT's
observation k of the model as PAYNT builds it (see :class:`misdirect.io.paynt_model.PayntView`),
when the file's labels are exactly PAYNT's for that model; otherwise, and for explicit
models, the labels are matched by name.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import scipy.sparse as sp

from misdirect.core import tolerance
from misdirect.core.model import (
    Controller,
    CostModel,
    Pomdp,
    Problem,
    factored_entries,
    reachable_from,
)
from misdirect.core.product import full_product_matrix
from misdirect.errors import ProblemError
from misdirect.io.files import parse_json, read_text_file
from misdirect.io.paynt_model import PAYNT_NO_LABEL, PayntView
from misdirect.io.storm_names import NO_LABEL, valuation_name

FIELD = "controller.paynt"
SUM_TOLERANCE = tolerance.PAYNT_STOCHASTIC  # PAYNT's probabilities: floats from model checking
_GENERATED = re.compile(r"^\w+_cmd_\d+$")  # PAYNT's name for an unlabelled PRISM command
MAX_LABELS_TRIED = 32  # labels tried as PAYNT's terminal targets when a file does not fit
_PAIR = re.compile(r"^\s*[(\[]?\s*(\d+)\s*,\s*(\d+)\s*[)\]]?\s*$")


def _label(name: Any) -> str:
    """PAYNT writes observation labels as Storm valuations (``[o=3]``, ``[x=2\\t& y=0]``); we
    name them as the Storm model's observations are named (``o=3``, ``x=2,y=0``)."""
    return valuation_name(name)


def _is_index(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


@dataclass(frozen=True)
class PayntController:
    controller: Controller
    # observations with a null entry (some node never meets them): not alteration targets
    never_read: np.ndarray
    # (nodes, observations) bool: the entries PAYNT left null, filled with a placeholder
    undefined: np.ndarray


def load_paynt_controller(path: Path, pomdp: Pomdp, *, aliases: Sequence[str] = ()) -> Controller:
    """The controller of a PAYNT ``.fsc.json`` (see :func:`read_paynt_controller`)."""
    return read_paynt_controller(path, pomdp, aliases=aliases).controller


def read_paynt_controller(
    path: Path,
    pomdp: Pomdp,
    *,
    aliases: Sequence[str] = (),
    view: PayntView | Callable[[], PayntView] | None = None,
) -> PayntController:
    """Read a PAYNT ``.fsc.json``; every malformed part is a ProblemError naming the file (as
    source), the field inside it (``update_function[1][2]``) and the reason.

    ``view`` is the model as PAYNT builds it (or a function building it), for models loaded
    through Storm: when the file's ``observation_labels`` are PAYNT's labels of that model,
    column k is PAYNT's observation k, and PAYNT's action labels (``maze_cmd_8``,
    ``__no_label__``) are mapped as PAYNT made them. Otherwise labels are matched by name;
    ``aliases[o]`` is Storm's own text for observation ``o``, matched when the label is not
    one of our names. A ``null`` entry means PAYNT's controller never meets that (node,
    observation): the observation is returned in ``never_read``, and the entry is filled with
    a placeholder (action 0, stay in the node) that no run can reach once no alteration may
    target it."""
    if not Path(path).exists():
        raise ProblemError(f"file not found: {path}", field=FIELD)
    document = parse_json(read_text_file(Path(path)), source=str(path))

    def fail(field: str, reason: str) -> ProblemError:
        return ProblemError(reason, source=str(path), field=field)

    if not isinstance(document, dict):
        raise fail(
            "(top level)", "expected a JSON object with action_function, update_function, ..."
        )
    joint = "transitions" in document and "action_function" not in document
    tables = ("transitions",) if joint else ("action_function", "update_function")
    for key in (*tables, "action_labels", "observation_labels"):
        if key not in document:
            raise fail(
                key,
                "missing (a PAYNT controller needs action_function, "
                "update_function, action_labels and observation_labels)",
            )
        if not isinstance(document[key], list):
            raise fail(key, f"expected a list, got {type(document[key]).__name__}")

    why_no_view = ""
    if callable(view):
        try:
            view = view()
        except ProblemError as error:  # matched by name then, and said why if that fails
            view, why_no_view = None, error.reason
    labels = document["observation_labels"]
    by_position = view is not None and [str(x) for x in labels] == list(view.labels)

    action_of = _action_columns(document["action_labels"], pomdp, view, fail)
    if by_position:
        assert view is not None  # by_position needs a view
        obs_columns = _columns_by_position(view, labels, pomdp, fail)
    else:
        obs_columns = _columns_by_name(labels, pomdp, aliases, view, why_no_view, fail)
    missing = sorted(set(range(pomdp.n_observations)) - set(obs_columns))
    if missing:
        raise fail(
            "observation_labels",
            f"observation {pomdp.observations[missing[0]]!r} is not covered; an attacker can "
            "make the robot see any observation, so every one needs a rule",
        )

    first_table = document[tables[0]]
    n_nodes, n_cols = len(first_table), len(labels)
    if n_nodes == 0:
        raise fail(tables[0], "empty: the controller needs at least one node")
    if not joint and len(document["update_function"]) != n_nodes:
        raise fail(
            "update_function",
            f"has {len(document['update_function'])} rows (nodes), action_function has {n_nodes}",
        )
    declared = document.get("num_nodes")
    if declared is not None and declared != n_nodes:
        raise fail("num_nodes", f"says {declared!r}, but {tables[0]} has {n_nodes} rows")
    declared = document.get("num_observations")
    if declared is not None and declared != n_cols:
        raise fail(
            "num_observations",
            f"says {declared!r}, but observation_labels has {n_cols} entries",
        )
    for key in tables:
        for n, row in enumerate(document[key]):
            if not isinstance(row, list):
                raise fail(f"{key}[{n}]", f"expected a list, got {type(row).__name__}")
            if len(row) != n_cols:
                raise fail(
                    f"{key}[{n}]",
                    f"has {len(row)} entries, observation_labels has {n_cols} (one per "
                    "observation)",
                )

    # flat entries (node, observation, action, next node, probability) of every cell
    cells: list[tuple[int, int, int, int, float]] = []
    never: set[int] = set()
    undefined = np.zeros((n_nodes, pomdp.n_observations), dtype=bool)
    for n in range(n_nodes):
        for k, o in enumerate(obs_columns):
            if o < 0:  # PAYNT's observation k has no state in our model: never read
                continue
            if joint:
                where = f"transitions[{n}][{k}]"
                pairs = _joint_entry(document["transitions"][n][k], where, fail)
                action_where = update_where = where
            else:
                action_where, update_where = (
                    f"action_function[{n}][{k}]",
                    f"update_function[{n}][{k}]",
                )
                action_dist = _point(
                    document["action_function"][n][k], action_where, "action", fail
                )
                node_dist = _point(document["update_function"][n][k], update_where, "node", fail)
                if action_dist is None and node_dist is not None:
                    raise fail(
                        action_where, "empty, but update_function has a node here; fill it in"
                    )
                if node_dist is None and action_dist is not None:
                    raise fail(
                        update_where, "empty, but action_function has an action here; fill it in"
                    )
                pairs = (
                    None
                    if action_dist is None or node_dist is None
                    else factored_entries(dict(action_dist), dict(node_dist))
                )
            if pairs is None:
                if o == pomdp.initial_observation and n == 0:
                    raise fail(
                        action_where,
                        "empty, but the robot starts in node 0 reading this observation",
                    )
                never.add(o)
                undefined[n, o] = True
                cells.append((n, o, action_of[0] if action_of else 0, n, 1.0))
                continue
            for chosen, target, p in pairs:
                if not 0 <= chosen < len(action_of):
                    raise fail(
                        action_where,
                        f"action index {chosen} is out of range (action_labels has "
                        f"{len(action_of)} entries)",
                    )
                if not 0 <= target < n_nodes:
                    raise fail(
                        update_where,
                        f"node {target} is out of range (the controller has "
                        f"{n_nodes} nodes, 0..{n_nodes - 1})",
                    )
                if by_position and view is not None and view.available[k]:
                    ours = pomdp.actions[action_of[chosen]]
                    enabled = {view.actions.get(label, label) for label in view.available[k]}
                    if ours not in enabled:
                        raise fail(
                            action_where,
                            f"plays {ours!r}, which PAYNT's observation {k} does not enable in "
                            f"this model ({', '.join(sorted(enabled))}): PAYNT built another "
                            "model (other constants, or another property: give its property as "
                            "pomdp.terminal_from)",
                        )
                cells.append((n, o, action_of[chosen], target, p))
    node, observation, action, next_node, probability = (
        np.array(column) for column in zip(*cells, strict=True)
    )
    controller = Controller.from_entries(
        nodes=tuple(f"n{n}" for n in range(n_nodes)),
        initial_node=0,
        n_observations=pomdp.n_observations,
        node=node,
        observation=observation,
        action=action,
        next_node=next_node,
        probability=probability,
    )
    return PayntController(controller, np.array(sorted(never), dtype=np.int64), undefined)


def unmet_rule_warning(
    problem: Problem,
    undefined: np.ndarray,
    path: Path,
    *,
    terminal_given: bool,
    labels: dict[str, np.ndarray] | None = None,
) -> str | None:
    """Whether the unaltered robot, before its run ends, reaches an entry PAYNT left null: a
    warning saying so (and which label's states, made terminal, would avoid it), else None.

    PAYNT leaves null exactly the (node, observation) entries its controller never meets in
    its own build of the model. Meeting one here means this model is not PAYNT's, most often
    because PAYNT made its property's target states terminal and this build did not (without
    ``terminal``/``terminal_from`` the robot walks on past the goal into entries PAYNT never
    met), and the values then differ from PAYNT's with no other sign. One reachability
    search over the product chain per label tried; runs end at decoy and absorbing states."""
    if not undefined.any():
        return None
    pomdp, controller = problem.pomdp, problem.controller
    n_nodes = controller.n_nodes
    full = full_product_matrix(problem, problem.identity()).tocsr()
    world = np.repeat(np.arange(pomdp.n_states), n_nodes)
    node = np.tile(np.arange(n_nodes), pomdp.n_states)
    null = undefined[node, pomdp.observation_of[world]]
    start = np.array([pomdp.initial_state * n_nodes + controller.initial_node])

    def met(ended: np.ndarray) -> np.ndarray:
        onward = (sp.diags((~ended).astype(np.float64)) @ full).tocsr()
        return np.flatnonzero(reachable_from(onward, start) & ~ended & null)

    ended = (problem.decoy | pomdp.absorbing)[world]
    first = met(ended)
    if first.size == 0:
        return None
    s, n = int(world[first[0]]), int(node[first[0]])
    labels = labels or {}
    candidates = [
        name
        for name, mask in sorted(labels.items())
        if mask.any() and not mask[pomdp.initial_state]  # `init` would end every run at once
    ][:MAX_LABELS_TRIED]
    fitting = [name for name in candidates if met(ended | labels[name][world]).size == 0]
    if fitting:
        hint = (
            f"it fits this model with the states labelled {fitting[0]!r} terminal, as PAYNT "
            f'builds it for a property such as P=? [F "{fitting[0]}"]: give that property '
            "as pomdp.terminal_from"
        )
    elif terminal_given:
        hint = "PAYNT built another model than this one (other constants, or another property?)"
    else:
        hint = (
            "PAYNT most likely built this model with its property's target states terminal: "
            "give the property as pomdp.terminal_from (or the targets as pomdp.terminal)"
        )
    return (
        f"{Path(path).name} has no rule for observation "
        f"{pomdp.observations[pomdp.observation_of[s]]!r} in node {controller.nodes[n]} (null), "
        f"yet the unaltered robot reaches it (state {pomdp.states[s]!r}): {hint}. misdirect "
        "plays a placeholder there, so these values are not those of PAYNT's model"
    )


def _action_columns(names: list[Any], pomdp: Pomdp, view: PayntView | None, fail) -> list[int]:
    """Our action of each ``action_labels`` entry: by name, or as PAYNT labelled it."""
    actions = {name: i for i, name in enumerate(pomdp.actions)}
    if PAYNT_NO_LABEL not in actions and NO_LABEL in actions:
        actions[PAYNT_NO_LABEL] = actions[NO_LABEL]
    action_of = []
    for k, name in enumerate(names):
        text = str(name)
        if text in actions:
            action_of.append(actions[text])
        elif view is not None and view.actions.get(text) in actions:
            action_of.append(actions[view.actions[text]])
        elif _label(name) in actions:
            action_of.append(actions[_label(name)])
        else:
            hint = ""
            if _GENERATED.match(text):
                hint = "; PAYNT names an unlabelled PRISM command so: " + (
                    "PAYNT's build of this model has no such command (other constants?)"
                    if view is not None
                    else "load the model from its PRISM file (pomdp: {prism: ...}) to map it"
                )
            raise fail(
                f"action_labels[{k}]",
                f"{name!r} is not an action of the model ({', '.join(pomdp.actions)}){hint}",
            )
    return action_of


def _columns_by_position(view: PayntView, labels: list[Any], pomdp: Pomdp, fail) -> list[int]:
    """Column k is PAYNT's observation k: our observation of the same states."""
    columns: list[int] = []
    for k, o in enumerate(view.observation.tolist()):
        if o == -2:
            raise fail(
                f"observation_labels[{k}]",
                f"PAYNT's observation {k} ({labels[k]!r}) spans several observations of the "
                "model misdirect built",
            )
        if o >= 0 and o in columns:
            first = columns.index(o)
            raise fail(
                f"observation_labels[{k}]",
                f"PAYNT's observation {k} is observation {pomdp.observations[o]!r}, as is "
                f"observation_labels[{first}]",
            )
        columns.append(o)
    return columns


def _columns_by_name(
    labels: list[Any],
    pomdp: Pomdp,
    aliases: Sequence[str],
    view: PayntView | None,
    why_no_view: str,
    fail,
) -> list[int]:
    """Column k is the observation its label names (our name, or Storm's text of it)."""
    observations = {name: i for i, name in enumerate(pomdp.observations)}
    # Storm's texts, where they name one observation only (a true boolean prints as nothing)
    texts, counts = np.unique(np.array(aliases, dtype=str), return_counts=True)
    unique_texts = set(texts[counts == 1].tolist())
    for o, text in enumerate(aliases):
        if text in unique_texts and text not in observations:
            observations[text] = o
    columns: list[int] = []
    for k, name in enumerate(labels):
        label = str(name) if str(name) in observations else _label(name)
        if label not in observations:
            if view is not None and view.kind == "drn":
                hint = (
                    f" (a DRN file numbers its observations, named {pomdp.observations[0]!r}, … "
                    f"here, and PAYNT labels them {view.labels[0]!r}, …: this controller names "
                    "another model's observations; a DRN written by `misdirect convert --to drn` "
                    "keeps the names, or export the controller from this problem)"
                )
            elif view is not None and len(view.labels) != len(labels):
                hint = (
                    f" (PAYNT's build of this model has {len(view.labels)} observations, the "
                    f"file {len(labels)}: was PAYNT run on this program with the same "
                    "constants? give its property as pomdp.terminal_from)"
                )
            elif view is not None:
                hint = (
                    f" (nor PAYNT's label of its observation {k}, {view.labels[k]!r}: was PAYNT "
                    "run on this program with the same constants? give its property as "
                    "pomdp.terminal_from)"
                )
            else:
                hint = f" ({why_no_view})" if why_no_view else ""
            raise fail(
                f"observation_labels[{k}]", f"{name!r} is not an observation of the model{hint}"
            )
        if observations[label] in columns:
            first = columns.index(observations[label])
            raise fail(
                f"observation_labels[{k}]",
                f"{name!r} names the same observation as observation_labels[{first}]",
            )
        columns.append(observations[label])
    return columns


def _distribution(items: list[tuple[Any, Any]], where: str, fail) -> list[tuple[Any, float]]:
    """The entries of positive probability, checked: numbers in [0, 1] summing to 1."""
    support, total = [], 0.0
    for key, p in items:
        if isinstance(p, bool) or not isinstance(p, int | float) or not 0 <= p <= 1:
            raise fail(where, f"probability {p!r} of {key!r} is not a number in [0, 1]")
        total += p
        if p > 0:
            support.append((key, float(p)))
    if abs(total - 1.0) > SUM_TOLERANCE:
        raise fail(where, f"probabilities sum to {total:.12g}, not 1")
    return [(key, p / total) for key, p in support]  # PAYNT's floats, made to sum to 1


def _point(entry: Any, where: str, what: str, fail) -> list[tuple[int, float]] | None:
    """One ``action_function``/``update_function`` entry as a distribution
    ``[(index, probability), ...]`` (None when empty): an integer (probability 1), or a
    ``{index: probability}`` map (PAYNT's randomized FscFactored)."""
    if entry is None:
        return None
    if isinstance(entry, dict):
        items = []
        for key, p in entry.items():
            if not re.fullmatch(r"\s*\d+\s*", str(key)):
                raise fail(where, f"a randomized choice must map {what} indices to probabilities")
            items.append((int(key), p))
        return _distribution(items, where, fail)
    if not _is_index(entry):
        article = "an" if what[0] in "aeiou" else "a"
        raise fail(where, f"expected {article} {what} index (integer), got {entry!r}")
    return [(entry, 1.0)]


def _joint_entry(entry: Any, where: str, fail) -> list[tuple[int, int, float]] | None:
    """One entry of PAYNT's joint ``Fsc`` (``transitions[node][obs]``, a distribution over
    (action, next node)) as ``[(action, next node, probability), ...]``; None when empty.
    Accepted forms:
    ``{"(a, m)": p}`` (also ``"a,m"``), ``[[a, m, p], ...]`` and
    ``[{"action": a, "update": m, "probability": p}, ...]`` (``memory``/``node`` for
    ``update``, ``prob`` for ``probability``)."""
    if entry is None:
        return None
    items: list[tuple[Any, Any]] = []
    shape = (
        'expected a distribution over (action, next node): {"(a, m)": p}, [[a, m, p], ...] '
        'or [{"action": a, "update": m, "probability": p}, ...]'
    )
    if isinstance(entry, dict):
        for key, p in entry.items():
            match = _PAIR.match(str(key))
            if match is None:
                raise fail(where, f"{shape}; got the key {key!r}")
            items.append(((int(match[1]), int(match[2])), p))
    elif isinstance(entry, list):
        for item in entry:
            if isinstance(item, list) and len(item) == 3:
                a, m, p = item
            elif isinstance(item, dict):
                a = item.get("action")
                m = next((item[k] for k in ("update", "memory", "node") if k in item), None)
                p = next((item[k] for k in ("probability", "prob") if k in item), None)
            else:
                raise fail(where, f"{shape}; got {item!r}")
            if not (_is_index(a) and _is_index(m)):
                raise fail(where, f"{shape}; got {item!r}")
            items.append(((a, m), p))
    else:
        raise fail(where, f"{shape}; got {entry!r}")
    if not items:
        raise fail(where, f"{shape}; got an empty one")
    return [(a, m, p) for (a, m), p in _distribution(items, where, fail)]


def controller_to_paynt(controller: Controller, pomdp: Pomdp) -> dict[str, Any]:
    """Our controller in PAYNT's format (initial node first).

    Deterministic: integer ``action_function``/``update_function``. Randomized: PAYNT's
    randomized ``FscFactored`` (``{index: probability}`` maps) when every move is the product
    of its action and next-node marginals, as FscFactored means it; otherwise the joint form
    ``transitions[node][obs]`` = ``{"(action, node)": probability}`` (PAYNT's ``Fsc``)."""
    order = [controller.initial_node] + [
        n for n in range(controller.n_nodes) if n != controller.initial_node
    ]
    position = np.empty(controller.n_nodes, dtype=np.int64)
    position[order] = np.arange(controller.n_nodes)
    document: dict[str, Any] = {
        "num_nodes": controller.n_nodes,
        "num_observations": pomdp.n_observations,
        "is_deterministic": controller.is_deterministic,
    }
    if controller.is_deterministic:
        document["action_function"] = [controller.action[n].tolist() for n in order]
        document["update_function"] = [position[controller.update[n]].tolist() for n in order]
    else:
        moves = [_paynt_move(controller, m, position) for m in range(controller.n_moves)]
        if all(move[0] is not None for move in moves):
            for key, part in (("action_function", 0), ("update_function", 1)):
                document[key] = [[moves[m][part] for m in controller.move[n]] for n in order]
        else:
            document["transitions"] = [[moves[m][2] for m in controller.move[n]] for n in order]
    document["action_labels"] = list(pomdp.actions)
    document["observation_labels"] = list(pomdp.observations)
    document["node_labels"] = [controller.nodes[n] for n in order]
    return document


def _paynt_move(controller: Controller, m: int, position: np.ndarray) -> tuple[Any, Any, Any]:
    """Move ``m`` as PAYNT writes it: its action and next-node marginals (None, None when the
    move is not their product) and its joint ``{"(a, n)": p}`` map; nodes renumbered."""
    joint = {f"({a}, {position[n]})": p for a, n, p in controller.move_table(m)}
    factored = controller.factored_move(m)
    if factored is None:
        return None, None, joint
    by_action, by_next = factored
    return (
        {str(a): p for a, p in sorted(by_action.items())},
        {str(position[n]): p for n, p in sorted(by_next.items(), key=lambda x: position[x[0]])},
        joint,
    )


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
    node's move for o' may play an action not enabled there (for a randomized controller, any
    action of the move's support). The controller's own choices must be enabled.

    Decoy and absorbing states are skipped: the run has ended there, so whatever the controller
    would play in them is never played.
    """
    ended = pomdp.absorbing.copy()
    if decoy is not None:
        ended |= decoy
    pairs = dict(cost.pairs)
    owner, move_action, _, _ = controller.move_entries(np.arange(controller.n_moves))
    for o in range(pomdp.n_observations):
        states = np.flatnonzero((pomdp.observation_of == o) & ~ended)
        if states.size == 0:
            continue
        # (|A|,) disabled in some state emitting o (all over an axis: an array, not a scalar)
        disabled = ~cast(np.ndarray, enabled[states].all(axis=0))
        bad_move = np.bincount(owner, weights=disabled[move_action], minlength=controller.n_moves)
        # ok[t]: every node's move for received t plays only actions enabled here
        ok = ~(bad_move[controller.move] > 0).any(axis=0)
        if not ok[o]:
            n = int(np.flatnonzero(bad_move[controller.move[:, o]] > 0)[0])
            m = int(controller.move[n, o])
            played = controller.move_action[controller.move_ptr[m] : controller.move_ptr[m + 1]]
            a = int(played[disabled[played]][0])
            s = int(states[np.flatnonzero(~enabled[states, a])[0]])
            raise ProblemError(
                f"the controller plays {pomdp.actions[a]!r} in state "
                f"{pomdp.states[s]!r} (observation {pomdp.observations[o]!r}, node "
                f"{controller.nodes[n]!r}), which the model does not enable there; fix the "
                "controller or use disabled_action: stay",
                field="pomdp.disabled_action",
            )
        for t in np.flatnonzero(~ok):
            pairs[o, int(t)] = math.inf
    return CostModel(cost.n_observations, cost.default, pairs, cost.protected)
