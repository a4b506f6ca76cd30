"""The problem file's text read against a Storm model: constants, conditions and properties.

A problem file over a PRISM or DRN model names states by condition (decoys, ``terminal``), by
property (``terminal_from``) and sets the program's constants. This module reads that text:
through Storm's own parser against the PRISM program (labels substituted, evaluated here with
numpy on the state valuations), or, for DRN models, as label expressions parsed here. Storm's
error text is turned into one line (:func:`storm_message`), wherever it comes from.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from misdirect.errors import ProblemError
from misdirect.io.storm_guard import check_nesting


def storm_message(error: Exception) -> str:
    """Storm's error text on one line (it spans several, with indentation)."""
    return " ".join(str(error).split())


def instantiate_constants(stormpy, program, constants: str):
    """Set ``constants`` ("N=5,p=0.1"); a bad definition is an error in ``pomdp.constants``."""
    check_nesting(constants, field="pomdp.constants", what="the constants")
    try:
        program, _ = stormpy.instantiate_constants(program, constants)
    except Exception as error:  # Storm raises RuntimeError (WrongFormatException) here
        message = storm_message(error)
        message = re.sub(
            r"^(\w+Exception: )?Illegal constant definition string[^:]*: ", "", message
        )
        message = re.sub(r"^\w+Exception: ", "", message).rstrip(".")
        undefined = [c.name for c in program.constants if not c.defined]
        known = ", ".join(undefined) if undefined else "none: the program defines all of them"
        raise ProblemError(
            f"cannot set {constants!r}: {message} (constants to set: {known})",
            field="pomdp.constants",
        ) from None
    return program


# -- PRISM expressions and properties -----------------------------------------------------------


@dataclass(frozen=True)
class PrismProgram:
    """A PRISM program and what is needed to parse expressions against it."""

    stormpy: Any
    program: Any
    source: str | None


def strip_comments(text: str) -> str:
    """PRISM source without its ``//`` comments."""
    return re.sub(r"//[^\n]*", "", text)


def _substitute_labels(program, text: str, field: str) -> str:
    """``"goal"`` (a label, as PRISM properties write it) becomes its definition, so that the
    whole condition is one expression over variables. A bare label name that is not also a
    variable is accepted too."""
    if ";" in text or "[" in text or "]" in text:
        raise ProblemError("expected a state expression (no ';' or brackets)", field=field)
    flat = program.substitute_formulas()
    labels = {label.name: str(label.expression) for label in flat.labels}
    variables = {v.name for v in program.variables} | {c.name for c in program.constants}

    def quoted(match: re.Match) -> str:
        if match[1] not in labels:
            known = ", ".join(sorted(labels)) or "none"
            raise ProblemError(f"no label {match[1]!r} (labels: {known})", field=field)
        return f"({labels[match[1]]})"

    text = re.sub(r'"([^"]*)"', quoted, text)

    def bare(match: re.Match) -> str:
        word = match[0]
        return f"({labels[word]})" if word in labels and word not in variables else word

    return re.sub(r"(?<![\w.])[A-Za-z_]\w*(?!\s*\()", bare, text)


def parse_property(stormpy, program, text: str, field: str):
    """Storm's formula of one property ``text``, against ``program`` (None: no program)."""
    check_nesting(text, field=field, what="the expression")
    try:
        if program is None:
            properties = stormpy.parse_properties(text)
        else:
            properties = stormpy.parse_properties(text, program)
    except Exception as error:
        message = re.sub(r"^\w+Exception: ", "", storm_message(error))
        raise ProblemError(f"Storm cannot parse it: {message}", field=field) from None
    if len(properties) != 1:
        raise ProblemError(f"expected one property, got {len(properties)}", field=field)
    return properties[0].get_raw_formula()


def prism_target(stormpy, program, text: str, field: str):
    """``P=? [F (text)]`` for the program: Storm builds its target states terminal."""
    expression_text = _substitute_labels(program, text, field)
    return parse_property(stormpy, program, f"P=? [F ({expression_text})]", field)


def prism_property(stormpy, program, text: str):
    """The ``terminal_from`` property, parsed against the program."""
    return parse_property(stormpy, program, text, "pomdp.terminal_from")


def prism_expression(stormpy, program, text: str, *, integer: bool = False, field: str = ""):
    """``text`` as a Storm expression over the program's variables (labels substituted)."""
    expression_text = _substitute_labels(program, text, field)
    wrapped = f"(({expression_text}) = 0)" if integer else f"({expression_text})"
    formula = parse_property(stormpy, program, f"P=? [F {wrapped}]", field).subformula
    state = formula.subformula
    if not hasattr(state, "get_expression"):  # true/false come back as literal formulas
        literal = str(state).strip().lower()
        if literal in ("true", "false"):
            return literal == "true"
        raise ProblemError("expected a state expression", field=field)
    expression = state.get_expression()
    return expression.get_operand(0) if integer else expression


def evaluate(expression, env: dict[str, np.ndarray]):
    """A Storm expression evaluated on arrays of variable values (numpy, one pass per node)."""
    if isinstance(expression, bool | int | float):
        return expression
    if expression.is_literal():
        if expression.has_boolean_type():
            return expression.evaluate_as_bool()
        if expression.has_integer_type():
            return expression.evaluate_as_int()
        return expression.evaluate_as_double()
    if expression.is_variable():
        name = expression.get_identifier()
        if name not in env:
            raise ValueError(f"no value for {name!r}")
        return env[name]
    if not expression.is_function_application:
        raise ValueError(f"cannot evaluate {expression}")
    args = [evaluate(expression.get_operand(i), env) for i in range(expression.arity)]
    name = str(expression.operator).rsplit(".", 1)[-1]
    if name == "MINUS" and len(args) == 1:
        return np.negative(args[0])
    operation = _OPERATIONS.get(name)
    if operation is None:
        raise ValueError(f"operator {name} is not supported")
    return operation(*args)


_OPERATIONS: dict[str, Callable[..., Any]] = {
    "AND": np.logical_and,
    "OR": np.logical_or,
    "XOR": np.logical_xor,
    "NOT": np.logical_not,
    "IMPLIES": lambda a, b: np.logical_or(np.logical_not(a), b),
    "IFF": np.equal,
    "PLUS": np.add,
    "MINUS": np.subtract,
    "TIMES": np.multiply,
    "DIVIDE": np.true_divide,
    "MODULO": np.mod,
    "POWER": np.power,
    "MIN": np.minimum,
    "MAX": np.maximum,
    "FLOOR": np.floor,
    "CEIL": np.ceil,
    "EQUAL": np.equal,
    "NOT_EQUAL": np.not_equal,
    "LESS": np.less,
    "LESS_OR_EQUAL": np.less_equal,
    "GREATER": np.greater,
    "GREATER_OR_EQUAL": np.greater_equal,
    "ITE": np.where,
}


def prism_condition(stormpy, program, values, labels) -> Callable[[str, str], np.ndarray]:
    """PRISM state conditions: expressions over variables, formulas, constants and labels."""
    n = next(iter(labels.values())).size if labels else 0

    def condition(text: str, field: str) -> np.ndarray:
        expression = prism_expression(stormpy, program, text, field=field)
        try:
            result = np.asarray(evaluate(expression, values))
        except ValueError as error:
            raise ProblemError(f"cannot evaluate {text!r}: {error}", field=field) from None
        if result.dtype != bool:
            raise ProblemError(f"{text!r} is not a condition (true or false)", field=field)
        return np.broadcast_to(result, (n,)).copy()

    return condition


# -- label expressions (DRN) --------------------------------------------------------------------

_TOKEN = re.compile(r'\s*(?:(?P<op>[!&|()])|"(?P<quoted>[^"]*)"|(?P<name>[A-Za-z_][\w\-]*))')


def label_condition(labels: dict[str, np.ndarray]) -> Callable[[str, str], np.ndarray]:
    """Label expressions (``!``, ``&``, ``|``, parentheses over label names) for DRN models,
    parsed here (recursive descent; nothing is evaluated as code)."""
    n = next(iter(labels.values())).size if labels else 0

    def condition(text: str, field: str) -> np.ndarray:
        check_nesting(text, field=field, what="the label expression")  # the parser recurses
        tokens: list[str] = []
        position = 0
        text = text.strip()
        while position < len(text):
            match = _TOKEN.match(text, position)
            if match is None or match.end() == position:
                raise ProblemError(
                    f"unexpected {text[position:].strip()[:10]!r} at character {position + 1} "
                    "(a label expression: labels, !, &, |, parentheses)",
                    field=field,
                )
            position = match.end()
            tokens.append(match["op"] or f"@{match['quoted'] or match['name']}")
        tokens.append("")
        at = 0

        def atom() -> np.ndarray:
            nonlocal at
            negations = 0  # counted, not recursed: "!!!...!x" may be any length
            while tokens[at] == "!":
                negations += 1
                at += 1
            value = operand()
            return ~value if negations % 2 else value

        def operand() -> np.ndarray:
            nonlocal at
            token = tokens[at]
            at += 1
            if token == "(":
                value = disjunction()
                if tokens[at] != ")":
                    raise ProblemError("missing ')'", field=field)
                at += 1
                return value
            if token.startswith("@"):
                label = token[1:]
                if label in ("true", "false"):
                    return np.full(n, label == "true")
                if label not in labels:
                    known = ", ".join(sorted(labels)) or "none"
                    raise ProblemError(f"no label {label!r} (labels: {known})", field=field)
                return labels[label]
            raise ProblemError(f"unexpected {token or 'end of text'!r}", field=field)

        def conjunction() -> np.ndarray:
            nonlocal at
            value = atom()
            while tokens[at] == "&":
                at += 1
                value = value & atom()
            return value

        def disjunction() -> np.ndarray:
            nonlocal at
            value = conjunction()
            while tokens[at] == "|":
                at += 1
                value = value | conjunction()
            return value

        value = disjunction()
        if tokens[at] != "":
            raise ProblemError(f"unexpected {tokens[at].lstrip('@')!r}", field=field)
        return value.copy()

    return condition


# -- properties as objectives -------------------------------------------------------------------

# what may be the objective, said in every refusal
_SUPPORTED = (
    "supported: P=? [F target], P=? [stay U target], P=? [F<=k target], P=? [stay U<=k target] "
    "(target and stay: labels or state expressions)"
)
# a path or an operator inside a state formula, as Storm prints it (labels stripped first)
_NESTED = re.compile(
    r"(?<![\w.])(?:[FGXU](?=\s|<|>|\[)|W(?=\s)|P\s*(?:max|min)?\s*(?:=\?|[<>])|R\s*[\[{=<>])"
)


@dataclass(frozen=True)
class Reachability:
    """A property ``P=? [stay U<=bound target]`` as its parts' texts (``stay`` None:
    ``true``; ``bound`` None: unbounded), each a state condition of the model."""

    target: str
    stay: str | None
    bound: int | None


def _refuse(text: str, what: str, field: str) -> ProblemError:
    return ProblemError(
        f"{text!r}: {what} is not supported as the objective; {_SUPPORTED}", field=field
    )


def _state_formula(formula, text: str, field: str) -> str | None:
    """The state formula's text (None: ``true``), refused when it holds a path formula or
    an operator (a nested property)."""
    shown = str(formula).strip()
    if _NESTED.search(re.sub(r'"[^"]*"', '""', shown)):
        raise _refuse(text, "a nested property (a path formula inside a state formula)", field)
    return None if shown == "true" else shown


def reachability(formula, text: str, field: str) -> Reachability:
    """The parts of a property Storm parsed (:func:`parse_property`), or an error naming what
    is not supported (rewards, Pmin, probability bounds, multi-objective, nested properties,
    G, X, lower step bounds). A strict step bound ``F<k`` is ``F<=k-1``; ``Pmax=?`` is
    ``P=?`` (the controller is fixed: the chain has no choice to optimise)."""
    if formula.is_multi_objective_formula:
        raise _refuse(text, "a multi-objective property", field)
    if formula.is_reward_operator_formula:
        raise _refuse(text, "a reward property (R)", field)
    if not formula.is_probability_operator_formula:
        raise _refuse(text, "a property that is not P=? [...]", field)
    if formula.has_bound:
        raise _refuse(text, "a probability bound (P>p, P<p: give P=?)", field)
    if formula.has_optimality_type:
        direction = str(formula.optimality_type).rsplit(".", 1)[-1]
        if direction == "MINIMIZE":
            raise _refuse(
                text, "Pmin (the attacker maximises; the robot's controller is fixed)", field
            )
        # Pmax=? is P=? here: the controller is fixed, the chain is a chain
    path = formula.subformula
    if path.is_eventually_formula:
        return Reachability(_required(path.subformula, text, field), None, None)
    if path.is_bounded_until_formula:
        shown = str(path)
        if path.has_lower_bound:
            raise _refuse(text, "a lower step bound (F>=k, F[a,b])", field)
        bound_expression = path.upper_bound_expression
        try:
            bound = bound_expression.evaluate_as_int()
        except Exception:
            raise _refuse(
                text, f"the step bound {bound_expression} (not an integer)", field
            ) from None
        if re.search(r"U<(?!=)", shown):  # strict: within k - 1 steps
            bound -= 1
        if bound < 0:
            raise ProblemError(f"{text!r}: the step bound is below 0", field=field)
        left = _state_formula(path.left_subformula, text, field)
        return Reachability(_required(path.right_subformula, text, field), left, bound)
    if path.is_until_formula:
        left = _state_formula(path.left_subformula, text, field)
        return Reachability(_required(path.right_subformula, text, field), left, None)
    shown = str(path).strip()
    kind = {"G": "G (globally)", "X": "X (next)", "W": "W (weak until)"}.get(
        shown[:1], "this path formula"
    )
    raise _refuse(text, kind, field)


def _required(formula, text: str, field: str) -> str:
    target = _state_formula(formula, text, field)
    if target is None:
        raise ProblemError(f"{text!r}: the target is every state (true)", field=field)
    return target
