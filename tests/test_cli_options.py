"""The shared problem input is declared once (misdirect.cli.options.problem_input): every
command that reads a problem has the same FILE argument and the same input options, with the
same names, defaults and help, just before --json."""

from __future__ import annotations

import typer.main

from misdirect.cli import app

INPUT = ["scenario", "size", "weights", "values", "capacity", "seed"]
PROBLEM_COMMANDS = {
    "evaluate",
    "solve",
    "simulate",
    "show",
    "convert",
    "export-fsc",
    "export-milp",
    "audit",
    "harden",
}


def _commands():
    root = typer.main.get_command(app)
    return {name: command for name, command in root.commands.items() if name in PROBLEM_COMMANDS}


def _described(param):
    return (
        param.param_type_name,
        tuple(param.opts),
        param.default,
        param.required,
        getattr(param, "help", None),
    )


def test_every_problem_command_has_the_same_input_options():
    commands = _commands()
    assert set(commands) == PROBLEM_COMMANDS
    first = None
    for name, command in commands.items():
        params = {p.name: p for p in command.params}
        assert "file" in params and set(INPUT) <= set(params), name
        shared = {n: _described(params[n]) for n in ["file", *INPUT] if n != "seed"}
        if first is None:
            first = shared
        assert shared == first, name
        assert params["file"].param_type_name == "argument"
        assert shared["size"][1:3] == (("--size",), 5)


def test_the_input_options_come_just_before_json():
    for name, command in _commands().items():
        names = [p.name for p in command.params]
        expected = [n for n in INPUT if not (name == "simulate" and n == "seed")]
        at = names.index("as_json")
        assert names[at - len(expected) : at] == expected, name


def test_seed_is_shared_except_where_the_command_has_its_own():
    seeds = {
        name: _described(next(p for p in command.params if p.name == "seed"))
        for name, command in _commands().items()
    }
    simulate = seeds.pop("simulate")
    assert len(set(seeds.values())) == 1
    assert next(iter(seeds.values()))[4] == "Seed (random scenario)."
    assert simulate[1:3] == (("--seed",), 0) and simulate[4] == "Random seed."
