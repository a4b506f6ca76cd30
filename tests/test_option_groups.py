"""The options' group table (``ChoiceProduct.group_of_option``) is stored per state over its
own observation's options; it must read exactly as the dense (states x options) table it
replaced, which these tests build independently, one entry of ``group_options`` at a time."""

from __future__ import annotations

import numpy as np
import pytest

from misdirect.core.alterations import alteration_space
from misdirect.core.choice_product import build_choice_product
from misdirect.core.memory import MEMORY_LIMIT_ENV
from misdirect.errors import ProblemError
from misdirect.scenarios import paper_grid
from misdirect.scenarios.random import random_problem


def dense_table(chain) -> np.ndarray:
    """The (Q, K) table by definition: a state with one group takes it whatever the option;
    otherwise option k selects the group whose ``group_options`` row holds k, else -1."""
    n_options = max(chain.options.size, 1)
    table = np.full((chain.n_states, n_options), -1, dtype=np.int64)
    groups_of = [[] for _ in range(chain.n_states)]
    for g, q in enumerate(chain.group_state.tolist()):
        groups_of[q].append(g)
    rows = chain.group_options.tolil().rows
    for q, groups in enumerate(groups_of):
        if len(groups) == 1:
            table[q, :] = groups[0]
            continue
        for g in groups:
            for k in rows[g]:
                table[q, k] = g
    return table


def chains():
    for seed in range(12):
        problem = random_problem(seed, states=7, observations=4, nodes=2)
        yield build_choice_product(problem, alteration_space(problem))
    problem = paper_grid(5)
    yield build_choice_product(problem, alteration_space(problem))


@pytest.mark.parametrize("chain", list(chains()), ids=lambda c: f"{c.n_states}states")
def test_the_table_reads_as_the_dense_one(chain):
    dense = dense_table(chain)
    table = chain.group_of_option
    assert table.shape == dense.shape
    every = np.arange(chain.n_states)
    rng = np.random.default_rng(chain.n_states)
    some = rng.choice(chain.n_states, size=max(1, chain.n_states // 2), replace=False)
    for k in range(dense.shape[1]):
        assert np.array_equal(table[:, k], dense[:, k])
        assert np.array_equal(table[some, k], dense[some, k])
        assert np.array_equal(table[some, np.int64(k)], dense[some, k])
    for lo in range(dense.shape[1]):
        for hi in (lo, lo + 1, lo + 3, dense.shape[1]):
            assert np.array_equal(table[some, lo:hi], dense[some, lo:hi])
            assert np.array_equal(table[every, lo:hi], dense[:, lo:hi])


@pytest.mark.parametrize("chain", list(chains()), ids=lambda c: f"{c.n_states}states")
def test_the_groups_a_choice_of_options_takes(chain):
    """Every state takes the highest group a chosen option selects there (the dense
    table's row maximum over the chosen columns), or its only group."""
    full = dense_table(chain)
    dense = full[:, : chain.options.size]
    rng = np.random.default_rng(7)
    for _ in range(20):
        chosen = rng.random(chain.options.size) < 0.3
        expected = np.where(chosen[None, :] & (dense >= 0), dense, -1).max(axis=1, initial=-1)
        single = np.bincount(chain.group_state, minlength=chain.n_states) == 1
        expected[single] = full[single, 0]
        assert np.array_equal(chain.groups_taking(chosen), expected)


def test_a_table_over_the_memory_limit_is_refused_with_its_size(monkeypatch):
    problem = paper_grid(5)
    chain = build_choice_product(problem, alteration_space(problem))
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "1")  # bytes
    with pytest.raises(ProblemError, match="table of the options' groups"):
        _ = chain.group_of_option
