"""The fault matrix (:mod:`tests.fault_matrix`), every row in a process of its own:
a one-line error, or the recovered state, within the row's time bound."""

from __future__ import annotations

from typing import TYPE_CHECKING

import pytest

from tests.fault_matrix import FAULTS, make_inputs, run_fault

if TYPE_CHECKING:
    from pathlib import Path

    from tests.fault_matrix import Fault


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_inputs(tmp_path_factory.mktemp("fault_inputs"))


@pytest.mark.slow
@pytest.mark.parametrize("fault", FAULTS, ids=[f.name for f in FAULTS])
def test_fault_matrix(fault: Fault, inputs: Path, tmp_path: Path) -> None:
    outcome = run_fault(fault, inputs, tmp_path)
    assert outcome.passed, f"{fault.name}: {outcome.why}"


def test_the_matrix_names_each_row_once() -> None:
    names = [f.name for f in FAULTS]
    assert len(set(names)) == len(names)
    assert all(f.kind in ("cli", "api", "ok") for f in FAULTS)
    assert all(bool(f.argv) != bool(f.code) for f in FAULTS), "a row runs argv or code"
