"""Storm's sparse model as numpy arrays, read in bulk.

stormpy has no array accessor for the transition matrix, and reading it entry by entry is a
Python loop per transition. So the model is written once as a UMB archive (Storm's binary
format: CSR arrays, one file each) and read back with numpy; nothing on this path loops in
Python per state, choice or transition. :func:`read_arrays_slowly` reads the same arrays
through stormpy's per-entry accessors, for a stormpy without UMB export.
"""

from __future__ import annotations

import itertools
import json
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import IO, cast

import numpy as np

from misdirect.errors import ProblemError
from misdirect.io.storm_names import NO_LABEL


@dataclass(frozen=True)
class StormArrays:
    """The sparse model as arrays: CSR with row groups (choices of a state)."""

    groups: np.ndarray  # (|S|+1,) first choice of each state
    rows: np.ndarray  # (|choices|+1,) first entry of each choice
    target: np.ndarray  # (entries,)
    probability: np.ndarray  # (entries,)
    action: np.ndarray  # (|choices|,) action index
    actions: tuple[str, ...]
    observation_of: np.ndarray  # (|S|,)
    initial: np.ndarray  # state indices
    # variables in Storm's order (UMB index), for names; empty when unknown
    state_variables: tuple[str, ...] = ()
    observation_variables: tuple[str, ...] = ()


def model_arrays(stormpy, model) -> StormArrays:
    """The model's arrays: in bulk through UMB, or entry by entry where stormpy has no UMB."""
    try:
        return read_arrays(stormpy, model)
    except (AttributeError, KeyError):  # stormpy < 2.0 has no UMB export
        return read_arrays_slowly(model)


def _bits(data: bytes, n: int) -> np.ndarray:
    return np.unpackbits(np.frombuffer(data, dtype=np.uint8), bitorder="little")[:n].astype(bool)


def read_arrays(stormpy, model) -> StormArrays:
    """Write the model as UMB (binary CSR arrays) and read the arrays back with numpy."""
    options = stormpy.io.UmbExportOptions()
    options.compression = stormpy.io.CompressionMode.NO_COMPRESSION
    options.canonicize_pomdp = False  # keep Storm's state and observation numbering
    with tempfile.TemporaryDirectory(prefix="misdirect-") as folder:
        archive = Path(folder) / "model.umb"
        stormpy.io.export_to_umb(model, str(archive), options=options)
        with tarfile.open(archive) as tar:
            files = {
                # a regular member always has a file object (typeshed: Optional)
                m.name: cast(IO[bytes], tar.extractfile(m)).read()
                for m in tar.getmembers()
                if m.isfile()
            }
    n_states, n_choices = model.nr_states, model.nr_choices

    def array(name: str, dtype: str) -> np.ndarray:
        data = np.frombuffer(files[name], dtype=np.dtype(dtype).newbyteorder("<"))
        if dtype == "f8":
            return data.astype(np.float64, copy=False)
        if dtype == "u8":  # indices < 2**63: the same bytes read as int64, no copy
            return data.view(np.dtype("<i8")).astype(np.int64, copy=False)
        return data.astype(np.int64)

    index = json.loads(files["index.json"])
    kind = index["transition-system"].get("branch-probability-type", {}).get("type", "double")
    if kind != "double":
        raise ProblemError(f"Storm exported {kind} probabilities; misdirect reads doubles")
    if "actions/choices/values.bin" in files:
        strings, offsets = (
            files["actions/choices/strings.bin"],
            array("actions/choices/string-mapping.bin", "u8"),
        )
        names = [
            strings[a:b].decode("utf-8") or NO_LABEL
            for a, b in itertools.pairwise(offsets.tolist())
        ]
        used, action = np.unique(array("actions/choices/values.bin", "u4"), return_inverse=True)
        actions = tuple(names[i] for i in used)
    else:
        action, actions = np.zeros(n_choices, dtype=np.int64), (NO_LABEL,)
    if len(set(actions)) != len(actions):  # two strings mapping to the same name
        unique, action = np.unique(np.array(actions)[action], return_inverse=True)
        actions = tuple(unique.tolist())

    def order(entity: str) -> tuple[str, ...]:
        classes = index.get("valuations", {}).get(entity, {}).get("classes", [])
        if len(classes) != 1:
            return ()
        return tuple(v["name"] for v in classes[0].get("variables", []) if "name" in v)

    return StormArrays(
        state_variables=order("states"),
        observation_variables=order("observations"),
        groups=array("state-to-choices.bin", "u8"),
        rows=array("choice-to-branches.bin", "u8"),
        target=array("branch-to-target.bin", "u8"),
        probability=array("branch-to-probability.bin", "f8"),
        action=action.astype(np.int64),
        actions=actions,
        observation_of=(
            array("observations/states/values.bin", "u8")
            if "observations/states/values.bin" in files
            else np.array(model.observations, dtype=np.int64)
        ),
        initial=np.flatnonzero(_bits(files["state-is-initial.bin"], n_states)),
    )


def read_arrays_slowly(model) -> StormArrays:
    """The same arrays through stormpy's per-entry accessors (stormpy without UMB)."""
    groups = np.array(model.nondeterministic_choice_indices, dtype=np.int64)
    labelling = model.choice_labeling if model.has_choice_labeling() else None
    index: dict[str, int] = {}
    action, rows, target, probability = [], [0], [], []
    for choice in range(model.nr_choices):
        labels = sorted(labelling.get_labels_of_choice(choice)) if labelling else []
        action.append(index.setdefault("+".join(labels) or NO_LABEL, len(index)))
        for entry in model.transition_matrix.get_row(choice):
            target.append(entry.column)
            probability.append(float(entry.value))
        rows.append(len(target))
    return StormArrays(
        groups=groups,
        rows=np.array(rows, dtype=np.int64),
        target=np.array(target, dtype=np.int64),
        probability=np.array(probability),
        action=np.array(action, dtype=np.int64),
        actions=tuple(index),
        observation_of=np.array(model.observations, dtype=np.int64),
        initial=np.array(sorted(model.initial_states), dtype=np.int64),
    )
