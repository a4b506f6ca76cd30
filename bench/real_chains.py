"""Evaluation on chains shaped like real benchmarks: ours against Storm on the same product chain.

    python bench/real_chains.py [--out bench/results] [--quick] [--repeats 5]

Issue 16: on PAYNT's drone benchmark (118,504 product states, one memoryless controller)
``misdirect evaluate`` ran past 900 s while Storm checked the chain in 0.34 s. The model is
not available here, so :func:`misdirect.scenarios.drone.drone` builds one of the same shape: a
drone crossing a grid among agents that patrol at random, seen within a radius; its dodging
controller makes the product chain one wide strongly connected component.

Each case runs in a fresh process. It builds the product chain, then times, best of
``--repeats`` and interleaved so that a busy machine hurts both sides alike:

* ours: :func:`misdirect.evaluate` (product, probability, every outcome, expected visits) and
  :func:`misdirect.core.evaluate.decoy_probability` (product and probability alone);
* Storm (stormpy) model checking ``P=? [F "decoy"]`` on the very same product chain, loaded
  from explicit DRN: its default set-up and each sparse engine (Eigen only where it is not
  slow: it runs GMRES with ILU and takes seconds here).

The ratio ours / Storm's default is the issue's measure (target <= 2); ours / Storm's fastest
engine is reported too. Storm stops at a relative precision of 1e-6; ours comes with a proven
error bound (``error_bound``). Writes real_chains.{json,csv,md} under --out.
"""

from __future__ import annotations

import argparse
import csv
import json
import multiprocessing
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from speed import _isolated, _peak_memory_gib

CASES = [  # (label, drone() keyword arguments)
    ("drone 8x8, 2 agents", {"n": 8, "agents": 2, "rows": 3}),
    ("drone 8x8, 3 agents", {"n": 8, "agents": 3, "rows": 2}),
    ("drone 10x10, 2 agents", {"n": 10, "agents": 2, "rows": 3}),
]
QUICK = [("drone 6x6, 1 agent", {"n": 6, "agents": 1, "rows": 2})]
ENGINES = ("GMMXX", "TOPOLOGICAL", "NATIVE")
TARGET = 2.0


def write_drn(matrix, initial: int, decoy: np.ndarray, path: Path) -> None:
    """The chain as Storm's explicit DRN: a DTMC labelled ``init`` and ``decoy``."""
    matrix = matrix.tocsr()
    matrix.sort_indices()
    n = matrix.shape[0]
    labels = np.full(n, "", dtype=object)
    labels[decoy] = " decoy"
    labels[initial] += " init"
    entries = [
        f"\t\t{t} : {p!r}"
        for t, p in zip(matrix.indices.tolist(), matrix.data.tolist(), strict=True)
    ]
    ends = matrix.indptr[1:].tolist()
    lines = ["@type: DTMC", "@parameters", "", "@reward_models", "", "@nr_states", str(n)]
    lines += ["@nr_choices", str(n), "@model"]
    start = 0
    for q, stop in enumerate(ends):
        lines.append(f"state {q}{labels[q]}\n\taction 0")
        lines.extend(entries[start:stop])
        start = stop
    path.write_text("\n".join(lines) + "\n")


def chain_case(label: str, kwargs: dict, repeats: int) -> dict:
    """Our evaluation and Storm's model checking of one drone chain, interleaved."""
    from misdirect import evaluate
    from misdirect.core.evaluate import decoy_probability
    from misdirect.core.product import build_product
    from misdirect.scenarios.drone import drone

    began = time.perf_counter()
    problem = drone(**kwargs)
    build_s = time.perf_counter() - began
    identity = problem.identity()
    chain = build_product(problem, identity)
    report = evaluate(problem)
    row = {
        "case": label,
        "model": kwargs,
        "pomdp_states": problem.pomdp.n_states,
        "observations": problem.pomdp.n_observations,
        "product_states": chain.n_states,
        "product_transitions": chain.n_transitions,
        "model_build_s": build_s,
        "probability": report.probability,
        "error_bound": report.error_bound,
        "outcomes_nonzero": len(report.outcomes),
        "outcomes_all": len(report.all_outcomes),
        "never_absorbed": report.never_absorbed,
    }
    timers = {
        "evaluate_s": lambda: evaluate(problem),
        "probability_s": lambda: decoy_probability(problem, identity),
    }
    try:
        import stormpy
        from stormpy.developer import EquationSolverType
    except ImportError:
        stormpy = None
    if stormpy is not None:
        with tempfile.TemporaryDirectory() as scratch:
            path = Path(scratch) / "chain.drn"
            write_drn(chain.matrix, chain.initial, problem.decoy[chain.world_state], path)
            model = stormpy.build_model_from_drn(str(path))
        formula = stormpy.parse_properties('P=? [F "decoy"]')[0]
        initial = model.initial_states[0]
        environments = {"storm_default_s": stormpy.Environment()}
        for engine in ENGINES:
            environment = stormpy.Environment()
            environment.solver().set_linear_equation_solver_type(
                getattr(EquationSolverType, engine)
            )
            environments[f"storm_{engine.lower()}_s"] = environment
        for key, environment in environments.items():
            value = stormpy.model_checking(model, formula, environment=environment)
            row[key.replace("_s", "_difference")] = abs(
                value.get_value(initial) - row["probability"]
            )
            timers[key] = lambda env=environment: stormpy.model_checking(
                model, formula, environment=env
            )
    best = dict.fromkeys(timers, float("inf"))
    for _ in range(repeats):  # interleaved: a busy moment hurts every side alike
        for key, function in timers.items():
            started = time.perf_counter()
            function()
            best[key] = min(best[key], time.perf_counter() - started)
    row.update(best)
    if stormpy is not None:
        storm = {k: v for k, v in best.items() if k.startswith("storm_")}
        fastest = min(storm, key=storm.get)
        row["storm_fastest"] = fastest.removeprefix("storm_").removesuffix("_s")
        row["ratio_evaluate"] = best["evaluate_s"] / best["storm_default_s"]
        row["ratio_probability"] = best["probability_s"] / best["storm_default_s"]
        row["ratio_evaluate_fastest"] = best["evaluate_s"] / storm[fastest]
        row["pass"] = row["ratio_evaluate"] <= TARGET and row["ratio_probability"] <= TARGET
    row["peak_memory_gib"] = _peak_memory_gib()
    return row


def markdown(rows: list[dict], machine: str, quick: bool) -> str:
    lines = [f"Machine: {machine}." + (" Reduced (--quick) run." if quick else ""), ""]
    lines += [
        "| chain | POMDP states | observations | product states | transitions | "
        "evaluate (s) | probability only (s) | Storm default (s) | Storm fastest (s) | "
        "evaluate / Storm | probability / Storm | proven error | target <= 2 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        storm = r.get("storm_default_s")
        fastest = r.get("storm_fastest")
        fastest_s = r.get(f"storm_{fastest}_s") if fastest else None
        bound = "none proven" if r["error_bound"] is None else f"{r['error_bound']:.1e}"
        lines.append(
            f"| {r['case']} | {r['pomdp_states']:,} | {r['observations']:,} | "
            f"{r['product_states']:,} | {r['product_transitions']:,} | {r['evaluate_s']:.3f} | "
            f"{r['probability_s']:.3f} | "
            + (
                f"{storm:.3f} | {fastest_s:.3f} ({fastest}) | {r['ratio_evaluate']:.2f} | "
                f"{r['ratio_probability']:.2f} | {bound} | {'yes' if r['pass'] else '**no**'} |"
                if storm is not None
                else f"— | — | — | — | {bound} | not run |"
            )
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--quick", action="store_true", help="one small chain (CI)")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    machine = f"{platform.processor() or platform.machine()}, {multiprocessing.cpu_count()} cores"
    machine += f", Python {platform.python_version()}, {platform.system()}"
    rows = []
    for label, kwargs in QUICK if args.quick else CASES:
        row = _isolated(chain_case, label, kwargs, args.repeats)
        rows.append(row)
        print(json.dumps(row), flush=True)
    stem = args.out / "real_chains"
    stem.with_suffix(".json").write_text(
        json.dumps({"machine": machine, "quick": args.quick, "runs": rows}, indent=2)
    )
    keys = sorted({k for r in rows for k in r})
    with stem.with_suffix(".csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    text = markdown(rows, machine, args.quick)
    stem.with_suffix(".md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
