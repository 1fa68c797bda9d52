"""The allocator catalog: docs/allocators.md is what ``platoon-opt allocators --markdown`` prints,
and the listing names every option of every registered allocator."""

from pathlib import Path

from platoon_opt.solvers import available_allocators
from platoon_opt.solvers.registry import registered
from platoon_opt.study import catalog
from platoon_opt.study.cli import main

DOCS = Path(__file__).resolve().parents[2] / "docs" / "allocators.md"


def test_docs_allocators_is_the_generated_catalog():
    regenerate = "platoon-opt allocators --markdown > docs/allocators.md"
    assert DOCS.read_text() == catalog.markdown(), regenerate


def test_the_listing_names_every_option(capsys):
    for name in available_allocators():
        assert main(["allocators", name]) == 0
        text = capsys.readouterr().out
        for option in registered(name).options:
            assert f"    {option.name} " in text, (name, option.name)


def test_an_unknown_allocator_is_one_line_and_exit_2(capsys):
    assert main(["allocators", "nope"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown allocator 'nope'; known: casadi-qp, cone" in err
