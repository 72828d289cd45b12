"""The README's claims are re-checked on every test run.

Each row of the README's accuracy table names, in its last column, the test that
re-measures that claim at a reduced size with its target as the assertion. Those tests
carry the `claims` marker and run in the default suite (so in CI); a row whose check is
too long for CI says `--slow` and names a slow-marked test. This file checks that the
table and the tests stay in step: a claim added to the README without a test, or a test
renamed or unmarked, fails here.
"""
import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TEST_ID = re.compile(r"`(test_\w+\.py)::(test_\w+)`")


def _section(text, heading):
    """The lines of one `## heading` section of a Markdown file."""
    lines = text.splitlines()
    start = lines.index(f"## {heading}")
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")), len(lines))
    return lines[start + 1:end]


def accuracy_rows():
    """(claim, result, checker cell) of every row of the README's accuracy table."""
    rows = []
    for line in _section((ROOT / "README.md").read_text(), "Accuracy"):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("|") or set(cells[0]) <= {"-"} or cells[0] == "check":
            continue
        rows.append((cells[0], cells[1], cells[-1]))
    return rows


def _marks(module_file, name):
    spec = importlib.util.spec_from_file_location(f"_claims_{module_file[:-3]}", ROOT / "test" / module_file)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    fn = getattr(module, name, None)
    assert fn is not None, f"{module_file}::{name} does not exist"
    return {m.name for m in getattr(fn, "pytestmark", [])}


def test_the_readme_has_an_accuracy_table_of_claims():
    rows = accuracy_rows()
    assert len(rows) >= 8, rows
    assert all(r[1] for r in rows)


@pytest.mark.parametrize("claim, result, checker", accuracy_rows(), ids=lambda v: str(v)[:40])
def test_every_readme_claim_names_the_test_that_rechecks_it(claim, result, checker):
    found = TEST_ID.findall(checker)
    assert found, f"README accuracy row {claim!r} names no test (`test_x.py::test_y`) in its last column"
    for module_file, name in found:
        marks = _marks(module_file, name)
        if "--slow" in checker:
            assert "slow" in marks, f"{module_file}::{name} is named as a --slow check but not marked slow"
        else:
            assert "claims" in marks, (f"{module_file}::{name} re-checks a README claim in CI "
                                       f"but is not marked claims (marks: {sorted(marks)})")
