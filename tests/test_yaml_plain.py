"""Problem files in YAML are built straight from the parser's events when they are plain (no
anchors, aliases, explicit tags or merge keys): the same document as the general loader's
(nodes, then PyYAML's safe constructor with our key rules), or the same refusal, on every
example, on generated models, and on the corner cases of YAML's scalars and keys."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from misdirect.errors import ProblemError
from misdirect.io import files
from misdirect.io.problem_file import write_problem
from misdirect.scenarios import drone, paper_grid, sensor_grid

ROOT = Path(__file__).resolve().parent.parent

SNIPPETS = {
    "scalars": "a: [1, -2, 0x1f, 010, 1_000, 1.5, 1e3, 1.0e3, .inf, -.Inf, .nan, ~, null, yes,"
    " No, true, 'quoted', \"010\", 2001-12-14, 2001-12-14t21:59:43.10-05:00, '', 0o17]",
    "keys as written": "010: a\n1: b\n1.50: c\ntrue: d\nnull: e\n2001-12-14: f\n'x': g\n",
    "block and flow": "m:\n  - {a: 1, b: [2, 3]}\n  - - 4\n    - 5\n  -\n",
    "empty": "",
    "scalar document": "just text",
    "comment only": "# nothing\n",
    "nested maps": "a: {b: {c: {d: [1, {e: 2}]}}}\n",
    "multi-line": "a: |\n  x\n  y\nb: >\n  z\n",
    "question mark key": "? k\n: v\n",
}
# the general way only: anchors, aliases, tags, merges, collections as keys
GENERAL = {
    "anchor": "a: &x 1\nb: *x\n",
    "tag": "a: !!str 1\n",
    "merge": "base: &b {x: 1}\nderived:\n  <<: *b\n  y: 2\n",
    "collection key": "? [1, 2]\n: v\n",
    "binary": "a: !!binary aGVsbG8=\n",
}
# refused either way, with the same message
BAD = {
    "duplicate": "a: 1\nb: 2\na: 3\n",
    "duplicate as text": '1: a\n"1": b\n',
    "deep": "a: " + "[" * 80 + "]" * 80 + "\n",
    "two documents": "a: 1\n---\nb: 2\n",
    "huge int": "a: " + "9" * 5000 + "\n",
    "broken": "a: [1, 2\n",
}


def _general(text: str):
    return files.BoundedSafeLoader(text).get_single_data()


def _texts() -> dict[str, str]:
    texts = dict(SNIPPETS)
    for path in sorted(
        [*(ROOT / "examples").glob("*.yaml"), *(ROOT / "tests/data").glob("*.yaml")]
    ):
        texts[path.name] = path.read_text()
    return texts


@pytest.mark.parametrize("name", list(_texts()))
def test_plain_documents_are_what_the_general_loader_builds(name):
    text = _texts()[name]
    fast = files.BoundedSafeLoader(text).plain_document()
    assert fast == _general(text)
    assert repr(fast) == repr(_general(text))  # WrittenInt, float and bool kinds alike


@pytest.mark.parametrize(
    "make",
    [lambda: paper_grid(6), lambda: sensor_grid(8, 6, goal="inside"), lambda: drone(5, agents=1)],
)
def test_generated_models_written_as_yaml_read_back_the_same(make, tmp_path):
    path = tmp_path / "model.yaml"
    write_problem(make(), path)
    text = path.read_text()
    assert files.BoundedSafeLoader(text).plain_document() == yaml.safe_load(text)


@pytest.mark.parametrize("name", list(GENERAL))
def test_documents_with_anchors_tags_or_merges_go_the_general_way(name):
    text = GENERAL[name]
    with pytest.raises(files._NotPlainError):
        files.BoundedSafeLoader(text).plain_document()
    if name != "collection key":  # unhashable: the general way refuses it
        assert files.parse_yaml(text, source="f.yaml") == _general(text)


@pytest.mark.parametrize("name", list(BAD))
def test_bad_documents_are_refused_with_the_general_loaders_message(name, monkeypatch):
    text = BAD[name]
    with pytest.raises(ProblemError) as fast:
        files.parse_yaml(text, source="f.yaml")

    def never_plain(self):
        raise files._NotPlainError

    monkeypatch.setattr(files.BoundedSafeLoader, "plain_document", never_plain)
    with pytest.raises(ProblemError) as general:
        files.parse_yaml(text, source="f.yaml")
    assert str(fast.value) == str(general.value)
